"""Pair recall of ``retrieval:K`` (VLAD over ALIKED descriptors) against ground-truth covisibility.

A pair is covisible when at least ``--min-overlap`` of one image's pixels are seen, unoccluded, by
the other (synth.covisibility, from the rendered depth). Recall is reported for same-view pairs
(aerial-aerial, ground-ground), where retrieval decides; aerial x ground pairs are all kept by
``retrieval:K`` by design. A random ranking with the same number of pairs is the baseline.

    python bench/retrieval_recall.py --seeds 0,1 --aerial 8 --ground 12 --k 3,5,8
"""

from __future__ import annotations

import argparse

import numpy as np
from common import print_table

from geomatch.matching.matcher import Matcher, MatcherConfig
from geomatch.pipeline.pair_sources import nearest_neighbours
from geomatch.pipeline.retrieval import vlad
from geomatch.synth.aerial import Scene, covisibility


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--aerial", type=int, default=8)
    ap.add_argument("--ground", type=int, default=12)
    ap.add_argument("--k", default="3,5,8")
    ap.add_argument("--min-overlap", type=float, default=0.1)
    args = ap.parse_args()
    matcher = Matcher(MatcherConfig(method="sparse", resize=640))
    rows = []
    for seed in (int(s) for s in args.seeds.split(",")):
        scene = Scene(seed)
        cams = scene.cameras(args.aerial, args.ground, 640, 480)
        names = [c.name for c in cams]
        cov = covisibility(scene, cams)
        covis = np.maximum(cov, cov.T) >= args.min_overlap
        same = np.array([[a.aerial == b.aerial for b in cams] for a in cams])
        iu = np.triu_indices(len(cams), 1)
        truth = {(names[i], names[j]) for i, j in zip(*iu, strict=True) if covis[i, j] and same[i, j]}
        local = []
        for c in cams:
            img, _ = scene.render(c)
            local.append(matcher.features(img)["aliked"].sparse.descriptors.float().numpy())
        g = vlad(local)
        rng = np.random.default_rng(seed)
        for k in (int(x) for x in args.k.split(",")):
            got = {p for p in nearest_neighbours(g, names, k) if same[names.index(p[0]), names.index(p[1])]}
            rand = {
                p
                for p in nearest_neighbours(rng.normal(size=g.shape), names, k)
                if same[names.index(p[0]), names.index(p[1])]
            }
            rows.append(
                {
                    "seed": seed,
                    "k": k,
                    "covisible": len(truth),
                    "retrieved": len(got),
                    "recall": len(got & truth) / max(len(truth), 1),
                    "precision": len(got & truth) / max(len(got), 1),
                    "random_recall": len(rand & truth) / max(len(truth), 1),
                }
            )
    print_table(
        f"retrieval:K pair recall, same-view pairs, overlap >= {args.min_overlap}",
        [
            ("seed", "seed", "d"),
            ("K", "k", "d"),
            ("covisible pairs", "covisible", "d"),
            ("retrieved", "retrieved", "d"),
            ("recall", "recall", ".2f"),
            ("precision", "precision", ".2f"),
            ("random ranking recall", "random_recall", ".2f"),
        ],
        rows,
    )


if __name__ == "__main__":
    main()
