"""Quality of the five methods on photos warped by random homographies (HPatches-style).

    python bench/quality_homography.py --pairs 20 --resize 640

Prints, per method: matches, matches within 3 px of the ground-truth homography, precision
(fraction within 3 px), homography AUC@3/5/10 px (mean corner error of a MAGSAC homography) and
seconds per pair, with COLMAP's own SIFT matching (``bench/peer_colmap.SiftPeer``: extraction at
the photos' own size, up to 1600 px, and verified matches) as the first row, timed in the same run.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from common import parse_variants, print_table
from peer_colmap import with_peer

from geomatch import METHODS, Matcher, MatcherConfig
from geomatch.eval.homography import corner_error, reprojection_errors
from geomatch.eval.metrics import auc
from geomatch.synth.photos import warped_pairs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pairs", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--strength", type=float, default=0.2)
    ap.add_argument("--resize", type=int, default=640)
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--variants", default=None, help="';'-separated 'METHOD [option=value ...]' rows")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    ap.add_argument("--no-peer", action="store_true", help="skip COLMAP SIFT's row")
    args = ap.parse_args()

    pairs = warped_pairs(args.pairs, args.seed, args.strength)
    base = Matcher(MatcherConfig(resize=args.resize, cache_anchors_mb=4096))
    variants = with_peer(
        [
            (label, base.derive(method=method, **options))
            for label, method, options in parse_variants(args.variants, args.methods)
        ],
        not args.no_peer,
    )
    # pairs outside, variants inside: a pair's features (DISK maps with their fp16 fine map are
    # ~90 MB an image at 640 px) are extracted once and shared by every variant while they are in
    # the byte-bounded cache; the other way round, an ablation of a dozen rows re-extracted all
    # 2 x pairs images per row
    # per variant, by position (two rows may carry the same label)
    n_all: list[list[int]] = [[] for _ in variants]
    n_good: list[list[int]] = [[] for _ in variants]
    errs: list[list[float]] = [[] for _ in variants]
    secs = [0.0] * len(variants)
    for i, p in enumerate(pairs):
        print(f"pair {i + 1}/{len(pairs)}", file=sys.stderr, flush=True)
        for v, (_, matcher) in enumerate(variants):
            t0 = time.perf_counter()
            r = matcher.match(p.image0, p.image1)
            secs[v] += time.perf_counter() - t0
            k0, k1 = r.keypoints0, r.keypoints1
            e = reprojection_errors(p.H, k0, k1)
            n_all[v].append(len(k0))
            n_good[v].append(int((e < 3).sum()))
            h, w = p.image0.shape[:2]
            errs[v].append(corner_error(p.H, k0, k1, w, h))
    rows = []
    for v, (label, _) in enumerate(variants):
        a3, a5, a10 = auc(errs[v], (3, 5, 10))
        row = {
            "method": label,
            "matches": float(np.mean(n_all[v])),
            "within_3px": float(np.mean(n_good[v])),
            "precision": float(np.sum(n_good[v]) / max(np.sum(n_all[v]), 1)),
            "auc3": a3,
            "auc5": a5,
            "auc10": a10,
            # the first variant of a pair pays its feature extraction
            "sec_per_pair": secs[v] / len(pairs),
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
        ("s / pair", "sec_per_pair", ".2f"),
    ]
    print_table(title, columns, rows)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
