"""Synthetic drone survey flights over an area that grows with the photos, with ground truth.

The plan and its cameras are synth.flightplan's, the world they photograph (terrain, buildings,
ground tiles) and its renders synth.world's, what each photo carries besides its pixels (GPS,
DJI XMP with the headings) synth.sensors'.

Output of :func:`write_flight`: ``images/`` (JPEG: EXIF focal length and GPS; DJI XMP on the
aerial photos), ``gt/`` (COLMAP text model and ``gps.json``, as synth.aerial.write_scene writes
them, and ``flight.json``: the plan), ``aerial.txt``.

:func:`write_fixedwing` writes a fixed-wing's survey (synth.fixedwing: legs both ways with sparser
return legs, repeated passes, banked turns, missing photos) over farmland (synth.farmtex, a
near-infrared look by default) in the same layout: ``IMG_*.JPG`` from a compact camera with EXIF
GPS and no XMP, and ``gt/flight.json`` with every trigger (failed ones too), the part of the flight
it fell in and the airframe's attitude.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

from .camera import Camera
from .farmtex import FarmTiles
from .fixedwing import FixedWingPlan, fixedwing_cameras
from .flightplan import FOCAL_PER_WIDTH, FlightPlan, aerial_cameras, ground_cameras
from .groundtruth import write_gps_truth, write_gt
from .sensors import BARO_NOISE_M, GPS_NOISE_M, baro_heights, gps_fixes, save_jpeg
from .world import World


def write_flight(
    out: str | Path,
    photos: int,
    ground: int = 0,
    seed: int = 0,
    size: tuple[int, int] = (640, 480),
    gps_noise: float = GPS_NOISE_M,
    baro_noise: float = BARO_NOISE_M,
    altitude: float = 80.0,
) -> list[Camera]:
    """Render a survey of ``photos`` nadir photos (and ``ground`` handheld ones) into ``out``
    (module docstring) and return its cameras; ``size``: the photos' (width, height). An image
    already in ``images/`` is kept (the renders are deterministic), so an interrupted render
    resumes."""
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    width, height = size
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


FIXEDWING_GPS_NOISE_M = 2.5  # a compact camera's GNSS, per axis horizontally
FIXEDWING_CAMERA = "synth-nir-compact"
FARM_BUILDING_SHARE = 0.03


def nir_look(image: np.ndarray) -> np.ndarray:
    """Most of the colour taken out, as a converted camera's false colour leaves it (the farmland
    is drawn so already; this takes it out of the buildings' photo faces too)."""
    img = image.astype(np.float32)
    grey = img.mean(axis=2, keepdims=True)
    return np.clip(grey + 0.2 * (img - grey) + 0.5, 0, 255).astype(np.uint8)


def write_fixedwing(
    out: str | Path,
    plan: FixedWingPlan,
    seed: int = 0,
    gps_noise: float = FIXEDWING_GPS_NOISE_M,
    nir: bool = True,
    detail: float = 0.15,
) -> list[Camera]:
    """Render ``plan``'s fixed-wing survey (module docstring) into ``out`` and return its
    cameras; ``detail``: the fields' texture contrast (synth.farmtex). A photo already in
    ``images/`` is kept (renders are deterministic), so an interrupted render resumes."""
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    gsd = plan.altitude / (FOCAL_PER_WIDTH * plan.width)
    ground = FarmTiles(seed, gsd / 2, nir=nir, detail=detail)
    world = World(seed, texel_m=gsd / 2, ground=ground, building_share=FARM_BUILDING_SHARE)
    cams, fired = fixedwing_cameras(plan, seed)
    fixes = gps_fixes(cams, gps_noise, seed)
    for c in cams:
        path = out / "images" / c.name
        if not path.is_file():
            img = world.render(c)[0]
            tmp = path.with_suffix(".tmp.jpg")
            save_jpeg(tmp, nir_look(img) if nir else img, c, fixes[c.name], model=FIXEDWING_CAMERA)
            tmp.replace(path)
    write_gt(cams, out / "gt")
    # no barometer: the EXIF altitude is the GNSS one
    write_gps_truth(out / "gt", cams, fixes, gps_noise, {}, 0.0)
    triggers = [
        {
            "index": s.index,
            "name": s.name,
            "part": s.part,
            "loop": s.loop,
            "position": [round(float(v), 3) for v in s.position],
            "heading_deg": round(s.heading_deg, 2),
            "track_deg": round(s.track_deg, 2),
            "roll_deg": round(s.roll_deg, 2),
            "pitch_deg": round(s.pitch_deg, 2),
            "ground_speed": round(s.ground_speed, 2),
        }
        for s in fired
    ]
    (out / "gt" / "flight.json").write_text(
        json.dumps(
            {
                "kind": "fixedwing",
                **asdict(plan),
                "wind": plan.wind.tolist(),
                "seed": seed,
                "nir": nir,
                "detail": detail,
                "gps_noise_m": gps_noise,
                "missing_triggers": [s.index for s in fired if s.name is None],
                "triggers": triggers,
            },
            indent=1,
        )
        + "\n"
    )
    (out / "aerial.txt").write_text("".join(f"{c.name}\n" for c in cams))
    return cams
