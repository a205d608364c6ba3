"""How close a georeferenced run's cameras are to the truth, in metres, against the GPS itself.

Reads a scene written by ``geomatch synth --gps-noise`` (``gt/gps.json``: the true and the noisy
ENU positions in the scene's frame) and a ``geomatch run`` of it (``summary.json``: the frame the
model was put in; ``sparse/0``). The truth is carried into the model's frame through ECEF, and the
camera centres are compared with no further alignment: the error a user measuring in the model
gets. The GPS fixes' own error is the baseline the reconstruction should beat.

    python bench/georef_accuracy.py SCENE RUN

``--model SPARSE --aerial A --ground G --seed S`` instead judges an existing reconstruction of
the scene ``geomatch synth --aerial A --ground G --seed S`` (renders are the same with or without
GPS): fixes with ``--gps-noise`` and the drones' heights with ``--baro-noise`` are drawn
``--trials`` times (synth.sensors.gps_fixes and baro_heights, their generators offset by the trial)
and the model is georeferenced by the pipeline's own code (georef.align) each time, three ways:
the free 7-parameter fit, the upright one (gimbal gravity) and upright with the heights; this
measures the georeferencing on reconstructions too costly to redo on a shared CPU.

    python bench/georef_accuracy.py --model RUN/sparse/0 --aerial 6 --ground 10 --seed 0 --trials 20
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pycolmap

from geomatch.geo.geodesy import EnuFrame
from geomatch.geo.georef import align, errors_against
from geomatch.synth.aerial import Scene
from geomatch.synth.sensors import BARO_NOISE_M, GPS_ORIGIN, baro_heights, gps_fixes, xmp_ups


def simulated(args: argparse.Namespace) -> None:
    cams = Scene(args.seed).cameras(args.aerial, args.ground, args.width, args.height)
    truth = {c.name: c.centre for c in cams}
    ups = xmp_ups(cams)
    variants = {
        "7-parameter (no gravity)": (None, False),
        "upright (gimbal gravity)": (ups, False),
        "upright + baro heights": (ups, True),
    }
    rows: dict[str, list] = {k: [] for k in variants}
    for trial in range(args.trials):
        fixes = gps_fixes(cams, args.gps_noise, args.seed * 1000 + trial)
        heights = baro_heights(cams, args.baro_noise, args.seed * 1000 + trial)
        for label, (up, use_heights) in variants.items():
            rec = pycolmap.Reconstruction(str(args.model))
            a = align(rec, fixes, up_cam=up, heights=heights if use_heights else None)
            assert a is not None
            e = errors_against(rec, truth)
            names = sorted(e["per_image_m"])
            g = np.array([np.linalg.norm(fixes[n] - truth[n]) for n in names])
            n_inl = int(a.inliers.sum())
            row = (e["mean_m"], e["max_m"], g.mean(), g.max(), e["scale_error"], n_inl, len(names))
            rows[label].append(row)
    first = np.array(next(iter(rows.values())))
    print(
        f"{args.model}: {int(first[0, 6])} registered of {len(cams)},",
        f"GPS sigma {args.gps_noise} m ({1.5 * args.gps_noise:g} m up), heights {args.baro_noise} m,",
        f"{args.trials} draws",
    )
    print(f"{'':26} {'':22} {'mean':>7} {'median':>7} {'worst':>7}")
    for label, rr in rows.items():
        r = np.array(rr)
        for name, col, f in (
            ("model centre error m", 0, 1.0),
            ("model max error m", 1, 1.0),
            ("GPS error m", 2, 1.0),
            ("scale error %", 4, 100.0),
        ):
            v = f * r[:, col]
            print(f"{label:26} {name:22} {v.mean():7.3f} {np.median(v):7.3f} {v.max():7.3f}")
        print(f"{label:26} inliers: min {int(r[:, 5].min())} of {int(r[0, 6])}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene", type=Path, nargs="?")
    ap.add_argument("run", type=Path, nargs="?")
    ap.add_argument("--model", type=Path, default=None)
    ap.add_argument("--aerial", type=int, default=8)
    ap.add_argument("--ground", type=int, default=12)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--gps-noise", type=float, default=2.0)
    ap.add_argument("--baro-noise", type=float, default=BARO_NOISE_M)
    ap.add_argument("--trials", type=int, default=20)
    args = ap.parse_args()
    if args.model is not None:
        simulated(args)
        return
    if args.scene is None or args.run is None:
        ap.error("SCENE and RUN, or --model")
    gt = json.loads((args.scene / "gt" / "gps.json").read_text())
    s = json.loads((args.run / "summary.json").read_text())
    if not s.get("georeferenced"):
        raise SystemExit(f"{args.run} is not georeferenced: {s.get('gps_images')} images with GPS")
    frame = EnuFrame(**s["origin"])

    def to_model(v: list[float]) -> np.ndarray:
        return frame.from_ecef(GPS_ORIGIN.to_ecef(np.array(v)))

    truth = {n: to_model(v) for n, v in gt["true_enu"].items()}
    rec = pycolmap.Reconstruction(str(args.run / "sparse" / "0"))
    model = errors_against(rec, truth)
    names = sorted(model["per_image_m"])
    gps_err = np.array([np.linalg.norm(np.subtract(gt["gps_enu"][n], gt["true_enu"][n])) for n in names])
    model_err = np.array([model["per_image_m"][n] for n in names])
    print(f"registered {s['registered']}/{s['images']}, pairs {s['pairs']}, alignment {s['alignment']}")
    print(f"{'':10} {'mean m':>8} {'median m':>9} {'max m':>7}")
    for label, e in (("model", model_err), ("GPS", gps_err)):
        print(f"{label:10} {e.mean():8.3f} {np.median(e):9.3f} {e.max():7.3f}")
    print(
        f"scale error {100 * model['scale_error']:.3f} %",
        f"(GPS sigma {gt['sigma_m']} m, over {len(names)} images)",
    )
    out = {"model": model, "gps_mean_m": float(gps_err.mean()), "gps_median_m": float(np.median(gps_err))}
    (args.run / "georef_accuracy.json").write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
