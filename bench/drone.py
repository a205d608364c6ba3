"""Real drone surveys, ``geomatch run`` with its defaults beside COLMAP's SIFT pipeline, same machine.

brighton_beach (18 DJI nadir photos with GPS and XMP) is the tuning set; caliterra (75 photos from
a compact camera with GPS only, no XMP) the test set. No surveyed cameras: a run is judged by what
can be judged (``../shared/data/real/drone/README.md``): photos registered, 3D points, mean track
length, mean reprojection error, and the camera centres against the photos' own GPS after one
least-squares similarity (median, rms and largest residual, metres: consumer GPS, so this shows scale
and gross failures). The peer matches brighton exhaustively and caliterra with its spatial
matcher (GPS neighbours), as a COLMAP user would; geomatch's default plan decides for itself.
Each row is a child process (wall time and peak RSS of the whole run). Plan recall: of the pairs
that see at least 15 (and 100) of the peer model's 3D points together, the share geomatch's default
plan matched (pairs with matches in its database); on brighton the peer matched every pair.

copr (41 kite photos, no GPS, ten ground control points in OpenDroneMap's gcp_list.txt) is the
tuning set for ground control points: geomatch runs with ``--gcp`` and CHECKPOINTS held out, and
the peer's model is georeferenced by the same points with the same function (geo/gcp.py), so both
are judged by their check points' residuals, triangulated in each model.

    .venv/bin/python bench/drone.py                       # all three sets
    .venv/bin/python bench/drone.py --sets copr           # the GCP table
    .venv/bin/python bench/drone.py --sets brighton_beach --peer-matcher exhaustive
"""

from __future__ import annotations

import argparse
import itertools
import json
import sqlite3
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
from real_sfm import timed

from geomatch.geo import gps
from geomatch.geo.georef import camera_centres
from geomatch.geo.similarity import umeyama
from geomatch.imagefolder import list_images
from geomatch.metadata import read_metadata

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "real" / "drone"
SETS = {
    "brighton_beach": ("tuning", "exhaustive"),
    "brighton_beach_full": ("tuning", "exhaustive"),
    "caliterra": ("test", "spatial"),
    "copr": ("tuning", "exhaustive"),
}
# copr's ground control points held out as check points (a fixed split: the other usable points
# are the control); both rows are judged by the same triangulation and fit (geo/gcp.py)
CHECKPOINTS = ["gcp03", "gcp06", "gcp09"]


def gps_residuals(model: Path, images: Path) -> tuple[float, float, float, int]:
    """(median, rms, max) metres between the model's camera centres and the photos' GPS (ENU) after
    one least-squares similarity, and how many cameras took part. The rms beside the median: over
    18 cameras the median is one camera's residual and jumps with it (0.36-0.46 m on brighton
    between mappings of one database that differ by a few hundred refined points)."""
    names = list_images(images)
    fixes = gps.fixes(names, {n: read_metadata(images / n) for n in names})
    if fixes is None:
        return float("nan"), float("nan"), float("nan"), 0
    centres = camera_centres(pycolmap.Reconstruction(str(model)))
    common = sorted(n for n in centres if n in fixes.enu)
    if len(common) < 3:
        return float("nan"), float("nan"), float("nan"), len(common)
    src = np.stack([centres[n] for n in common])
    dst = np.stack([fixes.enu[n] for n in common])
    res = np.linalg.norm(umeyama(src, dst).apply(src) - dst, axis=1)
    return float(np.median(res)), float(np.sqrt(np.mean(res**2))), float(res.max()), len(common)


def covisible(model: Path, min_shared: int) -> set[tuple[str, str]]:
    """Pairs of photos that see at least ``min_shared`` of a model's 3D points together."""
    rec = pycolmap.Reconstruction(str(model))
    shared: Counter[tuple[int, int]] = Counter()
    for point in rec.points3D.values():
        ids = sorted({el.image_id for el in point.track.elements})
        shared.update(itertools.combinations(ids, 2))
    name = {i: im.name for i, im in rec.images.items()}
    return {tuple(sorted((name[a], name[b]))) for (a, b), n in shared.items() if n >= min_shared}


def matched_pairs(database: Path) -> set[tuple[str, str]]:
    """The pairs a run matched: the rows of its COLMAP database's matches table."""
    with sqlite3.connect(database) as db:
        name = dict(db.execute("SELECT image_id, name FROM images"))
        ids = [r[0] for r in db.execute("SELECT pair_id FROM matches WHERE rows > 0")]
    out = set()
    for pair_id in ids:
        b = pair_id % 2147483647
        a = (pair_id - b) // 2147483647
        out.add(tuple(sorted((name[a], name[b]))))
    return out


def plan_recall(gm_out: Path, peer_model: Path) -> str:
    """The share of the pairs that the peer's model shows covisible (>= 15 and >= 100 shared 3D
    points) that geomatch's plan matched: what its default pairing leaves out."""
    planned = matched_pairs(gm_out / "database.db")
    cells = []
    for k in (15, 100):
        truth = covisible(peer_model, k)
        cells.append(f"{100 * len(truth & planned) / max(len(truth), 1):.1f} % of {len(truth)}")
    return " / ".join(cells)


def judge(out: Path, images: Path) -> dict[str, Any]:
    summary = json.loads((out / "summary.json").read_text())
    model = out / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(model))
    median, rms, largest, _ = gps_residuals(model, images)
    return {
        "registered": f"{rec.num_reg_images()}/{len(list_images(images))}",
        "models": summary.get("models", len(list((out / "sparse").iterdir()))),
        "points": rec.num_points3D(),
        "track": rec.compute_mean_track_length(),
        "reproj": rec.compute_mean_reprojection_error(),
        "gps": f"{median:.2f} / {rms:.2f} / {largest:.2f}",
        "pairs": summary.get("pairs", "-"),
    }


def gcp_judge(out: Path, images: Path, gcp_file: Path) -> dict[str, Any]:
    """The model of ``out`` georeferenced by ``gcp_file`` with CHECKPOINTS held out: the same
    function ``geomatch run --gcp`` applies, on a copy of the model (the run's own is kept)."""
    import shutil
    import tempfile

    from geomatch.geo.gcp import apply_to_model
    from geomatch.geo.gcpfile import read_gcp_file

    metas = {n: read_metadata(images / n) for n in list_images(images)}
    gcps = read_gcp_file(gcp_file.read_text(), {n: (m.width, m.height) for n, m in metas.items()})
    with tempfile.TemporaryDirectory() as tmp:
        model = Path(tmp) / "model"
        shutil.copytree(out / "sparse" / "0", model)
        return apply_to_model(model, gcps, CHECKPOINTS)


def gcp_row(set_name: str, run: str, g: dict[str, Any]) -> str:
    if "error" in g:
        return f"| {set_name} | {run} | - | - | - | - | - | - | {g['error']} |"
    roles = [p["role"] for p in g["points"]]
    nan = float("nan")
    unused = "; ".join(f"{p['name']}: {p['reason']}" for p in g["points"] if p["role"] == "unused")
    # a check point counts only where its clicks meet in the model (within 2 px): one that does not
    # is reported unused, or judged by a point its own photos disagree on
    judged = ", ".join(
        f"{p['name']} {p['reprojection_px']:.1f} px"
        for p in g["points"]
        if p["name"] in CHECKPOINTS and p.get("reprojection_px") is not None
    )
    acc = g.get("accuracy_m")
    held = f"{acc['horizontal']:.2f} / {acc['vertical']:.2f}" if acc else "exact"
    return (
        f"| {set_name} | {run} | {roles.count('control')} | {roles.count('check')} "
        f"| {g.get('check_rmse_horizontal_m', nan):.2f} / {g.get('check_rmse_3d_m', nan):.2f} "
        f"| {judged} | {held} "
        f"| {g.get('control_rmse_3d_m', nan):.2f} | {unused} |"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", default=",".join(SETS), help="comma-separated: " + ", ".join(SETS))
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "out" / "drone")
    ap.add_argument("--peer-matcher", choices=("exhaustive", "spatial"), help="default: per set")
    ap.add_argument("--extra", default="", help="more `geomatch run` flags for the geomatch row")
    args = ap.parse_args(argv)
    rows: list[dict[str, Any]] = []
    gcp_rows: list[str] = []
    for name in args.sets.split(","):
        split, peer_matcher = SETS[name]
        peer_matcher = args.peer_matcher or peer_matcher
        images = DATA / name / "images"
        gcp_file = DATA / name / "gcp_list.txt"  # a set with ground control points (copr)
        peer_out, gm_out = args.out / name / "colmap-sift", args.out / name / "geomatch"
        peer_cmd = [
            sys.executable,
            "bench/peer_colmap.py",
            str(images),
            str(peer_out),
            "--matcher",
            peer_matcher,
        ]
        wall_peer, rss_peer, rc = timed(peer_cmd)
        if rc == 0 and gcp_file.is_file():
            gcp_rows.append(
                gcp_row(name, f"COLMAP SIFT ({peer_matcher})", gcp_judge(peer_out, images, gcp_file))
            )
        if rc == 0:
            rows.append(
                {
                    "set": name,
                    "split": split,
                    "run": f"COLMAP SIFT ({peer_matcher})",
                    "wall": wall_peer,
                    "ratio": 1.0,
                    "rss": rss_peer,
                    **judge(peer_out, images),
                }
            )
        gm_cmd = [sys.executable, "-m", "geomatch_app", "run", str(images), "--out", str(gm_out)]
        if gcp_file.is_file():
            gm_cmd += ["--gcp", str(gcp_file), "--checkpoints", ",".join(CHECKPOINTS)]
        gm_cmd += args.extra.split()
        if gm_out.exists():
            import shutil

            shutil.rmtree(gm_out)
        wall, rss, rc = timed(gm_cmd)
        if rc == 0:
            label = "geomatch run" + (f" {args.extra}" if args.extra else " (defaults)")
            if gcp_file.is_file():
                summary = json.loads((gm_out / "summary.json").read_text())
                gcp_rows.append(gcp_row(name, label + " --gcp", summary["gcp"]))
            rows.append(
                {
                    "set": name,
                    "split": split,
                    "run": label,
                    "wall": wall,
                    "ratio": wall / wall_peer,
                    "rss": rss,
                    "recall": plan_recall(gm_out, peer_out / "sparse" / "0")
                    if (peer_out / "sparse" / "0").is_dir()
                    else "-",
                    **judge(gm_out, images),
                }
            )
    print(
        "| set | split | run | registered | models | pairs | 3D points | mean track length "
        "| mean reprojection px | GPS residual median / rms / max m | wall s | x peer | peak RSS MiB "
        "| plan recall (>= 15 / >= 100 shared points in the peer's model) |"
    )
    print("|---|---|---|---|---:|---:|---:|---:|---:|---|---:|---:|---:|---|")
    for r in rows:
        print(
            f"| {r['set']} | {r['split']} | {r['run']} | {r['registered']} | {r['models']} | {r['pairs']} "
            f"| {r['points']} | {r['track']:.2f} | {r['reproj']:.2f} | {r['gps']} | {r['wall']:.0f} "
            f"| {r['ratio']:.2f} | {r['rss']:.0f} | {r.get('recall', '-')} |"
        )
    if gcp_rows:
        print(
            f"\nGround control points: check points {', '.join(CHECKPOINTS)}, "
            "the other usable points control\n"
        )
        print(
            "| set | run | control | check | check-point RMSE horizontal / 3D m "
            "| check points' clicks: largest px from their point | control held to h / v m "
            "| control RMSE 3D m | not used |"
        )
        print("|---|---|---:|---:|---|---|---|---:|---|")
        print("\n".join(gcp_rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
