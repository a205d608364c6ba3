"""Air-to-ground over many synthetic scenes: the distribution of correct cameras, not four seeds.

Each seed of each layout (``A+G``: aerial + ground images) is rendered by ``geomatch synth`` and run
as a user runs it, ``geomatch run`` with its defaults (method ``auto``, the default plan, tiling,
the view-graph checks). A camera counts when it is CORRECT (geomatch/eval/metrics.py: <= 3 deg and
<= 5 % of the scene extent after a robust alignment). Beside the cameras: the verified pairs the
ground truth's epipolar geometry calls wrong, and how many of them reached the mapper
(geomatch/eval/pairtruth.py). Tuning seeds (``--seeds``) and test seeds (``--test-seeds``) are
reported apart; tune on the first only.

Raw pair matches are cached per scene under bench/out/air_ground_sweep, keyed by the pixels, the
pair and the matcher's config, so a re-run after a change re-matches only the pairs it changes.
``--tiled-floor N`` writes the tiled pairs with dbwrite.TILED_MIN_INLIERS set to N (0: COLMAP's own
floor only), the ablation row of that floor; ``--min-pose-inliers N`` maps with that PnP minimum
(RunOptions.min_pose_inliers; 0: the default); neither matches anything again. ``--tile-min-probe N``
matches with MatcherConfig.tile_min_probe set to N (0: a tiled pair whose crop probe finds too few
matches matches all five crops instead of none), the ablation row of that skip.

    python bench/air_ground_sweep.py --layouts 2+4 --seeds 4242,1,2 --test-seeds 100,101
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path
from typing import Any

import matchcache
import numpy as np
import pycolmap
from common import print_table

from geomatch import dbwrite
from geomatch.eval.evaluate import evaluate_run
from geomatch.eval.pairtruth import judge_pairs
from geomatch.pipeline import RunOptions, run
from geomatch.synth.aerial import write_scene

OUT = Path(__file__).parent / "out" / "air_ground_sweep"

SEED_COLUMNS = [
    ("layout", "layout", "s"),
    ("split", "split", "s"),
    ("seed", "seed", "s"),
    ("correct", "corr", "s"),
    ("registered", "reg", "s"),
    ("verified pairs", "verified", "d"),
    ("wrong verified", "wrong", "d"),
    ("wrong mapped", "wrong_used", "d"),
    ("right dropped", "right_dropped", "d"),
    ("tiled verified (wrong)", "tiled", "s"),
    ("cameras wrong / left out", "cameras_off", "s"),
    ("matching s", "matching_s", ".0f"),
]

SUMMARY_COLUMNS = [
    ("layout", "layout", "s"),
    ("split", "split", "s"),
    ("seeds", "seeds", "d"),
    ("cameras correct", "cameras", "s"),
    ("% correct", "percent", ".1f"),
    ("seeds all correct", "all_correct", "d"),
    ("seeds below 5/6", "below", "d"),
    ("worst seed", "worst", "s"),
    ("wrong mapped (sum)", "wrong_used", "d"),
    ("matching s / seed", "matching_s", ".0f"),
]


def run_seed(
    layout: str, seed: int, split: str, min_pose_inliers: int = 0, matcher: dict[str, Any] | None = None
) -> dict[str, Any]:
    n_aerial, n_ground = (int(x) for x in layout.split("+"))
    scene = OUT / f"scene_a{n_aerial}_g{n_ground}_s{seed}"
    if not (scene / "gt" / "images.txt").is_file():
        write_scene(scene, n_aerial, n_ground, seed)
    extra = "".join(f"_{k}{v}" for k, v in sorted((matcher or {}).items()))
    out = scene / f"run_floor{dbwrite.TILED_MIN_INLIERS}_pnp{min_pose_inliers}{extra}"
    shutil.rmtree(out, ignore_errors=True)  # a fresh database; raw matches come from the cache
    opts = RunOptions(progress=False, min_pose_inliers=min_pose_inliers, matcher=dict(matcher or {}))
    s = run(scene / "images", out, opts, match=matchcache.cached(scene / "matches"))
    m = evaluate_run(out, scene / "gt").metrics
    gt = pycolmap.Reconstruction(str(scene / "gt"))
    aerial = set(s["aerial"])
    tiled = [v for v in judge_pairs(out / "database.db", gt) if (v.name0 in aerial) != (v.name1 in aerial)]
    pairs = m.get("pairs") or {}
    row = {
        "layout": layout,
        "split": split,
        "seed": str(seed),
        "correct": m["correct"],
        "images": m["images"],
        "corr": f"{m['correct']}/{m['images']}",
        "reg": f"{m['registered']}/{m['images']}",
        "verified": pairs.get("verified_pairs", 0),
        "wrong": pairs.get("wrong_pairs", 0),
        "wrong_used": pairs.get("wrong_pairs_admitted", 0),
        "right_dropped": pairs.get("right_pairs_dropped", 0),
        "tiled": f"{len(tiled)} ({sum(v.wrong for v in tiled)})",
        "cameras_off": " ".join(
            [f"{n.split('.')[0]} wrong" for n in sorted(m.get("wrong") or {})]
            + [f"{n.split('.')[0]} out" for n in sorted(s.get("unregistered_names") or [])]
        )
        or "-",
        "matching_s": s["timings"]["matching"],
        "wrong_pairs": pairs.get("wrong", []),
    }
    print(json.dumps({k: v for k, v in row.items() if k != "wrong_pairs"}), flush=True)
    return row


def summarise(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    out = []
    for layout in dict.fromkeys(r["layout"] for r in rows):
        for split in ("tuning", "test"):
            rs = [r for r in rows if r["layout"] == layout and r["split"] == split]
            if not rs:
                continue
            correct = sum(r["correct"] for r in rs)
            images = sum(r["images"] for r in rs)
            worst = min(rs, key=lambda r: r["correct"] / r["images"])
            out.append(
                {
                    "layout": layout,
                    "split": split,
                    "seeds": len(rs),
                    "cameras": f"{correct}/{images}",
                    "percent": 100.0 * correct / images,
                    "all_correct": sum(r["correct"] == r["images"] for r in rs),
                    "below": sum(r["correct"] / r["images"] < 5 / 6 for r in rs),
                    "worst": f"{worst['corr']} (seed {worst['seed']})",
                    "wrong_used": sum(r["wrong_used"] for r in rs),
                    "matching_s": float(np.mean([r["matching_s"] for r in rs])),
                }
            )
    return out


def seeds(spec: str) -> list[int]:
    """``1,2,5`` or a range ``100-119``, or both (``1,2,100-104``)."""
    out: list[int] = []
    for part in filter(None, spec.split(",")):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi) + 1)) if hi else [int(lo)]
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--layouts", default="2+4,2+6,4+8", help="aerial+ground per scene, comma-separated")
    ap.add_argument("--seeds", default="4242,1-9", help="tuning seeds")
    ap.add_argument("--test-seeds", default="", help="test seeds, reported apart (never tune on them)")
    ap.add_argument("--tiled-floor", type=int, help="dbwrite.TILED_MIN_INLIERS for this run")
    ap.add_argument("--min-pose-inliers", type=int, default=0, help="PnP minimum (0: the default)")
    ap.add_argument("--tile-min-probe", type=int, help="MatcherConfig.tile_min_probe for this run")
    ap.add_argument("--json", type=Path, help="append each seed's row to this JSON-lines file")
    args = ap.parse_args()
    if args.tiled_floor is not None:
        dbwrite.TILED_MIN_INLIERS = args.tiled_floor
    matcher = {} if args.tile_min_probe is None else {"tile_min_probe": args.tile_min_probe}
    rows = []
    t0 = time.perf_counter()
    for layout in args.layouts.split(","):
        for split, spec in (("tuning", args.seeds), ("test", args.test_seeds)):
            for seed in seeds(spec):
                row = run_seed(layout, seed, split, args.min_pose_inliers, matcher)
                rows.append(row)
                if args.json:
                    with args.json.open("a") as f:
                        f.write(json.dumps(row) + "\n")
    label = f"defaults, tiled pairs verified from {dbwrite.TILED_MIN_INLIERS} inliers"
    if args.min_pose_inliers:
        label += f", PnP minimum {args.min_pose_inliers}"
    if matcher:
        label += ", " + ", ".join(f"{k} {v}" for k, v in matcher.items())
    print_table(f"Air-to-ground sweep, geomatch run ({label}), per seed", SEED_COLUMNS, rows)
    print_table(
        f"Air-to-ground sweep ({label}): correct = <= 3 deg and <= 5% of the scene extent; "
        f"{time.perf_counter() - t0:.0f} s",
        SUMMARY_COLUMNS,
        summarise(rows),
    )


if __name__ == "__main__":
    main()
