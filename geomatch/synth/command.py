"""``geomatch synth``: a synthetic scene with exact ground truth written to a folder (an
air-to-ground scene, an indoor room, a survey flight, a fixed-wing flight), its arguments and the
line it prints. Imports stay light here: the scenes load inside the command."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from ..options import EXIT_BAD_INPUT


def register(sub: Any) -> None:
    """The ``synth`` command on a parser's subcommands."""
    s = sub.add_parser("synth", help="render a synthetic air-to-ground scene with ground truth")
    s.add_argument("out", type=Path)
    s.add_argument("--aerial", type=int, default=8)
    s.add_argument("--ground", type=int, default=None, help="ground views (default 12; flight: 0)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument(
        "--kind",
        choices=("outdoor", "indoor", "flight", "fixedwing"),
        default="outdoor",
        help="indoor: one room, --ground views (--aerial ignored), depth/ as .npy; flight: a nadir "
        "survey of --photos photos over an area that grows with them, GPS and DJI XMP on every "
        "photo (--gps-noise default 1.5), --ground handheld photos of buildings (--aerial ignored); "
        "fixedwing: --photos photos of a fixed-wing circling one field (legs both ways, banked "
        "turns, near-infrared farmland), EXIF GPS only (--gps-noise default 2.5)",
    )
    s.add_argument(
        "--photos", type=int, default=100, help="with --kind flight or fixedwing: the survey's photos"
    )
    s.add_argument(
        "--return-spacing",
        type=float,
        default=1.75,
        metavar="RATIO",
        help="with --kind fixedwing: the return legs' photo spacing over the outbound legs' (wind)",
    )
    s.add_argument(
        "--missing", type=float, default=0.03, help="with --kind fixedwing: a trigger's chance to fail"
    )
    s.add_argument(
        "--colour", action="store_true", help="with --kind fixedwing: a colour camera, not near infrared"
    )
    s.add_argument("--width", type=int, default=640)
    s.add_argument("--height", type=int, default=480)
    s.add_argument(
        "--gps-noise",
        type=float,
        default=None,
        metavar="METRES",
        help="write EXIF GPS fixes (scene metres as ENU around lat 47.3769, lon 8.5417, alt 408), "
        "noise N(0, METRES) east/north and 1.5x that up; gt/gps.json has the truth",
    )
    s.add_argument(
        "--baro-noise",
        type=float,
        default=None,
        metavar="METRES",
        help="with --gps-noise: noise N(0, METRES) on the aerial images' DJI relative altitude "
        "(a barometer; default 0.3, synth.sensors.BARO_NOISE_M)",
    )
    s.add_argument(
        "--gcps", type=int, default=0, metavar="N", help="write N ground control points (gt/gcp_list.txt)"
    )
    s.add_argument(
        "--gcp-noise",
        type=float,
        default=0.0,
        metavar="METRES",
        help="with --gcps: survey noise N(0, METRES) per axis on their coordinates (truth in gt/gcps.json)",
    )
    s.set_defaults(func=cmd_synth)


def cmd_synth(args: argparse.Namespace) -> int:
    from .aerial import write_scene

    t0 = time.perf_counter()
    if args.kind == "flight":
        return _synth_flight(args, t0)
    if args.kind == "fixedwing":
        return _synth_fixedwing(args, t0)
    args.ground = 12 if args.ground is None else args.ground
    if args.kind == "indoor":
        from .indoor import write_room

        views = write_room(args.out, args.ground, args.seed, args.width, args.height)
        print(
            f"{len(views)} indoor views in {time.perf_counter() - t0:.1f}s -> {args.out}/images, "
            f"ground truth in {args.out}/gt, depth in {args.out}/depth"
        )
        return 0
    cams = write_scene(
        args.out,
        args.aerial,
        args.ground,
        args.seed,
        (args.width, args.height),
        args.gps_noise,
        baro_noise=args.baro_noise,  # None: synth.sensors.BARO_NOISE_M
    )
    if args.gcps:
        from .aerial import Scene
        from .gcps import write_gcps

        write_gcps(args.out, Scene(args.seed), cams, args.gcps, args.seed, args.gcp_noise)
    print(
        f"{len(cams)} images ({args.aerial} aerial, {args.ground} ground) in {time.perf_counter() - t0:.1f}s "
        f"-> {args.out}/images, ground truth in {args.out}/gt, aerial names in {args.out}/aerial.txt"
        + (f", {args.gcps} GCPs in {args.out}/gt/gcp_list.txt" if args.gcps else "")
    )
    return 0


def _synth_flight(args: argparse.Namespace, t0: float) -> int:
    from .flight import write_flight
    from .sensors import BARO_NOISE_M, GPS_NOISE_M

    if args.photos < 1:
        print(f"geomatch: error: --photos must be at least 1, not {args.photos}", file=sys.stderr)
        return EXIT_BAD_INPUT
    cams = write_flight(
        args.out,
        args.photos,
        args.ground or 0,
        args.seed,
        (args.width, args.height),
        GPS_NOISE_M if args.gps_noise is None else args.gps_noise,
        BARO_NOISE_M if args.baro_noise is None else args.baro_noise,
    )
    seconds = time.perf_counter() - t0
    print(
        f"{len(cams)} images ({args.photos} aerial, {len(cams) - args.photos} ground) in {seconds:.1f}s "
        f"({seconds / len(cams):.2f}s an image) -> {args.out}/images, ground truth in {args.out}/gt "
        f"(flight plan: gt/flight.json), aerial names in {args.out}/aerial.txt"
    )
    return 0


def _synth_fixedwing(args: argparse.Namespace, t0: float) -> int:
    from .fixedwing import FixedWingPlan
    from .flight import FIXEDWING_GPS_NOISE_M, write_fixedwing

    try:
        plan = FixedWingPlan(
            args.photos, args.width, args.height, return_ratio=args.return_spacing, missing=args.missing
        )
    except ValueError as e:
        print(f"geomatch: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    noise = FIXEDWING_GPS_NOISE_M if args.gps_noise is None else args.gps_noise
    cams = write_fixedwing(args.out, plan, args.seed, noise, nir=not args.colour)
    seconds = time.perf_counter() - t0
    print(
        f"{len(cams)} images (fixed-wing) in {seconds:.1f}s ({seconds / len(cams):.2f}s an image) -> "
        f"{args.out}/images, ground truth in {args.out}/gt (every trigger: gt/flight.json)"
    )
    return 0
