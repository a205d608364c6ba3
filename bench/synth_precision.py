"""Match precision against the rendered ground truth of a synthetic scene, per pair kind.

A match (p0 in image A, p1 in image B) is correct when A's rendered depth at p0, back-projected
and projected into B, lands within ``--px`` pixels of p1 and B's own depth there agrees (the point
is not occluded in B). This is the check behind every claim about air-to-ground matching: a
registration count alone can be fooled by repeated texture.

    python bench/synth_precision.py --seed 1 --aerial 2 --ground 4 --methods sparse,geo
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict
from pathlib import Path

import matchcache
import numpy as np
from common import print_table

from geomatch.matching.matcher import Matcher, config_from_options
from geomatch.pipeline import pair_sources as pairing
from geomatch.synth.aerial import Scene, covisibility, write_scene
from geomatch.synth.camera import Camera

OUT = Path(__file__).parent / "out" / "synth_precision"


def correct(
    cam_a: Camera,
    depth_a: np.ndarray,
    cam_b: Camera,
    depth_b: np.ndarray,
    k0: np.ndarray,
    k1: np.ndarray,
    px: float,
) -> np.ndarray:
    """Boolean per match: consistent with the true geometry within ``px``."""
    if len(k0) == 0:
        return np.zeros(0, bool)
    u = np.clip(np.round(k0[:, 0]).astype(int), 0, cam_a.width - 1)
    v = np.clip(np.round(k0[:, 1]).astype(int), 0, cam_a.height - 1)
    d = depth_a[v, u]
    ok = np.isfinite(d)
    pix = np.stack([k0[:, 0] + 0.5, k0[:, 1] + 0.5, np.ones(len(k0))], 1)
    X = (pix @ np.linalg.inv(cam_a.K).T * np.where(ok, d, 1.0)[:, None] - cam_a.t) @ cam_a.R
    uv, z = cam_b.project(X)
    ub = np.clip(np.round(uv[:, 0]).astype(int), 0, cam_b.width - 1)
    vb = np.clip(np.round(uv[:, 1]).astype(int), 0, cam_b.height - 1)
    visible = np.abs(depth_b[vb, ub] - z) < 0.03 * np.abs(z)
    return ok & (z > 0) & visible & (np.linalg.norm(uv - k1, axis=1) < px)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--aerial", type=int, default=2)
    ap.add_argument("--ground", type=int, default=4)
    ap.add_argument("--methods", default="sparse,geo")
    ap.add_argument("--px", type=float, default=3.0)
    ap.add_argument("--kinds", default="AA,AG,GG", help="pair kinds to match: AA, AG, GG")
    ap.add_argument("--per-pair", action="store_true", help="print every pair")
    args = ap.parse_args()
    scene_dir = OUT / f"scene_a{args.aerial}_g{args.ground}_s{args.seed}"
    cams = write_scene(scene_dir, args.aerial, args.ground, args.seed)
    scene = Scene(args.seed)
    depth = {c.name: scene.render(c)[1] for c in cams}
    covis = covisibility(scene, cams)
    byname = {c.name: c for c in cams}
    aerial = {c.name for c in cams if c.aerial}
    names = [c.name for c in cams]
    planned = pairing.finalize(pairing.exhaustive(names), aerial, "auto")
    from geomatch.imageio import read_image

    images = {n: read_image(scene_dir / "images" / n) for n in names}
    rows = []
    for method in args.methods.split(","):
        matcher = Matcher(config_from_options(method=method, resize=640))
        agg: dict[str, list[float]] = defaultdict(lambda: [0, 0, 0, 0, 0.0])
        for p in planned:
            kind = "".join(sorted("A" if n in aerial else "G" for n in (p.name0, p.name1)))
            if kind not in args.kinds.split(","):
                continue
            t0 = time.perf_counter()
            m = matchcache.match(matcher, p, images[p.name0], images[p.name1], OUT / "cache")
            k0, k1 = m.keypoints0, m.keypoints1
            dt = time.perf_counter() - t0
            a, b = byname[p.name0], byname[p.name1]
            ok = correct(a, depth[a.name], b, depth[b.name], k0, k1, args.px)
            i, j = names.index(a.name), names.index(b.name)
            overlap = min(covis[i, j], covis[j, i]) > 0.05
            key = f"{kind} {'covisible' if overlap else 'not covisible'}"
            s = agg[key]
            s[0] += 1
            s[1] += len(ok)
            s[2] += int(ok.sum())
            s[3] += int(ok.sum() >= 30)
            s[4] += dt
            if args.per_pair:
                print(
                    f"{method:8s} {a.name} {b.name} covis {covis[i, j]:.2f}/{covis[j, i]:.2f} "
                    f"matches {len(ok):5d} correct {int(ok.sum()):5d}"
                )
        for key, (n, m, c, good, dt) in sorted(agg.items()):
            rows.append(
                {
                    "method": method,
                    "kind": key,
                    "pairs": int(n),
                    "matches": m / n,
                    "correct": c / n,
                    "precision": c / max(m, 1),
                    "good": f"{int(good)}/{int(n)}",
                    "s": dt / n,
                }
            )
    print_table(
        f"match precision vs rendered ground truth ({args.px:g} px), seed {args.seed}, "
        f"{args.aerial} aerial + {args.ground} ground",
        [
            ("method", "method", "s"),
            ("pair kind", "kind", "s"),
            ("pairs", "pairs", "d"),
            ("matches/pair", "matches", ".0f"),
            ("correct/pair", "correct", ".0f"),
            ("precision", "precision", "%"),
            ("pairs with >=30 correct", "good", "s"),
            ("s/pair", "s", ".1f"),
        ],
        rows,
    )


if __name__ == "__main__":
    main()
