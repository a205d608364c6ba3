"""Pair recall of ``gps:K`` on synthetic 200-image drone flights (poses only, no rendering).

A flight is a lawnmower survey over flat ground: parallel lines flown in alternating directions,
a 4:3 camera with a 24 mm-equivalent lens (73 deg horizontal field of view, as a DJI Mavic or
Phantom), positions jittered as a drone holds its line (GNSS noise on the fixes on top). Two
layouts: ``nadir`` (80 m, 80 % front / 70 % side overlap, the photogrammetry default) for tuning,
and ``oblique`` (60 m, gimbal 30 deg off nadir looking along the line, so the footprint flips
with the line direction; 75 % / 60 %) as the held-out test, with other seeds.

Covisibility is geometric: ground points on a 2 m grid, a camera sees those inside its image;
a pair is covisible when the points both see are at least ``--min-overlap`` of the smaller of
their footprints. Recall is the share of covisible pairs that ``gps:K`` plans (fixes with
``--gps-noise`` metres of noise), pairing by the fixes themselves and by the look points that
``geomatch run`` uses when DJI XMP gives gimbal pitch and yaw (2 deg / 1 deg of gimbal error);
"of exhaustive" is the plan's size as a share of all pairs.

    python bench/gps_pairs.py --k 5,10,15,20 --min-overlap 0.1,0.3,0.5
"""

from __future__ import annotations

import argparse
import itertools
from dataclasses import dataclass

import numpy as np
from common import print_table

from geomatch.geo.gps import footprint, look_point
from geomatch.metadata import ImageMeta
from geomatch.pipeline.pair_sources import gps_neighbours
from geomatch.synth.camera import look_at

WIDTH, HEIGHT = 4000, 3000
FOCAL = 24.0 / 36.0 * WIDTH  # 24 mm equivalent on the 36 mm long side
# what gps:K pairs by: the fix itself, the look point the gimbal's XMP gives (gps.look_point), or
# the footprint it gives (gps.footprint, what ``geomatch run`` does: most shared ground first)
BY = ("position", "look point", "footprint")


@dataclass(frozen=True)
class Layout:
    name: str
    altitude: float
    front: float  # overlap along the line, for a nadir footprint
    side: float  # overlap between lines
    tilt_deg: float  # camera axis from nadir, forward along the flight direction
    lines: int
    per_line: int


LAYOUTS = {
    "nadir": Layout("nadir", 80.0, 0.80, 0.70, 0.0, 10, 20),
    "oblique": Layout("oblique", 60.0, 0.75, 0.60, 30.0, 8, 25),
}


def flight(layout: Layout, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, list[ImageMeta]]:
    """Camera centres (N, 3), cam_from_world rotations (N, 3, 3) and the DJI XMP a drone would
    write (relative altitude, gimbal pitch and yaw, each with the gimbal's error) of one survey."""
    foot_w = layout.altitude * WIDTH / FOCAL  # across the line (image x across track)
    foot_h = layout.altitude * HEIGHT / FOCAL  # along the line
    step, spacing = foot_h * (1 - layout.front), foot_w * (1 - layout.side)
    centres, rots, metas = [], [], []
    for line in range(layout.lines):
        direction = 1.0 if line % 2 == 0 else -1.0
        for i in range(layout.per_line):
            along = i * step if direction > 0 else (layout.per_line - 1 - i) * step
            C = np.array([line * spacing, along, layout.altitude]) + rng.normal(0, [1.0, 1.0, 0.5])
            tilt = np.radians(layout.tilt_deg + rng.normal(0, 1.0))
            yaw = rng.normal(0, np.radians(3.0))
            fwd = np.array([np.sin(yaw), np.cos(yaw), 0.0]) * direction
            target = C + np.array([0, 0, -1.0]) + np.tan(tilt) * fwd
            R, _ = look_at(C, target, up=fwd)
            centres.append(C)
            rots.append(R)
            heading = np.degrees(np.arctan2(fwd[0], fwd[1])) + rng.normal(0, 2.0)
            pitch = -90.0 + np.degrees(tilt) + rng.normal(0, 1.0)
            metas.append(
                ImageMeta(
                    WIDTH,
                    HEIGHT,
                    focal_px=FOCAL,
                    relative_altitude_m=C[2],
                    gimbal_pitch_deg=pitch,
                    gimbal_yaw_deg=heading,
                )
            )
    return np.array(centres), np.array(rots), metas


def covisible_overlap(centres: np.ndarray, rots: np.ndarray, grid: float = 2.0) -> np.ndarray:
    """(N, N) shared ground points over the smaller footprint."""
    lo, hi = centres[:, :2].min(0) - 150, centres[:, :2].max(0) + 150
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0], grid), np.arange(lo[1], hi[1], grid))
    X = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)
    K = np.array([[FOCAL, 0, WIDTH / 2], [0, FOCAL, HEIGHT / 2], [0, 0, 1.0]])
    vis = np.zeros((len(centres), len(X)), np.float32)
    for i, (C, R) in enumerate(zip(centres, rots, strict=True)):
        Xc = (X - C) @ R.T
        uv = Xc @ K.T
        z = Xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = uv[:, 0] / z, uv[:, 1] / z
        vis[i] = (z > 0) & (u >= 0) & (u < WIDTH) & (v >= 0) & (v < HEIGHT)
    shared = vis @ vis.T
    size = vis.sum(1)
    return shared / np.maximum(np.minimum(size[:, None], size[None, :]), 1.0)


def evaluate(layout: Layout, seed: int, ks: list[int], overlaps: list[float], noise: float) -> list[dict]:
    rng = np.random.default_rng(seed)
    centres, rots, metas = flight(layout, rng)
    ov = covisible_overlap(centres, rots)
    n = len(centres)
    names = [f"img_{i:04d}" for i in range(n)]
    fixes = {nm: c + rng.normal(0, [noise, noise, 1.5 * noise]) for nm, c in zip(names, centres, strict=True)}
    looks = {nm: look_point(fixes[nm], m) for nm, m in zip(names, metas, strict=True)}
    feet = {nm: footprint(fixes[nm], m) for nm, m in zip(names, metas, strict=True)}
    index = {nm: i for i, nm in enumerate(names)}
    exhaustive = n * (n - 1) // 2
    rows = []
    for k, by in itertools.product(ks, BY):
        points = fixes if by == "position" else looks
        fp = feet if by == "footprint" else None
        plan = {(index[a], index[b]) for a, b in gps_neighbours(names, points, k, footprints=fp)}
        plan |= {(j, i) for i, j in plan}
        for t in overlaps:
            iu = np.triu_indices(n, 1)
            cov = [(i, j) for i, j in zip(*iu, strict=True) if ov[i, j] >= t]
            hit = sum((i, j) in plan for i, j in cov)
            rows.append(
                {
                    "layout": layout.name,
                    "seed": seed,
                    "k": k,
                    "by": by,
                    "min_overlap": t,
                    "covisible": len(cov),
                    "recall": hit / max(len(cov), 1),
                    "pairs": len(plan) // 2,
                    "share": len(plan) / 2 / exhaustive,
                }
            )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--k", default="5,10,15,20")
    ap.add_argument("--min-overlap", default="0.1,0.3,0.5")
    ap.add_argument("--gps-noise", type=float, default=2.0)
    ap.add_argument("--tune", default="nadir:0,oblique:0", help="layout:seed,... (tuning split)")
    ap.add_argument("--test", default="oblique:1,oblique:2,nadir:3", help="layout:seed,... (held out)")
    args = ap.parse_args()
    ks = [int(k) for k in args.k.split(",")]
    overlaps = [float(t) for t in args.min_overlap.split(",")]
    cols = [
        ("layout", "layout", "s"),
        ("seed", "seed", "d"),
        ("K", "k", "d"),
        ("by", "by", "s"),
        ("min overlap", "min_overlap", ".1f"),
        ("covisible", "covisible", "d"),
        ("recall %", "recall", "%"),
        ("pairs", "pairs", "d"),
        ("of exhaustive %", "share", "%"),
    ]
    for split, spec in (("tuning", args.tune), ("test", args.test)):
        rows = []
        for item in spec.split(","):
            name, seed = item.split(":")
            rows += evaluate(LAYOUTS[name], int(seed), ks, overlaps, args.gps_noise)
        print_table(f"gps:K pair recall, {split} split (GPS noise {args.gps_noise} m)", cols, rows)


if __name__ == "__main__":
    main()
