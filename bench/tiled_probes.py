"""What the cheap probes of a tiled pair say, beside what the pair came to: the data a rule that
skips tiled pairs sharing nothing would be tuned on.

A tiled pair (aerial x ground) first ranks the aerial image's quarter turns with the cheap probe,
and with four full-strength LightGlue calls where the probe is not clear-cut
(matching.rotation.best_turn), then probes the five crops of the turned aerial image
(matching.probes.crop_probe_points): where fewer than ``tiling.SELECT_MIN_PROBE`` probe matches
come back, every crop is matched at full strength, the dearest path a tiled pair takes. This
prints, for each tiled pair of scenes ``bench/air_ground_sweep.py`` has run (their databases
under bench/out/air_ground_sweep), the probe and anchor counts, the turn, the crop probe's
matches, the seconds the probes took, and the pair's verified inliers and the share of them on
the ground truth's epipolar lines (geomatch/eval/pairtruth.py). Tuning seeds only.

    python bench/air_ground_sweep.py --layouts 2+6 --seeds 1,6     # the scenes and databases
    OMP_NUM_THREADS=1 python bench/tiled_probes.py --layout 2+6 --seeds 1,6
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
from air_ground_sweep import OUT, seeds
from common import print_table

from geomatch.eval.pairtruth import epipolar_distances, gt_fundamental
from geomatch.imageio import read_image
from geomatch.matching import rotation
from geomatch.matching.matcher import Matcher
from geomatch.matching.probes import crop_probe_points
from geomatch.matching.tiling import SELECT_MIN_PROBE
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
    ("on the true lines", "agree", "s"),
]


def verified(database: Path, gt: pycolmap.Reconstruction) -> dict[frozenset[str], tuple[int, float]]:
    """Each verified pair's inliers and their share within 4 px of the true epipolar lines."""
    db = pycolmap.Database.open(str(database))
    try:
        names = {im.image_id: im.name for im in db.read_all_images()}
        kps = {i: db.read_keypoints(i)[:, :2] - 0.5 for i in names}  # COLMAP pixel centres at .5
        out = {}
        for pid, g in zip(*db.read_two_view_geometries(), strict=True):
            a, b = pycolmap.pair_id_to_image_pair(pid)
            inl = g.inlier_matches
            F = gt_fundamental(gt, names[a], names[b])
            if F is None or not len(inl):
                continue
            d = epipolar_distances(F, kps[a][inl[:, 0]], kps[b][inl[:, 1]])
            out[frozenset((names[a], names[b]))] = (len(inl), float((d < 4.0).mean()))
        return out
    finally:
        db.close()


def probe_pair(matcher: Matcher, aerial: np.ndarray, ground: np.ndarray) -> dict[str, Any]:
    """The probes as a tiled pair runs them (probes.tiled_turn, then the crop probe)."""
    t0 = time.perf_counter()
    probe = [rotation.probe_count(matcher, ground, rotation.quarter_turn(aerial, t)) for t in rotation.TURNS]
    best, runner_up = sorted(probe, reverse=True)[:2]
    anchors: list[int] | None = None
    if best >= rotation.PROBE_MARGIN * max(runner_up, 1):
        turn = int(np.argmax(probe))
    else:
        anchors = [
            rotation.anchor_count(matcher, ground, rotation.quarter_turn(aerial, t)) for t in rotation.TURNS
        ]
        turn = int(np.argmax(anchors))
    crop_probe = len(crop_probe_points(matcher, rotation.quarter_turn(aerial, turn), ground))
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
        runs = sorted(scene.glob("run_*/database.db"))
        if not runs:
            raise SystemExit(f"{scene}: no run; run bench/air_ground_sweep.py on this seed first")
        truth = verified(runs[0], pycolmap.Reconstruction(str(scene / "gt")))
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
    print_table(
        f"Tiled pairs' probes ({args.layout}; all five crops matched below {SELECT_MIN_PROBE})", COLUMNS, rows
    )
    weak = [r for r in rows if r["crop_probe"] < SELECT_MIN_PROBE]
    print(
        f"\n{len(weak)} of {len(rows)} tiled pairs under {SELECT_MIN_PROBE} crop-probe matches, "
        f"{sum(r['inliers'] > 0 for r in weak)} of them verified; "
        f"verified pairs' fewest crop-probe matches: "
        f"{min((r['crop_probe'] for r in rows if r['inliers']), default='-')}"
    )


if __name__ == "__main__":
    main()
