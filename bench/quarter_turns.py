"""How many matches are right when one image of a pair is turned by a quarter turn (synthetic scene).

    python bench/quarter_turns.py --seed 0 --aerial 3 --ground 6

Renders the scene of ``geomatch demo``, matches every aerial x aerial pair and every pair of the
nadir image(s) with the ground views with ``sparse``, the second image turned by 0/90/180/270
degrees counter-clockwise, maps its keypoints back and counts the matches within 3 px of the
rendered truth (bench/synth_precision.correct). Shows why pairs with an aerial side are matched at
their best quarter turn (geomatch/rotation.py).
"""

from __future__ import annotations

import argparse
import itertools

from common import print_table
from synth_precision import correct

from geomatch import Matcher, MatcherConfig
from geomatch.rotation import TURNS, points_back, quarter_turn
from geomatch.synth import Scene


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--aerial", type=int, default=3)
    ap.add_argument("--ground", type=int, default=6)
    ap.add_argument("--resize", type=int, default=640)
    args = ap.parse_args()
    scene = Scene(args.seed)
    cams = {c.name: c for c in scene.cameras(args.aerial, args.ground, 640, 480)}
    renders = {n: scene.render(c) for n, c in cams.items()}
    aerial = sorted(n for n, c in cams.items() if c.aerial)
    nadir = [n for i, n in enumerate(aerial) if i % 3 == 2]  # synth.Scene.cameras: every third
    ground = sorted(n for n, c in cams.items() if not c.aerial)
    pairs = list(itertools.combinations(aerial, 2)) + [(a, g) for a in nadir for g in ground]
    m = Matcher(MatcherConfig(method="sparse", resize=args.resize))
    rows = []
    for a, b in pairs:
        row: dict[str, object] = {"pair": f"{a} x {b}"}
        img_b = renders[b][0]
        for t in TURNS:
            r = m.match(renders[a][0], quarter_turn(img_b, t))
            k1 = points_back(r.keypoints1, t, img_b.shape[1], img_b.shape[0])
            ok = correct(cams[a], renders[a][1], cams[b], renders[b][1], r.keypoints0, k1, 3.0)
            row[f"t{t}"] = f"{len(r)} ({int(ok.sum())} right)"
        rows.append(row)
        print(row, flush=True)
    cols = [("pair", "pair", "s")] + [(f"{90 * t} deg", f"t{t}", "s") for t in TURNS]
    print_table(f"quarter turns, scene seed {args.seed}, sparse at {args.resize} px", cols, rows)


if __name__ == "__main__":
    main()
