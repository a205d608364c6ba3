"""``stats.json``: the model's statistics in the shape of ODM's ``odm_report/stats.json`` (the keys
WebODM and ODM's own report read: ``processing_statistics``, ``reconstruction_statistics``,
``gps_errors``, ``gcp_errors``, ``point_cloud_statistics``), built from the run's summary and its
survey report (``geomatch.report``), with the report itself under ``geomatch_report``."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ..report import survey_report


def _rmse_block(rmse_h: Any, rmse_3d: Any) -> dict[str, Any]:
    return {"average_error": rmse_3d, "horizontal_rmse": rmse_h, "rmse_3d": rmse_3d}


def stats_json(summary: Mapping[str, Any]) -> dict[str, Any]:
    report = summary.get("report") or survey_report(summary)
    photos, model, geo = report["photos"], report["model"], report["georeferencing"]
    timings = report.get("timings_s", {})
    gcp = geo.get("gcp") or {}
    out: dict[str, Any] = {
        "processing_statistics": {
            "steps_times": dict(timings),
            "total_time": timings.get("total"),
        },
        "reconstruction_statistics": {
            "components": model.get("models"),
            "has_gps": bool(photos.get("with_gps")),
            "has_gcp": bool(gcp.get("points")) and "error" not in gcp,
            "initial_shots_count": photos.get("images"),
            "reconstructed_shots_count": photos.get("registered"),
            "reconstructed_points_count": model.get("points3D"),
            "observations_count": model.get("observations"),
            "average_track_length": model.get("mean_track_length"),
            "reprojection_error_pixels": model.get("mean_reprojection_error_px"),
        },
        "point_cloud_statistics": {"dense": False, "stats": {"points": model.get("points3D")}},
        "geomatch_report": report,
    }
    gps = geo.get("gps")
    if gps:
        out["gps_errors"] = {
            "average_error": gps.get("median_m"),
            "rmse": gps.get("rmse_m"),
            "max_inlier": gps.get("max_inlier_m"),
        }
    if gcp and "error" not in gcp:
        out["gcp_errors"] = {
            "control": _rmse_block(gcp.get("control_rmse_horizontal_m"), gcp.get("control_rmse_3d_m")),
            "check": _rmse_block(gcp.get("check_rmse_horizontal_m"), gcp.get("check_rmse_3d_m")),
        }
    return out


def finite(value: Any) -> Any:
    """``value`` with NaN and infinities as None: JSON has no spelling for them, and summary.json
    (Python's JSON) may hold them."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Mapping):
        return {str(k): finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite(v) for v in value]
    return value


def write_stats(path: Path, summary: Mapping[str, Any]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(finite(stats_json(summary)), indent=1, allow_nan=False, default=str))
    return path
