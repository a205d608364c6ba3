"""Localize new photos against a project's model, without mapping the project again.

:func:`localize_photos` is the entry point: it opens the project (:class:`Project`, project.py:
its layouts), localizes each photo (:class:`Localizer`, localizer.py: candidates, matching, 2D-3D
lifting, pose), judges the answer (:func:`judge`, answer.py: localized or not, and how confident)
and, when asked, adds the photo to the project (:func:`add_to_project`, add.py).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from ..options import DEFAULTS
from .add import add_to_project
from .answer import Localization, LocalizeOptions, describe, judge
from .localizer import QUERY, Evidence, Localizer
from .project import LocalizeError, Project, project_matcher

__all__ = [
    "QUERY",
    "Evidence",
    "Localization",
    "LocalizeError",
    "LocalizeOptions",
    "Localizer",
    "Project",
    "add_to_project",
    "describe",
    "judge",
    "localizations_json",
    "localize_photos",
    "project_matcher",
]


def localize_photos(
    project_dir: Path,
    photos: Sequence[Path],
    options: LocalizeOptions | None = None,
    matcher: Any = None,
    add: bool = False,
    progress: Callable[[int, int], None] | None = None,
    *,
    model_dir: Path | None = None,
    images_dir: Path | None = None,
) -> list[Localization]:
    """Each photo's pose in the project's model (one :class:`Localization` per photo, in order).

    ``matcher``: the project's (a service passes its own, with its feature store); default: the
    one the run recorded. ``add``: also put the photos into the project (:func:`add_to_project`).
    ``progress(done, total)`` is called after each photo. ``model_dir`` / ``images_dir``: where
    the model and the images are when the project's layout does not say (see project.py's
    docstring). The model's aerial images are those its summary or their metadata name (a caller
    that knows better builds its own :class:`Localizer`)."""
    project = Project.find(Path(project_dir), model_dir, images_dir)
    localizer = Localizer(project, options or LocalizeOptions(), matcher)
    snap = float(project.run_options.get("snap_radius", DEFAULTS["snap_radius"]))
    results = []
    for k, photo in enumerate(photos):
        result, evidence = localizer.localize(Path(photo))
        if add and evidence is not None:
            add_to_project(project, Path(photo), evidence, localizer.matcher, snap)
        results.append(result)
        if progress is not None:
            progress(k + 1, len(photos))
    return results


def localizations_json(results: Sequence[Localization]) -> dict[str, Any]:
    """The one JSON document of ``geomatch localize --json``."""
    return {
        "photos": [r.to_json() for r in results],
        "localized": sum(r.localized for r in results),
        "total": len(results),
    }
