"""The paper's air-to-ground table on synthetic scenes with ground truth.

For each seed: render a scene (``geomatch synth``), run the pipeline with each method and
evaluate. Raw pair matches are cached per scene and method under bench/out, so the extra rows
(no keypoint consolidation, no tiling, global mapper) re-use them or add only what differs.

    python bench/air_ground.py --seeds 0,1 --aerial 8 --ground 12 --methods sparse,dense,geo
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

from common import print_table

from geomatch.evaluate import evaluate_run
from geomatch.pipeline import RunOptions, run
from geomatch.synth import write_scene

OUT = Path(__file__).parent / "out" / "air_ground"

COLUMNS = [
    ("seed", "seed", "d"),
    ("method", "label", "s"),
    ("registered", "reg", "s"),
    ("3D points", "points3D", "d"),
    ("mean track length", "mean_track_length", ".2f"),
    ("mean reproj. error px", "mean_reprojection_error", ".3f"),
    ("AUC@3", "auc@3", ".1f"),
    ("AUC@5", "auc@5", ".1f"),
    ("AUC@10", "auc@10", ".1f"),
    ("matching s", "matching_s", ".0f"),
]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--aerial", type=int, default=8)
    ap.add_argument("--ground", type=int, default=12)
    ap.add_argument("--methods", default="sparse,dense,geo")
    ap.add_argument(
        "--extra",
        default="geo:snap_radius=0;geo:tiling=off",
        help="extra rows METHOD:option=value (RunOptions fields), ';'-separated",
    )
    ap.add_argument("--resize", type=int, default=640)
    args = ap.parse_args()
    rows = []
    variants = [(m, m, {}) for m in args.methods.split(",")]
    for spec in filter(None, args.extra.split(";")):
        method, kv = spec.split(":", 1)
        k, v = kv.split("=", 1)
        variants.append((f"{method} {k}={v}", method, {k: float(v) if k == "snap_radius" else v}))
    for seed in (int(s) for s in args.seeds.split(",")):
        scene = OUT / f"scene_a{args.aerial}_g{args.ground}_s{seed}"
        if not (scene / "gt" / "images.txt").is_file():
            write_scene(scene, args.aerial, args.ground, seed)
        aerial = (scene / "aerial.txt").read_text().split()
        for label, method, extra in variants:
            out = scene / "runs" / label.replace(" ", "_").replace("=", "-")
            opts = RunOptions(
                method=method,
                resize=args.resize,
                aerial_names=aerial,
                match_cache=str(scene / "matches" / method),
                **extra,
            )
            shutil.rmtree(out, ignore_errors=True)  # a fresh database; raw matches come from the cache
            t0 = time.perf_counter()
            s = run(scene / "images", out, opts)
            m = evaluate_run(out, scene / "gt").metrics
            m.update(
                seed=seed,
                label=label,
                reg=f"{m['registered']}/{m['images']}",
                matching_s=s["timings"]["matching"],
                wall_s=time.perf_counter() - t0,
            )
            rows.append(m)
            print(
                json.dumps(
                    {k: m[k] for k in ("seed", "label", "reg", "points3D", "mean_track_length", "auc@5")}
                )
            )
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"table_a{args.aerial}_g{args.ground}.json").write_text(json.dumps(rows, indent=2))
    print_table(
        f"Air-to-ground, synthetic ({args.aerial} aerial + {args.ground} ground, resize {args.resize})",
        COLUMNS,
        rows,
    )


if __name__ == "__main__":
    main()
