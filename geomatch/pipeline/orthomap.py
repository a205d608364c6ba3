"""The map after the mapping (geomatch.ortho: a DSM and an orthophoto of a georeferenced model),
for both runners: ``geomatch run --ortho`` and a reconstruct job with ``ortho`` on.

The map reads the model as its folder has it (summary.json says its frame), so the summary is
written once before, and its record goes into the summary that ``outputs.finish`` then writes. A
model that cannot have a map (not georeferenced) gets ``ortho.skipped`` with why, and so does a
map that failed: the model is the run's product and stands without one.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..ortho import map_step
from .outputs import finite, write_outputs

log = logging.getLogger(__name__)


def add_map(
    out: Path,
    summary: dict[str, Any],
    images: Path,
    ortho: str,
    gsd: float = 0.0,
    explain: Callable[[Exception], str] = repr,
) -> dict[str, Any]:
    """``summary`` with ``ortho`` (the map's record, or why there is none) when ``ortho`` is on,
    the map's files in ``out``; ``gsd`` 0: the survey's; ``explain``: a failure as a user reads
    it (the service takes its server's paths out)."""
    if ortho != "on":
        return summary
    t0 = time.perf_counter()
    write_outputs(out, finite(summary))  # what the map reads: the model's frame
    try:
        record = map_step(out, images, gsd or None)
    except Exception as e:  # the model stays good: the summary says what went wrong
        log.warning("the map failed: %r", e)
        record = {"skipped": f"the map failed ({explain(e)})"}
    timings = {**summary.get("timings", {}), "map": time.perf_counter() - t0}
    return {**summary, "ortho": record, "timings": timings}
