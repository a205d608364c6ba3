"""The view graph's rotation candidates against a reference model: what each essential-matrix
estimator costs and how near its rotations are.

The view-graph checks (geomatch.sfm.viewgraph) judge each verified pair by its candidate relative
rotations (geomatch.sfm.pairrotations: the essential matrix's, COLMAP's two-view pose, the
homography's decompositions). For every verified pair of a run's database whose two photos the
reference model registered (e.g. COLMAP SIFT's model of the same photos, from ``bench/drone.py``),
this prints, per estimator of the essential matrix, its CPU seconds over all pairs (one thread),
how far its own rotation is from the reference's relative rotation, and how far the best of the
pair's candidates is (what the loop and tree checks can find).

    .venv/bin/python bench/viewgraph_rotations.py bench/out/drone/caliterra/geomatch/database.db \\
        bench/out/drone/caliterra/colmap-sift/sparse/0
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from common import print_table

from geomatch.imageio import working_scale
from geomatch.sfm.pairrotations import rotation_angle

ESTIMATORS = {"RANSAC (1000 iterations)": cv2.RANSAC, "USAC_DEFAULT": cv2.USAC_DEFAULT}
COLUMNS = [
    ("estimator", "estimator", "s"),
    ("pairs", "pairs", "d"),
    ("CPU s", "cpu_s", ".2f"),
    ("own rotation: median deg", "own_median", ".2f"),
    ("own > 5 deg", "own_over5", "d"),
    ("best candidate: median deg", "best_median", ".2f"),
    ("best > 5 deg", "best_over5", "d"),
]


def essential_rotation(n0: np.ndarray, n1: np.ndarray, focal: float, method: int) -> np.ndarray | None:
    """As pairrotations.candidate_rotations estimates it, with ``method``."""
    E, mask = cv2.findEssentialMat(n0, n1, np.eye(3), method, 0.999, 1.0 / focal)
    if E is None or E.shape != (3, 3):
        return None
    n, R, _, _ = cv2.recoverPose(E, n0, n1, np.eye(3), mask=mask)
    return R if n >= 8 else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("database", type=Path, help="a run's database.db")
    ap.add_argument("reference", type=Path, help="a reference model's folder (sparse/0)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    db = pycolmap.Database.open(str(args.database))
    reference = pycolmap.Reconstruction(str(args.reference))
    posed = {im.name: im for im in reference.images.values() if im.has_pose}
    images = {im.image_id: im for im in db.read_all_images()}
    cameras = {c.camera_id: c for c in db.read_all_cameras()}
    cpu = dict.fromkeys(ESTIMATORS, 0.0)
    own: dict[str, list[float]] = {k: [] for k in ESTIMATORS}
    best: dict[str, list[float]] = {k: [] for k in ESTIMATORS}
    pair_ids, geometries = db.read_two_view_geometries()
    for pid, g in zip(pair_ids, geometries, strict=True):
        if len(g.inlier_matches) < 15:
            continue
        a, b = pycolmap.pair_id_to_image_pair(pid)
        if images[a].name not in posed or images[b].name not in posed:
            continue
        truth = (
            posed[images[b].name].cam_from_world().rotation.matrix()
            @ posed[images[a].name].cam_from_world().rotation.matrix().T
        )
        c0, c1 = cameras[images[a].camera_id], cameras[images[b].camera_id]
        kp0, kp1 = db.read_keypoints(a)[:, :2], db.read_keypoints(b)[:, :2]
        m = g.inlier_matches
        n0 = np.asarray(c0.cam_from_img(kp0[m[:, 0]].astype(np.float64)), np.float64)
        n1 = np.asarray(c1.cam_from_img(kp1[m[:, 1]].astype(np.float64)), np.float64)
        focal = float(np.mean([c0.mean_focal_length(), c1.mean_focal_length()]))
        focal /= working_scale(max(c0.width, c0.height, c1.width, c1.height))
        others: list[np.ndarray] = []
        if pycolmap.estimate_two_view_geometry_pose(
            c0, kp0.astype(np.float64), c1, kp1.astype(np.float64), g
        ) and (g.cam2_from_cam1 is not None):
            others.append(g.cam2_from_cam1.rotation.matrix())
        H, _ = cv2.findHomography(n0, n1, cv2.RANSAC, 2.0 / focal)
        if H is not None:
            others.extend(cv2.decomposeHomographyMat(H, np.eye(3))[1])
        for name, method in ESTIMATORS.items():
            t = time.process_time()
            R = essential_rotation(n0, n1, focal, method)
            cpu[name] += time.process_time() - t
            candidates = others + ([R] if R is not None else [])
            own[name].append(rotation_angle(R.T @ truth) if R is not None else 180.0)
            best[name].append(min([rotation_angle(X.T @ truth) for X in candidates], default=180.0))
    db.close()
    rows = [
        {
            "estimator": name,
            "pairs": len(own[name]),
            "cpu_s": cpu[name],
            "own_median": float(np.median(own[name])),
            "own_over5": int(np.sum(np.array(own[name]) > 5)),
            "best_median": float(np.median(best[name])),
            "best_over5": int(np.sum(np.array(best[name]) > 5)),
        }
        for name in ESTIMATORS
    ]
    print_table(f"View-graph rotation candidates of {args.database} against {args.reference}", COLUMNS, rows)


if __name__ == "__main__":
    main()
