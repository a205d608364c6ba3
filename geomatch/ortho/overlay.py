"""What the console draws on the map's preview: the registered cameras and the ground control
points, at their places on it (fractions of its width and height from the top-left corner, so a
page draws them at any size without knowing the CRS).

GCPs are where the survey put them (the GCP file beside the run, in its metric frame, which is
the map's CRS for a GCP model), with the role the fit gave each (control, check, unused): a check
point's marker beside the target it stands on in the picture shows the map's error by eye.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ..geo.gcpfile import GcpError, read_gcp_file
from .grid import Grid
from .survey import Survey

GCP_FILE = "gcp_list.txt"


def _place(grid: Grid, e: float, n: float) -> tuple[float, float] | None:
    w, s, east, north = grid.bounds
    x, y = (e - w) / (east - w), (north - n) / (north - s)
    return (round(x, 5), round(y, 5)) if 0 <= x <= 1 and 0 <= y <= 1 else None


def gcp_places(run: Path, survey: Survey, grid: Grid) -> list[dict[str, Any]]:
    """The GCP file's points on the map (GCP models only: their frame is the map's CRS)."""
    path = run / GCP_FILE
    summary_path = run / "summary.json"
    if survey.frame.kind != "GCP" or not path.is_file() or not summary_path.is_file():
        return []
    sizes = {v.name: (v.width, v.height) for v in survey.views}
    try:
        gcps = read_gcp_file(path.read_text(), sizes)
    except GcpError:
        return []
    roles = {
        p["name"]: p.get("role")
        for p in (json.loads(summary_path.read_text()).get("gcp") or {}).get("points", [])
    }
    out = []
    for name, point in sorted(gcps.points.items()):
        at = _place(grid, float(point.xyz[0]), float(point.xyz[1]))
        if at is not None:
            out.append({"name": name, "role": roles.get(name, "unused"), "x": at[0], "y": at[1]})
    return out


def overlay(run: Path, survey: Survey, grid: Grid) -> dict[str, Any]:
    """Cameras and GCPs as fractions of the map's extent (``grid``: the orthophoto's)."""
    cams = []
    for v in survey.views:
        at = _place(grid, float(v.centre[0]), float(v.centre[1]))
        if at is not None:
            cams.append({"name": v.name, "x": at[0], "y": at[1]})
    return {"cameras": cams, "gcps": gcp_places(run, survey, grid)}
