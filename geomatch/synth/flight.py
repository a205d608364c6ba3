"""Synthetic drone survey flights over an area that grows with the photos, with ground truth.

The plan and its cameras are synth.flightplan's, the world they photograph (terrain, buildings,
ground tiles) and its renders synth.world's, what each photo carries besides its pixels (GPS,
DJI XMP with the headings) synth.sensors'.

Output of :func:`write_flight`: ``images/`` (JPEG: EXIF focal length and GPS; DJI XMP on the
aerial photos), ``gt/`` (COLMAP text model and ``gps.json``, as synth.aerial.write_scene writes
them, and ``flight.json``: the plan), ``aerial.txt``.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

from .camera import Camera
from .flightplan import FOCAL_PER_WIDTH, FlightPlan, aerial_cameras, ground_cameras
from .groundtruth import write_gps_truth, write_gt
from .sensors import BARO_NOISE_M, GPS_NOISE_M, baro_heights, gps_fixes, save_jpeg
from .world import World


def write_flight(
    out: str | Path,
    photos: int,
    ground: int = 0,
    seed: int = 0,
    width: int = 640,
    height: int = 480,
    gps_noise: float = GPS_NOISE_M,
    baro_noise: float = BARO_NOISE_M,
    altitude: float = 80.0,
) -> list[Camera]:
    """Render a survey of ``photos`` nadir photos (and ``ground`` handheld ones) into ``out``
    (module docstring) and return its cameras. An image already in ``images/`` is kept (the
    renders are deterministic), so an interrupted render resumes."""
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    plan = FlightPlan.make(photos, width, height, altitude)
    gsd = altitude / (FOCAL_PER_WIDTH * width)
    world = World(seed, texel_m=gsd / 2)
    cams, headings = aerial_cameras(plan, seed)
    cams += ground_cameras(world, plan, ground, seed)
    fixes = gps_fixes(cams, gps_noise, seed)
    heights = baro_heights(cams, baro_noise, seed)
    compass = np.random.default_rng([seed, 0xC0A]).normal(0.0, 2.0, len(cams))
    for c, err in zip(cams, compass, strict=True):
        path = out / "images" / c.name
        if not path.is_file():
            tmp = path.with_suffix(".tmp.jpg")
            save_jpeg(tmp, world.render(c)[0], c, fixes[c.name], heights.get(c.name), float(err))
            tmp.replace(path)
    write_gt(cams, out / "gt")
    write_gps_truth(out / "gt", cams, fixes, gps_noise, heights, baro_noise)
    (out / "gt" / "flight.json").write_text(
        json.dumps(
            {
                **asdict(plan),
                "per_line": plan.per_line,
                "headings_deg": dict(zip((c.name for c in cams if c.aerial), headings, strict=True)),
                "ground": [c.name for c in cams if not c.aerial],
                "seed": seed,
            },
            indent=1,
        )
        + "\n"
    )
    (out / "aerial.txt").write_text("".join(f"{c.name}\n" for c in cams if c.aerial))
    return cams
