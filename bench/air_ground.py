"""The paper's air-to-ground table on synthetic scenes with ground truth.

For each seed: render a scene (``geomatch synth``), run the pipeline with each method and
evaluate. A camera counts when it is CORRECT (geomatch/eval/metrics.py: <= 3 deg and <= 5 % of the
scene extent after a robust alignment), not merely registered; both are reported, with the tuning seeds
(``--seeds``) and the test seeds (``--test-seeds``) in separate rows and separate means. Raw pair
matches are cached per scene and method under bench/out, so the extra rows (no keypoint
consolidation, no tiling, global mapper) re-use them or add only what differs.

Pair plans (``--plan``): ``exhaustive`` matches every pair (6 + 10 images: 120 pairs, 60 of them
tiled at ~5 LightGlue calls each: ~15 min per method and seed on 2 CPU cores). ``nearby:K`` is
what a capture with GPS allows (hloc's pairs-from-poses): every aerial x aerial pair, each ground
image with the next K along the walk, and each ground image with its K aerial images nearest in
horizontal position. Positions are the ground-truth centres standing in for GPS; covisibility is
NOT used, so pairs that see different things stay in the plan (as they would with real GPS).

    python bench/air_ground.py --seeds 0 --test-seeds 100 --aerial 6 --ground 10 --methods geo \\
        --plan nearby:3 --extra ''
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import time
from dataclasses import fields
from pathlib import Path
from typing import Any

import matchcache
import numpy as np
from common import parse_value, print_table

from geomatch.eval.evaluate import evaluate_run
from geomatch.pipeline import RunOptions, run
from geomatch.synth.aerial import Scene, write_scene
from geomatch.synth.camera import Camera

OUT = Path(__file__).parent / "out" / "air_ground"

COLUMNS = [
    ("split", "split", "s"),
    ("seed", "seed", "s"),
    ("method", "label", "s"),
    ("correct", "corr", "s"),
    ("registered", "reg", "s"),
    ("other models correct", "others", "s"),
    ("3D points", "points3D", ".0f"),
    ("mean track length", "mean_track_length", ".2f"),
    ("mean reproj. error px", "mean_reprojection_error", ".3f"),
    ("AUC@3", "auc@3", ".1f"),
    ("AUC@5", "auc@5", ".1f"),
    ("AUC@10", "auc@10", ".1f"),
    ("matching s", "matching_s", ".0f"),
]


def nearby_pairs(cams: list[Camera], k: int) -> list[list[str]]:
    """The ``nearby:K`` plan of the module docstring, from camera centres (GPS stand-in)."""
    aerial = [c for c in cams if c.aerial]
    ground = [c for c in cams if not c.aerial]
    pairs = [[a.name, b.name] for i, a in enumerate(aerial) for b in aerial[i + 1 :]]
    pairs += [[g.name, h.name] for i, g in enumerate(ground) for h in ground[i + 1 : i + 1 + k]]
    for g in ground:
        dist = [float(np.linalg.norm(a.centre[:2] - g.centre[:2])) for a in aerial]
        pairs += [[aerial[i].name, g.name] for i in np.argsort(dist, kind="stable")[:k]]
    return pairs


def plan(spec: str, cams: list[Camera]) -> list[list[str]] | None:
    """None: exhaustive (the pipeline's own plan); else an explicit list."""
    if spec == "exhaustive":
        return None
    m = re.fullmatch(r"nearby:(\d+)", spec)
    if not m:
        raise SystemExit(f"unknown plan {spec!r}: exhaustive or nearby:K")
    return nearby_pairs(cams, int(m.group(1)))


def run_seed(
    seed: int, split: str, args: argparse.Namespace, variants: list[tuple[str, str, dict[str, Any]]]
) -> list[dict[str, Any]]:
    scene = OUT / f"scene_a{args.aerial}_g{args.ground}_s{seed}"
    if not (scene / "gt" / "images.txt").is_file():
        write_scene(scene, args.aerial, args.ground, seed)
    cams = Scene(seed).cameras(args.aerial, args.ground, 640, 480)
    pairs_list = plan(args.plan, cams)
    aerial = (scene / "aerial.txt").read_text().split()
    rows = []
    for label, method, extra in variants:
        tag = label.replace(" ", "_").replace("=", "-")
        out = scene / "runs" / f"{args.plan.replace(':', '')}_{tag}"
        opts = RunOptions(
            method=method,
            resize=args.resize,
            aerial_names=aerial,
            pairs_list=pairs_list,
            progress=False,
            **extra,
        )
        shutil.rmtree(out, ignore_errors=True)  # a fresh database; raw matches come from the cache
        t0 = time.perf_counter()
        s = run(scene / "images", out, opts, match=matchcache.cached(scene / "matches" / method))
        m = evaluate_run(out, scene / "gt").metrics
        m.update(
            split=split,
            seed=str(seed),
            label=label,
            corr=f"{m['correct']}/{m['images']}",
            reg=f"{m['registered']}/{m['images']}",
            others=", ".join(f"{o['correct']}/{o['registered']}" for o in m["other_models"]) or "-",
            pairs=s["pairs"],
            matching_s=s["timings"]["matching"],
            wall_s=time.perf_counter() - t0,
        )
        rows.append(m)
        print(
            json.dumps(
                {
                    k: m[k]
                    for k in ("split", "seed", "label", "corr", "reg", "others", "auc@5", "pairs", "wall_s")
                }
            ),
            flush=True,
        )
    return rows


def means(rows: list[dict[str, Any]], split: str) -> list[dict[str, Any]]:
    """One row per method: correct and registered summed over the split's seeds, the rest averaged."""
    out = []
    for label in dict.fromkeys(r["label"] for r in rows):
        rs = [r for r in rows if r["label"] == label and r["split"] == split]
        if not rs:
            continue
        row: dict[str, Any] = {"split": f"{split} mean", "seed": f"{len(rs)} seeds", "label": label}
        row["corr"] = f"{sum(r['correct'] for r in rs)}/{sum(r['images'] for r in rs)}"
        row["reg"] = f"{sum(r['registered'] for r in rs)}/{sum(r['images'] for r in rs)}"
        row["others"] = "-"
        for _, key, spec in COLUMNS:
            if spec not in ("s",):
                row[key] = float(np.mean([r[key] for r in rs]))
        out.append(row)
    return out


RUN_FIELDS = {f.name for f in fields(RunOptions)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="0,1", help="tuning seeds")
    ap.add_argument("--test-seeds", default="", help="test seeds, reported apart (never tune on them)")
    ap.add_argument("--aerial", type=int, default=6)
    ap.add_argument("--ground", type=int, default=10)
    ap.add_argument("--methods", default="sparse,dense,geo")
    ap.add_argument("--plan", default="nearby:3", help="exhaustive | nearby:K (see the module docstring)")
    ap.add_argument(
        "--extra",
        default="geo:snap_radius=0;geo:tiling=off",
        help="extra rows METHOD:option=value (RunOptions or MatcherConfig fields), ';'-separated",
    )
    ap.add_argument("--resize", type=int, default=640)
    args = ap.parse_args()
    variants: list[tuple[str, str, dict[str, Any]]] = [(m, m, {}) for m in args.methods.split(",")]
    for spec in filter(None, args.extra.split(";")):
        method, kv = spec.split(":", 1)
        k, v = kv.split("=", 1)
        if k in RUN_FIELDS:
            value = parse_value(v) if k not in ("tiling", "mapper") else v
            variants.append((f"{method} {k}={v}", method, {k: value}))
        else:  # a MatcherConfig option (probe_keypoints, max_keypoints, ...)
            variants.append((f"{method} {k}={v}", method, {"matcher": {k: parse_value(v)}}))
    splits = [("tuning", s) for s in args.seeds.split(",") if s] + [
        ("test", s) for s in args.test_seeds.split(",") if s
    ]
    rows = []
    for split, seed in splits:
        rows += run_seed(int(seed), split, args, variants)
    table = rows + means(rows, "tuning") + means(rows, "test")
    OUT.mkdir(parents=True, exist_ok=True)
    name = f"table_a{args.aerial}_g{args.ground}_{args.plan.replace(':', '')}.json"
    (OUT / name).write_text(json.dumps(rows, indent=2))
    print_table(
        f"Air-to-ground, synthetic ({args.aerial} aerial + {args.ground} ground, resize {args.resize}, "
        f"pairs {args.plan}); correct = <= 3 deg and <= 5% of the scene extent after robust alignment",
        COLUMNS,
        table,
    )


if __name__ == "__main__":
    main()
