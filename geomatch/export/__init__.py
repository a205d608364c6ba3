"""Exports of a run's model for other tools: ``geomatch export`` and the service's model formats.

A run folder (``geomatch run`` / ``geomatch demo``, or the service's model folder) holds the
model in ``sparse/0`` and, beside it or elsewhere, the COLMAP database and the images. Each
format is one module with one ``write(source, dest)``; this module finds the inputs, writes
into a temporary sibling of ``dest`` and renames it into place, so a reader never sees half an
export, and zips an export for the service. Nothing here imports torch (the service's API
process builds the exports it serves), which is why hloc reads the database with pycolmap
rather than through colmapdb.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import uuid
import zipfile
from collections.abc import Callable
from pathlib import Path

from ..options import EXPORT_FORMATS as FORMATS
from .source import ExportError, Source

__all__ = ["FORMATS", "ExportError", "Source", "export", "export_zip", "model_dir", "open_run"]

# what each format reads besides the model: the images (nerfstudio copies them, openmvs
# undistorts them) or the database (hloc's keypoints and matches)
NEEDS_IMAGES = frozenset({"nerfstudio", "openmvs"})
NEEDS_DATABASE = frozenset({"hloc"})


def model_dir(run: Path) -> Path:
    """The largest model of a run (``sparse/0``, as sfm.reconstruct ranks them)."""
    return run / "sparse" / "0"


def open_run(run: str | Path, images: str | Path | None = None, database: str | Path | None = None) -> Source:
    """The inputs of a run folder; ``images`` defaults to the folder the run read (``image_dir``
    of summary.json), ``database`` to the run's ``database.db``."""
    run = Path(run)
    model = model_dir(run)
    if not (model / "images.bin").is_file():
        if not (run / "summary.json").is_file():
            raise ExportError(f"{run} is not a run folder (no summary.json): make one with `geomatch run`")
        raise ExportError(f"{run} has no model ({model} is missing: no image was registered)")
    summary = run / "summary.json"
    if images is None:
        recorded = json.loads(summary.read_text()).get("image_dir") if summary.is_file() else None
        images = Path(recorded) if recorded else None
    db = Path(database) if database is not None else run / "database.db"
    return Source(
        model=model,
        database=db if db.is_file() else None,
        images=Path(images) if images is not None else None,
        summary=summary if summary.is_file() else None,
    )


def _check(source: Source, fmt: str) -> None:
    if fmt not in FORMATS:
        raise ExportError(f"unknown export format {fmt!r}; choose from {', '.join(FORMATS)}")
    if fmt in NEEDS_IMAGES and (source.images is None or not source.images.is_dir()):
        where = f" ({source.images} is not a folder)" if source.images is not None else ""
        raise ExportError(f"the {fmt} export needs the run's images{where}: pass --images DIR")
    if fmt in NEEDS_DATABASE and source.database is None:
        raise ExportError(f"the {fmt} export needs the run's COLMAP database (database.db)")


def _writer(fmt: str) -> Callable[[Source, Path], list[Path]]:
    # imported on use: each format pulls only what it needs (h5py for hloc)
    if fmt == "nerfstudio":
        from . import nerfstudio as m
    elif fmt == "colmap-text":
        from . import colmap_text as m  # type: ignore[no-redef]  # one name, whichever format's module
    elif fmt == "ply":
        from . import ply as m  # type: ignore[no-redef]  # ditto
    elif fmt == "hloc":
        from . import hloc as m  # type: ignore[no-redef]  # ditto
    else:
        from . import openmvs as m  # type: ignore[no-redef]  # ditto
    return m.write


def export(source: Source, fmt: str, dest: str | Path) -> list[Path]:
    """Write ``fmt`` into the folder ``dest`` (replaced whole); returns the files written there."""
    _check(source, fmt)
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(f".{dest.name}-{uuid.uuid4().hex[:8]}")
    tmp.mkdir()  # not mkdtemp: its mode 0700 would stay on the renamed folder
    try:
        written = _writer(fmt)(source, tmp)
        old = dest.with_name(f".old-{dest.name}-{uuid.uuid4().hex[:8]}")
        if dest.exists():
            os.replace(dest, old)
        os.replace(tmp, dest)
        shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return [dest / p.relative_to(tmp) for p in written]


def export_zip(source: Source, fmt: str, zip_path: str | Path) -> Path:
    """The export as one zip at ``zip_path`` (with the run's summary.json at its root, so the
    archive says which model it came from); written beside and renamed, so never half there."""
    zip_path = Path(zip_path)
    zip_path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".export-", dir=zip_path.parent) as work:
        folder = Path(work) / fmt
        export(source, fmt, folder)
        part = Path(work) / "export.zip"
        with zipfile.ZipFile(part, "w", zipfile.ZIP_DEFLATED) as z:
            for f in sorted(folder.rglob("*")):
                if f.is_file():
                    z.write(f, f.relative_to(folder).as_posix())
            if source.summary is not None and not (folder / "summary.json").exists():
                z.write(source.summary, "summary.json")
        os.replace(part, zip_path)
    return zip_path
