"""What the cheap probes of a tiled pair say, beside what the pair came to: the data a rule that
skips tiled pairs sharing nothing would be tuned on.

A tiled pair (aerial x ground) first ranks the aerial image's quarter turns with the cheap probe,
and with four full-strength LightGlue calls where the probe is not clear-cut
(matching.rotation.ranked_turns), then probes the five crops of the turned aerial image
(matching.probes.crop_probe_points): where fewer than ``MatcherConfig.tile_min_probe`` probe
matches come back the pair matches no crop (with the floor off, every crop at full strength, the
dearest path a tiled pair takes). This
prints, for each tiled pair of scenes ``bench/air_ground_sweep.py`` has run (their databases
under bench/out/air_ground_sweep), the probe and anchor counts, the turn, the crop probe's
matches, the seconds the probes took, and the pair's verified inliers and the share of them on
the ground truth's epipolar lines (geomatch/eval/pairtruth.judge_pairs). Tuning seeds only.

    python bench/air_ground_sweep.py --layouts 2+6 --seeds 1,6 --tile-min-probe 0  # the databases
    OMP_NUM_THREADS=1 python bench/tiled_probes.py --layout 2+6 --seeds 1,6
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np
import pycolmap
from air_ground_sweep import OUT, seeds
from common import print_table

from geomatch.eval.pairtruth import judge_pairs
from geomatch.imageio import read_image
from geomatch.matching.matcher import Matcher
from geomatch.matching.probes import crop_probe_points
from geomatch.matching.rotation import quarter_turn, ranked_turns
from geomatch.matching.variants import for_pair

COLUMNS = [
    ("seed", "seed", "s"),
    ("aerial", "aerial", "s"),
    ("ground", "ground", "s"),
    ("turn probe (0/1/2/3)", "probe", "s"),
    ("anchors (0/1/2/3)", "anchors", "s"),
    ("turn", "turn", "d"),
    ("crop probe matches", "crop_probe", "d"),
    ("probes s", "seconds", ".1f"),
    ("verified inliers", "inliers", "d"),
    ("on the true epipolar lines", "agree", "s"),
]


def probe_pair(matcher: Matcher, aerial: np.ndarray, ground: np.ndarray) -> dict[str, Any]:
    """The probes as a tiled pair runs them (probes.tiled_turn, then the crop probe)."""
    t0 = time.perf_counter()
    turn, probe, anchors = ranked_turns(matcher, ground, aerial)
    crop_probe = len(crop_probe_points(matcher, quarter_turn(aerial, turn), ground))
    return {
        "probe": "/".join(map(str, probe)),
        "anchors": "/".join(map(str, anchors)) if anchors else "clear-cut",
        "turn": turn,
        "crop_probe": crop_probe,
        "seconds": time.perf_counter() - t0,
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--layout", default="2+6")
    ap.add_argument("--seeds", default="1,6", help="tuning seeds the sweep has run")
    args = ap.parse_args()
    n_aerial, n_ground = (int(x) for x in args.layout.split("+"))
    matcher = Matcher()
    tiled = for_pair(matcher, tiled=True, aerial_project=True)
    rows = []
    for seed in seeds(args.seeds):
        scene = OUT / f"scene_a{n_aerial}_g{n_ground}_s{seed}"
        # the run that matched all five crops under the floor, where there is one: under the default
        # a pair below the floor is never matched, so it could not show whether it would verify
        runs = sorted(
            scene.glob("run_*/database.db"), key=lambda p: ("tile_min_probe0" not in p.parent.name, p)
        )
        if not runs:
            raise SystemExit(f"{scene}: no run; run bench/air_ground_sweep.py on this seed first")
        gt = pycolmap.Reconstruction(str(scene / "gt"))
        truth = {frozenset((v.name0, v.name1)): (v.inliers, v.agreeing) for v in judge_pairs(runs[0], gt)}
        names = sorted(p.name for p in (scene / "images").iterdir())
        for a in (n for n in names if n.startswith("aerial")):
            aerial = read_image(scene / "images" / a)
            for g in (n for n in names if n.startswith("ground")):
                row = probe_pair(tiled, aerial, read_image(scene / "images" / g))
                inliers, agree = truth.get(frozenset((a, g)), (0, float("nan")))
                row |= {"seed": str(seed), "aerial": a, "ground": g, "inliers": inliers}
                row["agree"] = "-" if not inliers else f"{100 * agree:.0f} %"
                rows.append(row)
                print(row, flush=True)
                matcher.clear_caches()  # as a fresh pair: no anchors or features carried over
    floor = tiled.config.tile_min_probe
    print_table(f"Tiled pairs' probes ({args.layout}; no crop matched below {floor})", COLUMNS, rows)
    weak = [r for r in rows if r["crop_probe"] < floor]
    print(
        f"\n{len(weak)} of {len(rows)} tiled pairs under {floor} crop-probe matches, "
        f"{sum(r['inliers'] > 0 for r in weak)} of them verified; "
        f"verified pairs' fewest crop-probe matches: "
        f"{min((r['crop_probe'] for r in rows if r['inliers']), default='-')}"
    )


if __name__ == "__main__":
    main()
