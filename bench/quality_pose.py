"""Relative-pose accuracy of the five methods on real photos, against a COLMAP SIFT reference.

    python bench/quality_pose.py --images ../shared/data/real/sacre_coeur --resize 640

The reference poses come from COLMAP's own pipeline (pycolmap: SIFT at full resolution,
exhaustive matching, incremental mapping), which none of the compared methods takes part in; it
is computed once and cached under bench/out/. Every pair of registered images is then matched by
each method, the relative pose is estimated from the matches with the reference intrinsics
(essential matrix, MAGSAC, 1 px threshold), and the pose error max(angle(R), angle(t)) is
summarised as AUC@5/10/20 degrees, as in the IMC / LoFTR protocol.
"""

from __future__ import annotations

import argparse
import itertools
import json
import shutil
import time
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from common import parse_variants, print_table

from geomatch import METHODS, Matcher, MatcherConfig, read_image
from geomatch.homography import auc

OUT = Path(__file__).resolve().parent / "out"


def reference(images: Path) -> pycolmap.Reconstruction:
    cache = OUT / f"{images.name}_sift_reference"
    model = cache / "model"
    if (model / "images.bin").exists():
        return pycolmap.Reconstruction(str(model))
    if cache.exists():
        shutil.rmtree(cache)
    cache.mkdir(parents=True)
    db = cache / "database.db"
    pycolmap.extract_features(db, images, camera_mode=pycolmap.CameraMode.PER_IMAGE)
    pycolmap.match_exhaustive(db)
    recs = pycolmap.incremental_mapping(db, images, cache / "sparse")
    best = max(recs.values(), key=lambda r: r.num_reg_images())
    model.mkdir()
    best.write(str(model))
    return best


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-12))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def pose_error(rec: pycolmap.Reconstruction, im0, im1, k0: np.ndarray, k1: np.ndarray) -> float:
    if len(k0) < 5:
        return 180.0
    cam0, cam1 = rec.cameras[im0.camera_id], rec.cameras[im1.camera_id]
    n0 = np.asarray(cam0.cam_from_img(k0.astype(np.float64) + 0.5))
    n1 = np.asarray(cam1.cam_from_img(k1.astype(np.float64) + 0.5))
    f = 0.5 * (cam0.mean_focal_length() + cam1.mean_focal_length())
    E, mask = cv2.findEssentialMat(n0, n1, np.eye(3), cv2.USAC_MAGSAC, 0.99999, 1.0 / f)
    if E is None or E.shape != (3, 3):
        return 180.0
    _, R, t, _ = cv2.recoverPose(E, n0, n1, np.eye(3), mask=mask)
    gt = im1.cam_from_world() * im0.cam_from_world().inverse()
    R_gt = gt.rotation.matrix()
    t_gt = np.asarray(gt.translation)
    err_r = float(np.degrees(np.arccos(np.clip((np.trace(R.T @ R_gt) - 1) / 2, -1, 1))))
    err_t = angle_deg(t.ravel(), t_gt)
    err_t = min(err_t, 180 - err_t)  # the essential matrix leaves the sign of t ambiguous
    return max(err_r, err_t)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", type=Path, required=True)
    ap.add_argument("--resize", type=int, default=640)
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument(
        "--variants",
        default=None,
        help="instead of --methods: ';'-separated 'METHOD [option=value ...]', e.g. 'geo;geo theta_c=0.05'",
    )
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    rec = reference(args.images)
    regs = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    print(f"reference: {len(regs)}/{len(list(args.images.iterdir()))} images registered by COLMAP SIFT")
    pairs = list(itertools.combinations(regs, 2))
    pixels = {im.name: read_image(args.images / im.name) for im in regs}
    base = Matcher(MatcherConfig(resize=args.resize, cache_anchors_mb=4096))
    rows = []
    for label, method, options in parse_variants(args.variants, args.methods):
        m = base.derive(method=method, **options)
        errs, n, t0 = [], [], time.perf_counter()
        for a, b in pairs:
            r = m.match(pixels[a.name], pixels[b.name])
            errs.append(pose_error(rec, a, b, r.keypoints0, r.keypoints1))
            n.append(len(r))
        a5, a10, a20 = auc(errs, (5, 10, 20))
        row = {
            "method": label,
            "auc5": a5,
            "auc10": a10,
            "auc20": a20,
            "matches": float(np.mean(n)),
            "median_err": float(np.median(errs)),
            "sec": time.perf_counter() - t0,
        }
        rows.append(row)
        print(json.dumps(row), flush=True)
    title = f"{args.images.name}: {len(pairs)} pairs, resize {args.resize}, reference COLMAP SIFT"
    columns = [
        ("method", "method", "s"),
        ("AUC@5", "auc5", "%"),
        ("AUC@10", "auc10", "%"),
        ("AUC@20", "auc20", "%"),
        ("median error deg", "median_err", ".2f"),
        ("matches", "matches", ".0f"),
    ]
    print_table(title, columns, rows)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
