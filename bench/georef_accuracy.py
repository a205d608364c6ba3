"""How close a georeferenced run's cameras are to the truth, in metres, against the GPS itself.

Reads a scene written by ``geomatch synth --gps-noise`` (``gt/gps.json``: the true and the noisy
ENU positions in the scene's frame) and a ``geomatch run`` of it (``summary.json``: the frame the
model was put in; ``sparse/0``). The truth is carried into the model's frame through ECEF, and the
camera centres are compared with no further alignment: the error a user measuring in the model
gets. The GPS fixes' own error is the baseline the reconstruction should beat.

    python bench/georef_accuracy.py SCENE RUN
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pycolmap

from geomatch.geodesy import EnuFrame
from geomatch.georef import errors_against
from geomatch.synth import GPS_ORIGIN


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene", type=Path)
    ap.add_argument("run", type=Path)
    args = ap.parse_args()
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
