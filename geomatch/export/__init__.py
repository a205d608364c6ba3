"""Exports of a run's model for other tools: ``geomatch export`` and the service's model formats.

A run folder (``geomatch run`` / ``geomatch demo``, or the service's model folder) holds the
model in ``sparse/0`` and, beside it or elsewhere, the COLMAP database and the images. Each
format is one module with one ``write(source, dest)`` and one row of ``formats.FORMATS`` (what it
reads, its help, its media type and proto number); this module finds the inputs, writes
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
from pathlib import Path

from .formats import DATABASE, FORMATS, IMAGES, ExportFormat
from .source import ExportError, Source

__all__ = [
    "FORMATS",
    "ExportError",
    "ExportFormat",
    "Source",
    "export",
    "export_zip",
    "model_dir",
    "open_run",
]


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


def _check(source: Source, fmt: str) -> ExportFormat:
    row = FORMATS.get(fmt)
    if row is None:
        raise ExportError(f"unknown export format {fmt!r}; choose from {', '.join(FORMATS)}")
    if IMAGES in row.needs and (source.images is None or not source.images.is_dir()):
        where = f" ({source.images} is not a folder)" if source.images is not None else ""
        raise ExportError(f"the {fmt} export needs the run's images{where}: pass --images DIR")
    if DATABASE in row.needs and source.database is None:
        raise ExportError(f"the {fmt} export needs the run's COLMAP database (database.db)")
    return row


def export(source: Source, fmt: str, dest: str | Path) -> list[Path]:
    """Write ``fmt`` into the folder ``dest`` (replaced whole); returns the files written there."""
    write = _check(source, fmt).load()
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(f".{dest.name}-{uuid.uuid4().hex[:8]}")
    tmp.mkdir()  # not mkdtemp: its mode 0700 would stay on the renamed folder
    try:
        written = write(source, tmp)
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
