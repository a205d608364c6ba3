"""What a run leaves in its output folder besides the model and the database: the run's summary,
and on request one archive of the model for download. The model's formats for other tools are
geomatch.export's."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path
from typing import Any


def write_outputs(out: Path, summary: dict[str, Any], archive: bool = False) -> None:
    """``out/summary.json``; ``archive``: also ``out/model.zip`` (sparse/<i>/, COLMAP binary, and
    text for sparse/0; points.ply; summary.json)."""
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    if not archive:
        return
    tmp = out / "model.zip.tmp"
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
        for f in sorted((out / "sparse").rglob("*")):
            if f.is_file():
                z.write(f, f.relative_to(out).as_posix())
        for name in ("points.ply", "summary.json"):
            if (out / name).is_file():
                z.write(out / name, name)
    tmp.rename(out / "model.zip")
