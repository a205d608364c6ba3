"""The map of a run (``geomatch ortho``, ``geomatch run --ortho``, a reconstruct job with ``ortho``)
as exports: ``orthophoto`` and ``dsm`` are the files the map step wrote into the run folder, at
OpenDroneMap's places (``odm_orthophoto/odm_orthophoto.tif``, ``odm_dem/dsm.tif``), which is also
where the ``odm`` export puts them, so that WebODM finds a task's map where ODM leaves it.

Building the map is not an export's work (minutes over the photos, in a worker or the run): an
export of a run without one says how to make it.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from .source import ExportError, Source

ORTHOPHOTO = Path("odm_orthophoto") / "odm_orthophoto.tif"
DSM = Path("odm_dem") / "dsm.tif"
PREVIEW = Path("odm_orthophoto") / "preview.png"
MAKE_IT = "make it with `geomatch ortho OUT` (or `geomatch run --ortho`, or a reconstruct job with ortho)"


def run_folder(source: Source) -> Path | None:
    """The folder the map lies in: beside the run's summary.json."""
    return source.summary.parent if source.summary is not None else None


def map_files(source: Source) -> list[Path]:
    """The map's files the run has, relative to the run folder (ORTHOPHOTO, DSM, PREVIEW)."""
    run = run_folder(source)
    if run is None:
        return []
    return [rel for rel in (ORTHOPHOTO, DSM, PREVIEW) if (run / rel).is_file()]


def copy_map(source: Source, dest: Path) -> list[Path]:
    """The run's orthophoto and DSM copied into ``dest`` at the same relative places (ODM's)."""
    run = run_folder(source)
    out = []
    for rel in (r for r in map_files(source) if r != PREVIEW):
        assert run is not None
        (dest / rel).parent.mkdir(parents=True, exist_ok=True)
        out.append(Path(shutil.copyfile(run / rel, dest / rel)))
    return out


def _one(source: Source, dest: Path, rel: Path, what: str) -> list[Path]:
    if rel not in map_files(source):
        raise ExportError(f"the run has no {what}: {MAKE_IT}")
    run = run_folder(source)
    assert run is not None
    dest.mkdir(parents=True, exist_ok=True)
    return [Path(shutil.copyfile(run / rel, dest / rel.name))]


def write_orthophoto(source: Source, dest: Path) -> list[Path]:
    return _one(source, dest, ORTHOPHOTO, "orthophoto")


def write_dsm(source: Source, dest: Path) -> list[Path]:
    return _one(source, dest, DSM, "DSM")


def write_preview(source: Source, dest: Path) -> list[Path]:
    return _one(source, dest, PREVIEW, "map preview")
