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
``--tiled-floor N`` writes the tiled pairs with database.TILED_MIN_INLIERS set to N (0: COLMAP's own
floor only), the ablation row of that floor; ``--min-pose-inliers N`` maps with that PnP minimum
(RunOptions.min_pose_inliers; 0: the default); neither matches anything again. ``--tile-min-probe N``
matches with MatcherConfig.tile_min_probe set to N (0: a tiled pair whose crop probe finds too few
matches matches all five crops instead of none), the ablation row of that skip.

``--drop K`` runs each scene with K of its ground photos left out, chosen at random by
``--drop-seeds`` (one case per drop seed and scene), as a user who photographed less would: the
model is judged against the ground truth of the photos it was given, and "wrong in model" counts
the cameras it wrote that are not correct (registered but off), which a user cannot tell from the
right ones. The subsets read the whole scene's match cache, so one matching of a scene serves all
its drops. Subsets are tuned and tested on scene seeds of their own: 300-309 for tuning, 400-419
for test (never the seeds the tables above tune on).

    python bench/air_ground_sweep.py --layouts 2+4 --seeds 4242,1,2 --test-seeds 100,101
    python bench/air_ground_sweep.py --layouts 2+6 --drop 2 --drop-seeds 0-2 --seeds 300 --test-seeds 400-403
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from itertools import combinations
from pathlib import Path
from typing import Any

import matchcache
import numpy as np
import pycolmap
from common import print_table

from geomatch.eval.evaluate import evaluate_run
from geomatch.eval.pairtruth import judge_pairs
from geomatch.pipeline import RunOptions, database, run
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
    ("wrong in model", "wrong_cams", "d"),
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
    ("wrong in model (cases)", "wrong_cams", "s"),
    ("wrong mapped (sum)", "wrong_used", "d"),
    ("matching s / seed", "matching_s", ".0f"),
]


def subset(scene: Path, seed: int, drop: int, drop_seed: int) -> tuple[Path, list[str]]:
    """The folder of ``scene`` (rendered from ``seed``) with ``drop`` ground photos left out, chosen
    at random by the scene's seed and ``drop_seed``:
    its ``images`` (hard links to the scene's) and its ``gt`` (the scene's truth without them);
    the names left out."""
    gt = pycolmap.Reconstruction(str(scene / "gt"))
    ground = sorted(im.name for im in gt.images.values() if im.name.startswith("ground"))
    # every way to leave ``drop`` out, in an order shuffled by the scene's seed: drop seeds 0, 1, ...
    # are different subsets as long as there are
    ways = list(combinations(ground, min(drop, len(ground))))
    order = np.random.default_rng([seed, drop]).permutation(len(ways))
    left = sorted(ways[int(order[drop_seed % len(ways)])])
    into = scene / f"drop{drop}_d{drop_seed}"
    if not (into / "gt" / "images.txt").is_file():
        shutil.rmtree(into, ignore_errors=True)
        (into / "images").mkdir(parents=True)
        for photo in sorted((scene / "images").iterdir()):
            if photo.name not in left:
                (into / "images" / photo.name).hardlink_to(photo)
        for im in list(gt.images.values()):
            if im.name in left:
                gt.deregister_frame(im.frame_id)
        (into / "gt").mkdir()
        gt.write_text(str(into / "gt"))  # a written model keeps its posed images only
    return into, left


def run_seed(
    layout: str,
    seed: int,
    split: str,
    min_pose_inliers: int = 0,
    matcher: dict[str, Any] | None = None,
    drop: int = 0,
    drop_seed: int = 0,
) -> dict[str, Any]:
    n_aerial, n_ground = (int(x) for x in layout.split("+"))
    scene = OUT / f"scene_a{n_aerial}_g{n_ground}_s{seed}"
    if not (scene / "gt" / "images.txt").is_file():
        write_scene(scene, n_aerial, n_ground, seed)
    case, left = subset(scene, seed, drop, drop_seed) if drop else (scene, [])
    extra = "".join(f"_{k}{v}" for k, v in sorted((matcher or {}).items()))
    out = case / f"run_floor{database.TILED_MIN_INLIERS}_pnp{min_pose_inliers}{extra}"
    shutil.rmtree(out, ignore_errors=True)  # a fresh database; raw matches come from the cache
    opts = RunOptions(progress=False, min_pose_inliers=min_pose_inliers, matcher=dict(matcher or {}))
    s = run(case / "images", out, opts, match=matchcache.cached(scene / "matches"))
    m = evaluate_run(out, case / "gt").metrics
    gt = pycolmap.Reconstruction(str(case / "gt"))
    aerial = set(s["aerial"])
    tiled = [v for v in judge_pairs(out / "database.db", gt) if (v.name0 in aerial) != (v.name1 in aerial)]
    pairs = m.get("pairs") or {}
    row = {
        "layout": layout,
        "split": split,
        "seed": f"{seed} -{','.join(n.split('.')[0].removeprefix('ground_') for n in left)}"
        if drop
        else str(seed),
        "dropped": left,
        "correct": m["correct"],
        "images": m["images"],
        "corr": f"{m['correct']}/{m['images']}",
        "reg": f"{m['registered']}/{m['images']}",
        "verified": pairs.get("verified_pairs", 0),
        "wrong": pairs.get("wrong_pairs", 0),
        "wrong_used": pairs.get("wrong_pairs_admitted", 0),
        "right_dropped": pairs.get("right_pairs_dropped", 0),
        "wrong_cams": len(m.get("wrong") or {}),
        "wrong_names": sorted(m.get("wrong") or {}),
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
                    "wrong_cams": f"{sum(r['wrong_cams'] for r in rs)} "
                    f"({sum(r['wrong_cams'] > 0 for r in rs)})",
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
    ap.add_argument("--tiled-floor", type=int, help="database.TILED_MIN_INLIERS for this run")
    ap.add_argument("--min-pose-inliers", type=int, default=0, help="PnP minimum (0: the default)")
    ap.add_argument("--tile-min-probe", type=int, help="MatcherConfig.tile_min_probe for this run")
    ap.add_argument("--drop", type=int, default=0, help="ground photos left out of each scene (0: none)")
    ap.add_argument("--drop-seeds", default="0", help="with --drop: which photos, one case per seed")
    ap.add_argument("--json", type=Path, help="append each seed's row to this JSON-lines file")
    args = ap.parse_args()
    if args.tiled_floor is not None:
        database.TILED_MIN_INLIERS = args.tiled_floor
    matcher = {} if args.tile_min_probe is None else {"tile_min_probe": args.tile_min_probe}
    rows = []
    t0 = time.perf_counter()
    for layout in args.layouts.split(","):
        for split, spec in (("tuning", args.seeds), ("test", args.test_seeds)):
            for seed in seeds(spec):
                for drop_seed in seeds(args.drop_seeds) if args.drop else [0]:
                    row = run_seed(layout, seed, split, args.min_pose_inliers, matcher, args.drop, drop_seed)
                    rows.append(row)
                    if args.json:
                        with args.json.open("a") as f:
                            f.write(json.dumps(row) + "\n")
    label = f"defaults, tiled pairs verified from {database.TILED_MIN_INLIERS} inliers"
    if args.min_pose_inliers:
        label += f", PnP minimum {args.min_pose_inliers}"
    if matcher:
        label += ", " + ", ".join(f"{k} {v}" for k, v in matcher.items())
    if args.drop:
        label += f", {args.drop} ground photo(s) left out (drop seeds {args.drop_seeds})"
    print_table(f"Air-to-ground sweep, geomatch run ({label}), per seed", SEED_COLUMNS, rows)
    print_table(
        f"Air-to-ground sweep ({label}): correct = <= 3 deg and <= 5% of the scene extent; "
        f"{time.perf_counter() - t0:.0f} s",
        SUMMARY_COLUMNS,
        summarise(rows),
    )


if __name__ == "__main__":
    main()
