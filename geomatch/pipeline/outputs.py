"""What a run leaves in its output folder besides the model, the database and the plan: the run's
summary, and on request one archive of the model for download. The model's formats for other tools
are geomatch.export's."""

from __future__ import annotations

import json
import math
import zipfile
from pathlib import Path
from typing import Any

from ..report import survey_report


def finite(value: Any) -> Any:
    """``value`` (a summary: dicts, lists, numbers, text) with every NaN or infinite number as
    None: JSON has no NaN, and a number a stage could not measure is unknown, which null says."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite(v) for v in value]
    return value


def finish(out: Path, summary: dict[str, Any], archive: bool = False) -> dict[str, Any]:
    """The run's summary made final (finite numbers, the survey report) and written once:
    ``out/summary.json``, and with ``archive`` ``out/model.zip``; returns it."""
    summary = finite(summary)  # summary.json and a job's stored result: JSON, no NaN
    summary["report"] = survey_report(summary)
    write_outputs(out, summary, archive)
    return summary


def write_outputs(out: Path, summary: dict[str, Any], archive: bool = False) -> None:
    """``out/summary.json``; ``archive``: also ``out/model.zip`` (sparse/<i>/, COLMAP binary, and
    text for sparse/0; points.ply; summary.json)."""
    (out / "summary.json").write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n")
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
