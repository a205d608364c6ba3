"""Ground control points on synthetic scenes with exact truth: the check-point RMSE against the
ground sampling distance, with survey noise of 0 and 2 cm on the points' coordinates.

For each finished run of a synthetic air-to-ground scene (``geomatch synth`` + ``geomatch run``,
e.g. the sweep's ``bench/out/air_ground_sweep/scene_*/run_*``): nine ground points that at least two
cameras see unoccluded become a GCP file (geomatch.synth.gcps, exact clicks), three of them held out
as check points; the model is georeferenced by the other six (geo/gcp.py, as ``geomatch run --gcp``
does: the similarity, then the adjustment holding the control points) and judged at the three, and
its camera centres against the truth. Beside it, the same model georeferenced by GPS alone (the
cameras' true positions plus consumer-GNSS noise, GPS_SIGMA_M horizontal and 1.5x that vertical,
fitted as ``geomatch run`` fits EXIF GPS: geo/georef.align) and judged at the same check points.
GSD: the coarser aerial view's height over its focal length (metres per pixel at the ground below it).

    .venv/bin/python bench/gcp_accuracy.py bench/out/air_ground_sweep/scene_a2_g6_s2/run_floor60_pnp0
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np
import pycolmap
from common import print_table

from geomatch.geo import georef
from geomatch.geo.gcp import adjust_to_control, georeference, triangulate
from geomatch.geo.gcpfile import GcpError, read_gcp_file
from geomatch.synth.aerial import Scene
from geomatch.synth.gcps import OFFSET, scene_gcps

COLUMNS = [
    ("scene", "scene", "s"),
    ("registered", "registered", "s"),
    ("GCP noise m", "noise", ".2f"),
    ("GSD m", "gsd", ".3f"),
    ("points left out", "unused", "s"),
    ("check RMSE horizontal m", "check_h", ".3f"),
    ("check RMSE 3D m, similarity only", "check_sim", ".3f"),
    ("check RMSE 3D m", "check_3d", ".3f"),
    ("check 3D / GSD", "ratio", ".2f"),
    ("control RMSE 3D m", "control_3d", ".3f"),
    ("camera centres median / max m (or why not georeferenced)", "cams", "s"),
]


GPS_SIGMA_M = 2.0  # consumer GNSS, horizontal, per axis


def judge(run: Path, noise: float, points: int = 9, check: int = 3) -> dict[str, object]:
    scene_dir = run.parent
    m = re.fullmatch(r"scene_a(\d+)_g(\d+)_s(\d+)", scene_dir.name)
    if m is None:
        raise SystemExit(f"{run}: not a run of a synthetic scene folder (scene_aA_gG_sS)")
    n_aerial, n_ground, seed = (int(v) for v in m.groups())
    scene = Scene(seed)
    cams = scene.cameras(n_aerial, n_ground, 640, 480)
    text, _ = scene_gcps(scene, cams, points, seed=seed, noise_m=noise)
    gcps = read_gcp_file(text, {c.name: (c.width, c.height) for c in cams})
    rec = pycolmap.Reconstruction(str(run / "sparse" / "0"))
    gsd = max(float(c.centre[2] / c.K[0, 0]) for c in cams if c.aerial)
    nan = float("nan")
    row: dict[str, object] = {"scene": scene_dir.name, "noise": noise, "gsd": gsd, "unused": "-"}
    try:
        report = georeference(rec, gcps, check)
    except GcpError as e:  # a model with wrongly placed cameras leaves points that do not meet
        row.update(registered=f"{rec.num_reg_images()}/{len(cams)}", cams=str(e)[:60])
        return {**row, "check_h": nan, "check_3d": nan, "check_sim": nan, "ratio": nan, "control_3d": nan}
    rec.transform(report.similarity.to_pycolmap())
    adjust_to_control(rec, gcps, report)
    similarity = report.similarity_check_rmse
    truth = {c.name: c.centre + OFFSET for c in cams}
    errors = [
        float(np.linalg.norm(np.asarray(im.projection_center()) + report.origin - truth[im.name]))
        for im in rec.images.values()
        if im.has_pose
    ]
    check_rmse, control_rmse = report.rmse("check"), report.rmse("control")
    return {
        **row,
        "unused": str(sum(p.role == "unused" for p in report.points)),
        "registered": f"{len(errors)}/{len(cams)}",
        "check_h": check_rmse[0] if check_rmse else float("nan"),
        "check_3d": check_rmse[1] if check_rmse else float("nan"),
        "check_sim": similarity[1] if similarity else float("nan"),
        "ratio": (check_rmse[1] / gsd) if check_rmse else float("nan"),
        "control_3d": control_rmse[1] if control_rmse else float("nan"),
        "cams": f"{np.median(errors):.3f} / {max(errors):.3f}",
    }


def judge_gps(run: Path, points: int = 9, check: int = 3) -> dict[str, object]:
    """The same model and check points, georeferenced by noisy GPS at the cameras instead."""
    scene_dir = run.parent
    n_aerial, n_ground, seed = (int(v) for v in re.findall(r"\d+", scene_dir.name)[:3])
    scene = Scene(seed)
    cams = scene.cameras(n_aerial, n_ground, 640, 480)
    text, _ = scene_gcps(scene, cams, points, seed=seed)
    gcps = read_gcp_file(text, {c.name: (c.width, c.height) for c in cams})
    rec = pycolmap.Reconstruction(str(run / "sparse" / "0"))
    gsd = max(float(c.centre[2] / c.K[0, 0]) for c in cams if c.aerial)
    rng = np.random.default_rng([seed, 2])
    sigma = np.array([GPS_SIGMA_M, GPS_SIGMA_M, georef.GNSS_VERTICAL_FACTOR * GPS_SIGMA_M])
    enu = {c.name: c.centre + rng.normal(0.0, sigma) for c in cams}  # scene metres (OFFSET removed)
    row: dict[str, object] = {
        "scene": scene_dir.name,
        "noise": float("nan"),
        "gsd": gsd,
        "unused": "-",
        "registered": f"{rec.num_reg_images()}/{len(cams)}",
        "check_sim": float("nan"),
        "control_3d": float("nan"),
    }
    if georef.align(rec, enu) is None:
        return {**row, "check_h": float("nan"), "check_3d": float("nan"), "ratio": float("nan"), "cams": "-"}
    names = sorted(gcps.points)
    idx = np.linspace(0, len(names) - 1, check + 2)[1:-1].round().astype(int)  # choose_checkpoints's
    res = []
    for n in (names[i] for i in idx):
        X = triangulate(rec, gcps.points[n])[0]
        if X is not None:
            res.append(X - (gcps.points[n].xyz - OFFSET))
    truth = {c.name: c.centre for c in cams}
    errors = [
        float(np.linalg.norm(np.asarray(im.projection_center()) - truth[im.name]))
        for im in rec.images.values()
        if im.has_pose
    ]
    r = np.stack(res) if res else np.full((1, 3), np.nan)
    h, d3 = float(np.sqrt(np.mean(np.sum(r[:, :2] ** 2, 1)))), float(np.sqrt(np.mean(np.sum(r**2, 1))))
    return {
        **row,
        "scene": f"{scene_dir.name} (GPS only, {GPS_SIGMA_M:g} m)",
        "check_h": h,
        "check_3d": d3,
        "ratio": d3 / gsd,
        "cams": f"{np.median(errors):.3f} / {max(errors):.3f}",
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", type=Path, nargs="+", help="run folders of synthetic scenes")
    ap.add_argument("--noise", default="0,0.02", help="GCP coordinate noise, metres, comma-separated")
    args = ap.parse_args()
    rows = []
    for run in args.runs:
        rows += [judge(run, float(n)) for n in args.noise.split(",")]
        rows.append(judge_gps(run))
    print_table("GCP georeferencing on synthetic scenes (6 control, 3 check points)", COLUMNS, rows)


if __name__ == "__main__":
    main()
