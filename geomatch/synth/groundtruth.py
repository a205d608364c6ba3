"""The ground truth a synthetic scene writes beside its images, in ``gt/``: the cameras as a
COLMAP text model (cameras.txt, images.txt, an empty points3D.txt; poses cam_from_world, as COLMAP
stores them) and, for photos that carry GNSS, ``gps.json``: the true centres beside the fixes and
heights written into the photos, with the noise they were drawn with.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .camera import Camera, rotmat_to_qvec
from .sensors import GPS_ORIGIN, GPS_VERTICAL_FACTOR


def write_gt(cams: list[Camera], gt: Path) -> None:
    """The cameras as a COLMAP text model: what pycolmap and ``geomatch eval`` read as the truth."""
    gt.mkdir(parents=True, exist_ok=True)
    with open(gt / "cameras.txt", "w") as f:
        f.write("# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        for i, c in enumerate(cams, 1):
            fx, fy, cx, cy = c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2]
            f.write(f"{i} PINHOLE {c.width} {c.height} {fx:.10g} {fy:.10g} {cx:.10g} {cy:.10g}\n")
    with open(gt / "images.txt", "w") as f:
        f.write(
            "# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n# POINTS2D[] as (X, Y, POINT3D_ID)\n"
        )
        for i, c in enumerate(cams, 1):
            q = rotmat_to_qvec(c.R)
            vals = " ".join(f"{v:.12g}" for v in (*q, *c.t))
            f.write(f"{i} {vals} {i} {c.name}\n\n")
    (gt / "points3D.txt").write_text("# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]\n")


def write_gps_truth(
    gt: Path,
    cams: list[Camera],
    fixes: dict[str, np.ndarray],
    gps_noise: float,
    heights: dict[str, float],
    baro_noise: float,
) -> None:
    """``gt/gps.json``: the cameras' true ENU centres beside the fixes and relative altitudes
    written into their EXIF/XMP, with the noise they were drawn with."""
    (gt / "gps.json").write_text(
        json.dumps(
            {
                "origin": GPS_ORIGIN.as_dict(),
                "frame": "ENU",
                "sigma_m": gps_noise,
                "vertical_factor": GPS_VERTICAL_FACTOR,
                "true_enu": {c.name: c.centre.tolist() for c in cams},
                "gps_enu": {n: v.tolist() for n, v in fixes.items()},
                "baro_sigma_m": baro_noise,
                "relative_altitude": heights,
            },
            indent=1,
        )
        + "\n"
    )
