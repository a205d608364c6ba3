"""How many matches are right when one image of a pair is turned by a quarter turn (synthetic scene).

    python bench/quarter_turns.py --seed 0 --aerial 3 --ground 6

Renders the scene of ``geomatch demo``, matches every aerial x aerial pair and every pair of the
nadir image(s) with the ground views with ``sparse``, the second image turned by 0/90/180/270
degrees counter-clockwise, maps its keypoints back and counts the matches within 3 px of the
rendered truth (bench/synth_precision.correct). Shows why pairs with an aerial side are matched at
their best quarter turn (geomatch/matching/rotation.py), and whether the cheap probe that picks the
turn (``matching.rotation.probe_count``) picks the turn with the most right matches as often as the
full-strength anchors do, at what cost per call. Each cell: full-strength matches (right ones) /
probe matches.
"""

from __future__ import annotations

import argparse
import itertools
import time

import numpy as np
from common import print_table
from synth_precision import correct

from geomatch import Matcher, MatcherConfig
from geomatch.matching.rotation import TURNS, points_back, probe_count, quarter_turn
from geomatch.synth.aerial import Scene


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--aerial", type=int, default=3)
    ap.add_argument("--ground", type=int, default=6)
    ap.add_argument("--resize", type=int, default=640)
    ap.add_argument("--all-ground", action="store_true", help="every aerial x ground pair")
    args = ap.parse_args()
    scene = Scene(args.seed)
    cams = {c.name: c for c in scene.cameras(args.aerial, args.ground, 640, 480)}
    renders = {n: scene.render(c) for n, c in cams.items()}
    aerial = sorted(n for n, c in cams.items() if c.aerial)
    nadir = [n for i, n in enumerate(aerial) if i % 3 == 2]  # synth.Scene.cameras: every third
    ground = sorted(n for n, c in cams.items() if not c.aerial)
    partners = aerial if args.all_ground else nadir
    pairs = list(itertools.combinations(aerial, 2)) + [(a, g) for a in partners for g in ground]
    m = Matcher(MatcherConfig(method="sparse", resize=args.resize))
    rows = []
    agree = {"full": 0, "probe": 0}
    seconds = {"full": 0.0, "probe": 0.0}
    for a, b in pairs:
        row: dict[str, object] = {"pair": f"{a} x {b}"}
        img_b = renders[b][0]
        right, full, probe = [], [], []
        for t in TURNS:
            turned = quarter_turn(img_b, t)
            m.features(renders[a][0]), m.features(turned)  # extraction is not the probes' cost
            t0 = time.perf_counter()
            r = m.match(renders[a][0], turned)
            seconds["full"] += time.perf_counter() - t0
            t0 = time.perf_counter()
            probe.append(probe_count(m, renders[a][0], turned))
            seconds["probe"] += time.perf_counter() - t0
            k1 = points_back(r.keypoints1, t, img_b.shape[1], img_b.shape[0])
            ok = correct(cams[a], renders[a][1], cams[b], renders[b][1], r.keypoints0, k1, 3.0)
            right.append(int(ok.sum()))
            full.append(len(r))
            row[f"t{t}"] = f"{len(r)} ({right[-1]} right) / {probe[-1]}"
        best = int(np.argmax(right))
        for name, counts in (("full", full), ("probe", probe)):
            choice = int(np.argmax(counts))
            row[name] = f"{90 * choice}" + ("" if right[choice] == right[best] else " WRONG")
            agree[name] += right[choice] == right[best]
        rows.append(row)
        print(row, flush=True)
    cols = [("pair", "pair", "s")] + [(f"{90 * t} deg: full (right) / probe", f"t{t}", "s") for t in TURNS]
    cols += [("full picks", "full", "s"), ("probe picks", "probe", "s")]
    print_table(f"quarter turns, scene seed {args.seed}, sparse at {args.resize} px", cols, rows)
    n = len(pairs)
    print(
        f"turn with the most right matches picked: full-strength anchors {agree['full']}/{n} "
        f"({seconds['full'] / (4 * n):.2f} s a call), probe ({m.config.probe_keypoints} strongest "
        f"keypoints, pruned) {agree['probe']}/{n} ({seconds['probe'] / (4 * n):.2f} s a call)"
    )


if __name__ == "__main__":
    main()
