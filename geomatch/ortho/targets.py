"""Ground control points measured on the orthophoto: each target found near where the model put
its point, so that the survey report can give the check points' residuals on the map itself
(what a surveyor checks a map by), beside the model's.

A target is what drone surveys lay out: a dark square, 0.3-1 m, with a light cross or
checkerboard on it. Near each point (``SEARCH_M`` around the model's place of it: the surveyed
place plus the point's residual) the very dark pixels are closed over the light cross into one
blob; a blob of a target's size with light pixels inside is the target, its centre the point. A
point whose target is not found (none laid out, hidden, too small at the map's GSD) is reported
as not found, never guessed.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import rasterio
from rasterio.windows import Window

from ..geo.gcpfile import GcpError, GcpFile, read_gcp_file

SEARCH_M = 1.5
TARGET_M = (0.2, 1.2)  # a target's side
DARK, LIGHT = 45, 170  # grey levels of the square and of its cross


def find_target(rgba: np.ndarray, res: float) -> tuple[float, float] | None:
    """The centre (col, row) of the target nearest the window's centre, or None."""
    grey = cv2.cvtColor(np.ascontiguousarray(rgba[..., :3]), cv2.COLOR_RGB2GRAY)
    dark = ((grey < DARK) & (rgba[..., 3] > 0)).astype(np.uint8)
    k = max(3, round(0.12 / res))  # closes a cross up to ~12 cm wide
    closed = cv2.morphologyEx(dark, cv2.MORPH_CLOSE, np.ones((k, k), np.uint8))
    n, _, stats, centres = cv2.connectedComponentsWithStats(closed)
    lo, hi = TARGET_M[0] / res, TARGET_M[1] / res
    mid = np.array([rgba.shape[1], rgba.shape[0]]) / 2
    best: tuple[float, np.ndarray] | None = None
    for i in range(1, n):
        x, y, w, h, area = (int(v) for v in stats[i])
        if not (lo <= w <= hi and lo <= h <= hi and area >= 0.25 * w * h and 0.5 <= w / h <= 2.0):
            continue
        if (grey[y : y + h, x : x + w] > LIGHT).mean() < 0.03:  # no cross: a shadow, a dark bush
            continue
        d = float(np.hypot(*(centres[i] - mid)))
        if best is None or d < best[0]:
            best = (d, centres[i])
    return None if best is None else (float(best[1][0]), float(best[1][1]))


def gcp_targets(ortho: Path, gcps: GcpFile, fit: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Each point of ``fit`` (summary.json's ``gcp``) with a residual, found on the orthophoto
    (in the GCP frame, the map's CRS): where the map has it against the model and the survey."""
    out = []
    with rasterio.open(ortho) as src:
        t = src.transform
        res = float(t.a)
        half = round(SEARCH_M / res)
        for p in fit.get("points", []):
            point = gcps.points.get(p["name"])
            if point is None or "dx_m" not in p:
                continue
            sx, sy = float(point.xyz[0]), float(point.xyz[1])
            mx, my = sx + float(p["dx_m"]), sy + float(p["dy_m"])  # where the model put it
            col, row = round((mx - t.c) / res), round((my - t.f) / t.e)
            window = Window(col - half, row - half, 2 * half, 2 * half)
            rgba = np.moveaxis(src.read(window=window, boundless=True), 0, -1)
            found = find_target(rgba, res) if rgba.shape[-1] == 4 else None
            row_out: dict[str, Any] = {"name": p["name"], "role": p.get("role"), "found": found is not None}
            if found is not None:
                fe = t.c + (col - half + found[0] + 0.5) * res
                fn = t.f + (row - half + found[1] + 0.5) * t.e
                row_out["map_vs_model_m"] = round(float(np.hypot(fe - mx, fn - my)), 4)
                row_out["map_vs_survey_m"] = round(float(np.hypot(fe - sx, fn - sy)), 4)
            out.append(row_out)
    return out


def check_summary(rows: list[dict[str, Any]], fit: Mapping[str, Any]) -> dict[str, Any]:
    """The check points' horizontal RMSE on the map beside the model's (summary.json's ``gcp``)."""
    check = [r for r in rows if r["role"] == "check" and r["found"]]
    out: dict[str, Any] = {
        "points": rows,
        "found": sum(r["found"] for r in rows),
        "model_check_rmse_horizontal_m": fit.get("check_rmse_horizontal_m"),
    }
    if check:
        out["check_rmse_horizontal_m"] = round(
            float(np.sqrt(np.mean([r["map_vs_survey_m"] ** 2 for r in check]))), 4
        )
    return out


def measure(
    ortho: Path, gcp_text: str, sizes: Mapping[str, tuple[int, int]], fit: Mapping[str, Any]
) -> dict[str, Any] | None:
    """The targets of a GCP model's points on its orthophoto, or None when its file cannot be read."""
    try:
        gcps = read_gcp_file(gcp_text, sizes)
    except GcpError:
        return None
    return check_summary(gcp_targets(ortho, gcps, fit), fit)
