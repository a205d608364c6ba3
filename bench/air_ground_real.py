"""Real drone x street photos (``../shared/data/real/airground``): what ``geomatch run`` writes.

No camera poses exist for these photos, so a pair is judged by eye, as the folder's README says:
for every drone x street pair this prints the matches the matcher found, the inliers COLMAP's
verification kept (only those reach the mapper), and whether the drone photo was registered, and
draws each pair's matches into ``--out`` (green: verified inliers, red: the rest) to look at. Each
folder runs twice: with defaults (the drone photo is aerial only if its metadata says so) and with
``--aerial`` naming the drone photo (tiled, the paper's full method on every crop).

    .venv/bin/python bench/air_ground_real.py
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pycolmap
from common import print_table

from geomatch.imageio import read_image
from geomatch.pipeline import RunOptions, run
from geomatch.sfm.colmapdb import COLMAP_OFFSET

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "real" / "airground"
# the drone photo of each folder (its README): the rest are street-level photos
DRONE = {"finearts": "*camA010*", "austin-rec-center": "*camA011*"}

COLUMNS = [
    ("folder", "folder", "s"),
    ("run", "run", "s"),
    ("street photo", "street", "s"),
    ("tiled", "tiled", "s"),
    ("matches", "matches", "d"),
    ("verified inliers", "inliers", "d"),
    ("drone photo registered", "registered", "s"),
]


def draw(path: Path, a: np.ndarray, b: np.ndarray, ka: np.ndarray, kb: np.ndarray, inl: np.ndarray) -> None:
    """Both photos side by side at 600 px high, every match a line: inliers green, others red."""
    h = 600
    sa, sb = h / a.shape[0], h / b.shape[0]
    ra = cv2.resize(a, (round(a.shape[1] * sa), h), interpolation=cv2.INTER_AREA)
    rb = cv2.resize(b, (round(b.shape[1] * sb), h), interpolation=cv2.INTER_AREA)
    canvas = np.concatenate([ra, np.full((h, 10, 3), 255, np.uint8), rb], axis=1)
    for p, q, ok in zip(ka * sa, kb * sb + [ra.shape[1] + 10, 0], inl, strict=True):
        colour = (0, 200, 0) if ok else (230, 0, 0)
        pt0, pt1 = tuple(int(v) for v in p), tuple(int(v) for v in q)
        cv2.line(canvas, pt0, pt1, colour, 1, cv2.LINE_AA)
        cv2.circle(canvas, pt0, 3, colour, -1)
        cv2.circle(canvas, pt1, 3, colour, -1)
    cv2.imwrite(str(path), cv2.cvtColor(canvas, cv2.COLOR_RGB2BGR))


def pairs_of(out: Path, folder: Path, drone: str, pictures: Path) -> list[dict[str, Any]]:
    """Each drone x street pair of a finished run: raw matches, verified inliers, a picture."""
    summary = json.loads((out / "summary.json").read_text())
    registered = set(summary.get("registered_names", []))
    db = pycolmap.Database.open(str(out / "database.db"))
    try:
        images = {im.image_id: im.name for im in db.read_all_images()}
        (drone_id,) = (i for i, n in images.items() if Path(n).match(drone))
        geometries = dict(zip(*db.read_two_view_geometries(), strict=True))
        rows = []
        for other, name in sorted(images.items(), key=lambda kv: kv[1]):
            if other == drone_id:
                continue
            a, b = sorted((drone_id, other))
            m = db.read_matches(a, b) if db.exists_matches(a, b) else np.zeros((0, 2), np.uint32)
            g = geometries.get(pycolmap.image_pair_to_pair_id(a, b))
            inliers = g.inlier_matches if g is not None else np.zeros((0, 2), np.uint32)
            ka, kb = db.read_keypoints(a)[:, :2] - COLMAP_OFFSET, db.read_keypoints(b)[:, :2] - COLMAP_OFFSET
            inl = {tuple(r) for r in inliers.tolist()}
            ok = np.array([tuple(r) in inl for r in m.tolist()], bool)
            pa, pb = (ka[m[:, 0]], kb[m[:, 1]]) if len(m) else (np.zeros((0, 2)), np.zeros((0, 2)))
            if a != drone_id:
                pa, pb = pb, pa
            draw(
                pictures / f"{Path(name).stem}.png",
                read_image(folder / images[drone_id]),
                read_image(folder / name),
                pa,
                pb,
                ok,
            )
            rows.append(
                {
                    "street": Path(name).stem[-6:],
                    "tiled": "yes" if summary.get("tiled_pairs") else "no",
                    "matches": len(m),
                    "inliers": len(inliers),
                    "registered": "yes" if images[drone_id] in registered else "no",
                }
            )
        return rows
    finally:
        db.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--folders", default=",".join(DRONE))
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "out" / "air_ground_real")
    args = ap.parse_args()
    rows: list[dict[str, Any]] = []
    for name in args.folders.split(","):
        folder = DATA / name
        for label, aerial in (("defaults", None), ("--aerial drone photo", DRONE[name])):
            out = args.out / name / ("defaults" if aerial is None else "aerial")
            shutil.rmtree(out, ignore_errors=True)
            run(folder, out, RunOptions(aerial_glob=aerial, progress=False))
            pictures = out / "pictures"
            pictures.mkdir()
            for r in pairs_of(out, folder, DRONE[name], pictures):
                rows.append({"folder": name, "run": label, **r})
            print(f"{name} ({label}): pictures in {pictures}", flush=True)
    print_table("Drone x street pairs as `geomatch run` writes them", COLUMNS, rows)


if __name__ == "__main__":
    main()
