"""Quality of the five methods on photos warped by random homographies (HPatches-style).

    python bench/quality_homography.py --pairs 20 --resize 640

Prints, per method: matches, matches within 3 px of the ground-truth homography, precision
(fraction within 3 px) and homography AUC@3/5/10 px (mean corner error of a MAGSAC homography).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from common import parse_variants, print_table

from geomatch import METHODS, Matcher, MatcherConfig
from geomatch.homography import auc, corner_error, reprojection_errors, warped_pairs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pairs", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--strength", type=float, default=0.2)
    ap.add_argument("--resize", type=int, default=640)
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--variants", default=None, help="';'-separated 'METHOD [option=value ...]' rows")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = ap.parse_args()

    pairs = warped_pairs(args.pairs, args.seed, args.strength)
    base = Matcher(MatcherConfig(resize=args.resize, cache_anchors_mb=4096))
    variants = [
        (label, base.derive(method=method, **options))
        for label, method, options in parse_variants(args.variants, args.methods)
    ]
    # pairs outside, variants inside: a pair's features (DISK maps with their fp16 fine map are
    # ~90 MB an image at 640 px) are extracted once and shared by every variant while they are in
    # the byte-bounded cache; the other way round, an ablation of a dozen rows re-extracted all
    # 2 x pairs images per row
    n_all: dict[str, list[int]] = {label: [] for label, _ in variants}
    n_good: dict[str, list[int]] = {label: [] for label, _ in variants}
    errs: dict[str, list[float]] = {label: [] for label, _ in variants}
    secs = dict.fromkeys(n_all, 0.0)
    for i, p in enumerate(pairs):
        print(f"pair {i + 1}/{len(pairs)}", file=sys.stderr, flush=True)
        for label, matcher in variants:
            t0 = time.perf_counter()
            r = matcher.match(p.image0, p.image1)
            secs[label] += time.perf_counter() - t0
            e = reprojection_errors(p.H, r.keypoints0, r.keypoints1)
            n_all[label].append(len(r))
            n_good[label].append(int((e < 3).sum()))
            h, w = p.image0.shape[:2]
            errs[label].append(corner_error(p.H, r.keypoints0, r.keypoints1, w, h))
    rows = []
    for label, _ in variants:
        a3, a5, a10 = auc(errs[label], (3, 5, 10))
        row = {
            "method": label,
            "matches": float(np.mean(n_all[label])),
            "within_3px": float(np.mean(n_good[label])),
            "precision": float(np.sum(n_good[label]) / max(np.sum(n_all[label]), 1)),
            "auc3": a3,
            "auc5": a5,
            "auc10": a10,
            # the first variant of a pair pays its feature extraction
            "sec_per_pair": secs[label] / len(pairs),
        }
        rows.append(row)
        print(json.dumps(row), flush=True)

    title = f"{len(pairs)} warped photos, resize {args.resize}, strength {args.strength}"
    columns = [
        ("method", "method", "s"),
        ("matches", "matches", ".0f"),
        ("within 3 px", "within_3px", ".0f"),
        ("precision", "precision", ".3f"),
        ("AUC@3px", "auc3", "%"),
        ("AUC@5px", "auc5", "%"),
        ("AUC@10px", "auc10", "%"),
    ]
    print_table(title, columns, rows)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
