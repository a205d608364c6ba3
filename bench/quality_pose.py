"""Relative-pose accuracy of the five methods on real photos (against a COLMAP SIFT reference) or on
synthetic indoor rooms (exact ground truth).

    python bench/quality_pose.py --images ../shared/data/real/sacre_coeur --resize 640
    python bench/quality_pose.py --set indoor --methods sparse,geo --json bench/out/indoor.json

The reference poses come from COLMAP's own pipeline (pycolmap: SIFT at full resolution,
exhaustive matching, incremental mapping), which none of the compared methods takes part in; it
is computed once and cached under bench/out/. Every pair of registered images is then matched by
each method, the relative pose is estimated from the matches with the reference intrinsics
(essential matrix, MAGSAC, 1 px threshold), and the pose error max(angle(R), angle(t)) is
summarised as AUC@5/10/20 degrees, as in the IMC / LoFTR protocol. The first row is the peer,
COLMAP's own SIFT matching of each pair at the photos' size (``peer_colmap.SiftPeer``); on real
photos it is judged against a reference built by a close relative of itself.

``--set indoor`` renders wide-baseline pairs of synthetic rooms (geomatch.synth.indoor: rotation
20-70 degrees, covisibility >= 10 %), a tuning split (``--seeds``) and a test split
(``--test-seeds``), and scores them by the SuperGlue / LoFTR protocol (geomatch.eval.pose: RANSAC
essential matrix at 0.5 px). Match precision is pooled over a split: the fraction of all matches
within 3 px of where image 0's depth, carried by the true pose, puts them in image 1, with
occluded or out-of-view points counting as wrong. A no-overlap set per split (views of the same
room that share no surface point) counts the pairs on which a method returns any match. Rendered
pairs are cached under bench/out/indoor/.
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import json
import shutil
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pycolmap
from common import parse_variants, print_table
from peer_colmap import with_peer

from geomatch import METHODS, Matcher, MatcherConfig, read_image
from geomatch.eval.pose import auc_over_runs, relative_pose_error, shuffled_errors
from geomatch.synth import indoor, room, roomtex
from geomatch.synth.indoor import IndoorPair, gt_matches, indoor_pairs, no_overlap_pairs

OUT = Path(__file__).resolve().parent / "out"


# the table both sets print (the indoor set adds precision and time)
POSE_COLUMNS = [
    ("method", "method", "s"),
    ("AUC@5", "auc5", "%"),
    ("AUC@10", "auc10", "%"),
    ("AUC@20", "auc20", "%"),
    ("sd@10", "sd10", "%"),
    ("median error deg", "median_err", ".2f"),
    ("matches", "matches", ".0f"),
]


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


FIELDS = ("image0", "image1", "K0", "K1", "R", "t", "depth0", "depth1", "covisibility", "rotation_deg")


def cached_pairs(kind: str, seed: int, n: int) -> list[IndoorPair]:
    """Rendered pairs from bench/out/indoor/ (rendered and saved on first use); the file name carries
    a hash of the generator's source, so editing the generator never serves stale renders."""
    digest = hashlib.sha256()
    for module in (indoor, room, roomtex):  # the pairs, the room and its render, its textures
        digest.update(Path(module.__file__).read_bytes())
    source = digest.hexdigest()[:10]
    path = OUT / "indoor" / f"{kind}_seed{seed}_n{n}_{source}.npz"
    if path.exists():
        z = np.load(path)
        return [IndoorPair(str(z["names"][i]), *(z[f][i] for f in FIELDS)) for i in range(len(z["names"]))]
    pairs = (indoor_pairs if kind == "pairs" else no_overlap_pairs)(seed, n)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {f: np.stack([np.asarray(getattr(p, f)) for p in pairs]) for f in FIELDS}
    np.savez_compressed(path, names=np.array([p.name for p in pairs]), **arrays)
    return pairs


def precision_hits(pair: IndoorPair, k0: np.ndarray, k1: np.ndarray, px: float = 3.0) -> int:
    if len(k0) == 0:
        return 0
    proj, ok = gt_matches(pair, k0)
    return int((ok & (np.linalg.norm(proj - k1, axis=1) < px)).sum())


def pose_row(split: str, label: str, errs: list[np.ndarray], n: list[int]) -> dict[str, object]:
    """One table row: AUC means and the AUC@10 spread over RANSAC orderings, per-pair errors pooled."""
    (a5, a10, a20), sd = auc_over_runs(errs)
    return {
        "split": split,
        "method": label,
        "auc5": a5,
        "auc10": a10,
        "auc20": a20,
        "sd10": sd[1],
        "median_err": float(np.median(errs)),
        "matches": float(np.mean(n)),
    }


def matchers(base: Matcher, args: argparse.Namespace) -> list[tuple[str, Any]]:
    """The rows' matchers: the peer (COLMAP SIFT's own matching at the photos' size) first."""
    specs = parse_variants(args.variants, args.methods)
    rows = [(label, base.derive(method=m, **o)) for label, m, o in specs]
    return with_peer(rows, not args.no_peer)


def run_indoor(args: argparse.Namespace) -> None:
    seeds_of = {"tuning": args.seeds, "test": args.test_seeds}
    splits = {name: [int(x) for x in seeds_of[name].split(",")] for name in args.splits.split(",")}
    # every pair's LightGlue output and every image's features stay cached across the variants
    base = Matcher(MatcherConfig(resize=args.resize, cache_anchors_mb=2048, cache_features_mb=3072))
    variants = matchers(base, args)
    report: dict[str, object] = {"pairs_per_seed": args.pairs_per_seed, "no_overlap": args.no_overlap}
    for split, seeds in splits.items():
        t0 = time.perf_counter()
        pairs = [p for s in seeds for p in cached_pairs("pairs", s, args.pairs_per_seed)]
        empty = cached_pairs("none", seeds[0], args.no_overlap) if args.no_overlap else []
        print(
            f"{split}: {len(pairs)} pairs + {len(empty)} no-overlap pairs "
            f"ready in {time.perf_counter() - t0:.0f}s"
        )
        rows, none_rows = [], []
        for label, m in variants:
            errs, n, hits, t0 = [], [], 0, time.perf_counter()
            for p in pairs:
                r = m.match(p.image0, p.image1)
                errs.append(
                    shuffled_errors(
                        r.keypoints0,
                        r.keypoints1,
                        lambda a, b, p=p: max(relative_pose_error(a, b, p.K0, p.K1, p.R, p.t)),
                        args.ransac_runs,
                    )
                )
                n.append(len(r))
                hits += precision_hits(p, r.keypoints0, r.keypoints1)
                if args.per_pair:
                    print(
                        f"  {label} {p.name} rot {p.rotation_deg:.0f} covis {p.covisibility:.2f}: "
                        f"{len(r)} matches, error {np.median(errs[-1]):.2f} deg (median of runs)"
                    )
            sec = time.perf_counter() - t0
            row = pose_row(split, label, errs, n)
            row.update(
                precision=hits / max(sum(n), 1),
                errors=[[float(e) for e in pair] for pair in errs],
                sec_per_pair=sec / max(len(pairs), 1),
            )
            rows.append(row)
            print(json.dumps({k: v for k, v in row.items() if k != "errors"}), flush=True)
            counts = [len(m.match(p.image0, p.image1)) for p in empty]
            none_rows.append(
                {
                    "split": split,
                    "method": label,
                    "pairs": len(empty),
                    "with_matches": sum(c > 0 for c in counts),
                    "mean_matches": float(np.mean(counts)) if counts else 0.0,
                    "counts": counts,
                }
            )
        title = (
            f"indoor {split} (seeds {','.join(map(str, seeds))}): {len(pairs)} pairs, rotation 20-70 deg, "
            f"covisibility >= 10 %, pose by RANSAC E at 0.5 px"
        )
        columns = [*POSE_COLUMNS, ("precision@3px", "precision", "%"), ("s/pair", "sec_per_pair", ".1f")]
        print_table(title, columns, rows)
        if empty:
            none_cols = [
                ("method", "method", "s"),
                ("pairs", "pairs", "d"),
                ("pairs with >0 matches", "with_matches", "d"),
                ("mean matches (all false)", "mean_matches", ".1f"),
            ]
            print_table(f"indoor {split}: no-overlap pairs (seed {seeds[0]})", none_cols, none_rows)
        report[split] = {"seeds": seeds, "pairs": rows, "no_overlap": none_rows}
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", type=Path, default=None, help="real photos (COLMAP SIFT reference)")
    ap.add_argument("--set", choices=("indoor",), default=None, help="a synthetic set instead of --images")
    ap.add_argument("--seeds", default="0,1,2", help="indoor tuning split")
    ap.add_argument("--test-seeds", default="100,101,102", help="indoor test split")
    ap.add_argument(
        "--splits",
        default="tuning,test",
        help="splits to run (indoor: seeds; real photos: first / second half of the names)",
    )
    ap.add_argument("--pairs-per-seed", type=int, default=10)
    ap.add_argument("--no-overlap", type=int, default=10, help="no-overlap pairs per split (0: none)")
    ap.add_argument("--per-pair", action="store_true", help="print every indoor pair")
    ap.add_argument("--resize", type=int, default=640)
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument(
        "--variants",
        default=None,
        help="instead of --methods: ';'-separated 'METHOD [option=value ...]', e.g. 'geo;geo theta_c=0.05'",
    )
    ap.add_argument(
        "--ransac-runs",
        type=int,
        default=10,
        help="score each pair's matches under this many orderings and average the AUC over them "
        "(RANSAC's draw alone moves AUC@10 by ~3.5 points on 30 pairs; sd@10 is that spread)",
    )
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--no-peer", action="store_true", help="skip COLMAP SIFT's row")
    args = ap.parse_args()
    if args.set == "indoor":
        run_indoor(args)
        return
    if args.images is None:
        ap.error("give --images DIR or --set indoor")

    rec = reference(args.images)
    regs = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    print(f"reference: {len(regs)}/{len(list(args.images.iterdir()))} images registered by COLMAP SIFT")
    # photo-disjoint splits: the first half of the names (sorted) tunes, the second half tests;
    # pairs across the halves belong to neither
    half = (len(regs) + 1) // 2
    groups = {"tuning": regs[:half], "test": regs[half:]}
    pixels = {im.name: read_image(args.images / im.name) for im in regs}
    base = Matcher(MatcherConfig(resize=args.resize, cache_anchors_mb=4096))
    rows = []
    for split in args.splits.split(","):
        pairs = list(itertools.combinations(groups[split], 2))
        split_rows = []
        for label, m in matchers(base, args):
            errs, n, t0 = [], [], time.perf_counter()
            for a, b in pairs:
                r = m.match(pixels[a.name], pixels[b.name])
                errs.append(
                    shuffled_errors(
                        r.keypoints0,
                        r.keypoints1,
                        lambda k0, k1, a=a, b=b: pose_error(rec, a, b, k0, k1),
                        args.ransac_runs,
                    )
                )
                n.append(len(r))
            row = pose_row(split, label, errs, n)
            row["sec"] = time.perf_counter() - t0
            print(json.dumps(row), flush=True)
            # per pair and ordering, in the JSON only: which pairs decide a difference between rows
            row["per_pair"] = {f"{a.name} {b.name}": e for (a, b), e in zip(pairs, errs, strict=True)}
            split_rows.append(row)
        names = ", ".join(im.name.split(".")[0] for im in groups[split])
        title = (
            f"{args.images.name} {split} ({names}): {len(pairs)} pairs, resize {args.resize}, "
            "reference COLMAP SIFT"
        )
        print_table(title, POSE_COLUMNS, split_rows)
        rows += split_rows
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
