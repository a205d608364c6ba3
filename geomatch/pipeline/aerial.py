"""Which images of a project are aerial and which were taken on the ground: as the caller says (a
list, a glob) or, left to the image, by its metadata, and for a drone survey whose photos say
nothing by the track of their GPS fixes."""

from __future__ import annotations

import fnmatch
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from ..geo import survey
from ..imagefolder import PipelineError
from ..metadata import ImageMeta


def captures(
    names: Sequence[str], aerial_names: Sequence[str] | None = None, aerial_glob: str | None = None
) -> dict[str, str]:
    """How each image was taken (aerial, ground, auto), as ``geomatch run`` is told: an explicit
    list of aerial images, or a glob over the relative path or the file name, makes every image
    aerial or ground; neither leaves each to its metadata (auto)."""
    if aerial_names is not None:
        unknown = sorted(set(aerial_names) - set(names))
        if unknown:
            raise PipelineError(f"aerial list names images not in the folder: {', '.join(unknown[:5])}")
        chosen = set(aerial_names)
        return {n: "aerial" if n in chosen else "ground" for n in names}
    if aerial_glob is not None:
        return {
            n: "aerial"
            if fnmatch.fnmatch(n, aerial_glob) or fnmatch.fnmatch(Path(n).name, aerial_glob)
            else "ground"
            for n in names
        }
    return {n: "auto" for n in names}


def aerial_set(
    captures: Mapping[str, str],
    metas: Mapping[str, ImageMeta],
    enu: Mapping[str, np.ndarray] | None = None,
) -> set[str]:
    """The aerial images: those captured ``aerial``, and those ``auto`` whose EXIF/XMP says so
    (silent metadata means ground). ``metas`` is read for the ``auto`` images only.

    A drone survey whose camera writes GPS but no XMP (a compact camera on a drone) says nothing
    per photo, but its track does: when every image is ``auto``, none says it is on the ground,
    none says it is aerial, and the GPS fixes (``enu``) in capture order trace a survey flight
    (geomatch.geo.survey.is_survey_track), every image of the project is aerial. ``--aerial``
    (a glob or list, even one that matches nothing) decides instead."""
    out = {n for n, c in captures.items() if c == "aerial" or (c == "auto" and metas[n].aerial_hint)}
    if (
        not out
        and enu
        and all(c == "auto" for c in captures.values())
        and all(metas[n].aerial_hint is None for n in captures)
        and survey.is_survey_track(list(captures), enu)
    ):
        return set(captures)
    return out
