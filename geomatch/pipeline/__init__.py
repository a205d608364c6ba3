"""The pipeline: a project's photos to a sparse model, one module per stage, which both runners
call: ``geomatch run`` in one process (runner.py) and the service's job steps, queued
(workers/jobs.py).

- aerial.py: which images are aerial; prepare.py: the photos read, the plan made (plan.py, from the
  pairings of pair_sources.py and retrieval.py, a survey's quarter turns in turns.py) and the
  images registered;
- match_pairs.py: one planned pair's features, matches and write; database.py: the project's
  COLMAP database as the stages fill it;
- reconstruction.py: the model, georeferenced; orthomap.py: a survey's map; outputs.py:
  summary.json (its fields: summary.py) and the model's archive.

``run`` and ``RunOptions`` load on first use: importing a stage does not load the runner's
dependencies.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .runner import RunOptions, run

__all__ = ["RunOptions", "run"]


def __getattr__(name: str) -> Any:
    if name not in __all__:
        raise AttributeError(f"module 'geomatch.pipeline' has no attribute {name!r}")
    value = getattr(import_module(".runner", __name__), name)
    globals()[name] = value
    return value
