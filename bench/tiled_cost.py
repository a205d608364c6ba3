"""What tiling costs: a tiled aerial x ground pair against the same pair untiled and against a
ground x ground pair, matched in project order (features reused across partners, as in a run).

    OMP_NUM_THREADS=2 python bench/tiled_cost.py [--aerial 2 --ground 4 --seed 0] [--resize 640]

One synthetic scene (``geomatch synth``, the demo's renderer). Each row is one way of matching
the scene's aerial x ground pairs, with a fresh matcher (networks loaded beforehand, not timed):
``tile_crops=probe`` (the default: only the crops where the crop probe's F-consistent matches
lie), ``tile_crops=all`` (all five crops), and ``tiling off`` (one match of the whole images).
The ground x ground pairs are matched once more by each row's matcher, after its aerial pairs, so
"plain pair" is measured under the same load. Every pair with an aerial side gets its quarter turn
(rotation.best_turn) in every row. "right" counts matches within 3 px of the truth (the renderer's depth
and poses, bench/synth_precision.correct), so a row that saves time by losing the overlap shows it.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from common import print_table
from synth_precision import correct

from geomatch.imagefolder import Images, list_images
from geomatch.matching.matcher import Matcher, config_from_options
from geomatch.metadata import read_metadata
from geomatch.pipeline import match_pairs
from geomatch.pipeline import plan as planning
from geomatch.pipeline.aerial import aerial_set, captures
from geomatch.pipeline.project import PlanRequest, ProjectImages
from geomatch.synth.aerial import Scene, write_scene

ROWS = [
    ("tiled, tile_crops=probe", "auto", "probe"),
    ("tiled, tile_crops=all", "auto", "all"),
    ("untiled (tiling off)", "off", "probe"),
]

COLUMNS = [
    ("pairs", "label", "s"),
    ("aerial x ground pairs", "n", "d"),
    ("s / aerial x ground pair", "pair_s", ".2f"),
    ("s / ground x ground pair", "plain_s", ".2f"),
    ("aerial x ground / ground x ground", "over_plain", ".2f"),
    ("aerial x ground / untiled same pair", "over_untiled", ".2f"),
    ("crops matched / pair", "crops", ".1f"),
    ("matches / pair", "matches", ".0f"),
    ("right / pair", "right", ".0f"),
]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--aerial", type=int, default=2)
    ap.add_argument("--ground", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--resize", type=int, default=640)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        scene = Path(tmp)
        cams = {c.name: c for c in write_scene(scene, args.aerial, args.ground, args.seed)}
        renderer = Scene(args.seed)
        depth = {n: renderer.render(c)[1] for n, c in cams.items()}
        image_dir = scene / "images"
        names = list_images(image_dir)
        aerial_names = [n for n in (scene / "aerial.txt").read_text().split() if n]
        metas = {n: read_metadata(image_dir / n) for n in names}
        aerial = aerial_set(captures(names, aerial_names, None), metas)
        rows = []
        for label, tiling, mode in ROWS:
            m = Matcher(config_from_options(method="geo", resize=args.resize, device="cpu", tile_crops=mode))
            images = Images(image_dir)
            warm = images[names[0]]
            m.match(warm, warm)  # networks loaded, not timed
            m.clear_caches()
            project = ProjectImages(image_dir, names, metas, None)
            planned = planning.plan(project, aerial, PlanRequest("exhaustive", None, tiling), m, images)
            ag = [p for p in planned if (p.name0 in aerial) != (p.name1 in aerial)]
            gg = [p for p in planned if p.name0 not in aerial and p.name1 not in aerial]
            secs, crops, matches, right = [], [], [], []
            for p in ag:
                t0 = time.perf_counter()
                r = match_pairs.match(m, p, images[p.name0], images[p.name1])
                secs.append(time.perf_counter() - t0)
                crops.append(r.crops)
                matches.append(len(r))
                c0, c1 = cams[p.name0], cams[p.name1]
                ok = correct(c0, depth[p.name0], c1, depth[p.name1], r.keypoints0, r.keypoints1, 3.0)
                right.append(int(np.sum(ok)))
            plain = []
            for p in gg:
                t0 = time.perf_counter()
                match_pairs.match(m, p, images[p.name0], images[p.name1])
                plain.append(time.perf_counter() - t0)
            rows.append(
                dict(
                    label=label,
                    n=len(ag),
                    pair_s=float(np.mean(secs)),
                    plain_s=float(np.mean(plain)),
                    over_plain=float(np.mean(secs) / np.mean(plain)),
                    crops=float(np.mean(crops)),
                    matches=float(np.mean(matches)),
                    right=float(np.mean(right)),
                )
            )
            print(f"{label}: {rows[-1]}", flush=True)
    untiled = rows[-1]["pair_s"]
    for r in rows:
        r["over_untiled"] = r["pair_s"] / untiled
    print_table(
        f"Tiling's cost, synthetic scene {args.aerial} aerial + {args.ground} ground, seed {args.seed}, "
        f"{args.resize} px, geo, CPU",
        COLUMNS,
        rows,
    )


if __name__ == "__main__":
    main()
