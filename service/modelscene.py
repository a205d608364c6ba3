"""The sparse model as a browser draws it: coloured points and posed cameras, read from the COLMAP
text files the reconstruct job leaves in ``model/sparse/0`` (the largest model).

Parsed here in plain Python rather than with pycolmap: the API stays free of the library's heavy
imports, and the text format is COLMAP's stable, documented one. Nothing is cached: the model folder
is swapped whole by a new reconstruct, and reading it again is the simplest way never to serve a
stale scene.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from geomatch_core.errors import NotFound


def quaternion_matrix(qw: float, qx: float, qy: float, qz: float) -> list[list[float]]:
    """Rotation matrix (rows) of a unit quaternion, COLMAP's convention (Hamilton, w first)."""
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz) or 1.0
    w, x, y, z = qw / n, qx / n, qy / n, qz / n
    return [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]


def _rows(path: Path) -> list[str]:
    """The file's lines without its ``#`` comments; blank lines kept (an image's empty 2D line)."""
    return [line for line in path.read_text().splitlines() if not line.startswith("#")]


def _cameras(path: Path) -> dict[int, dict[str, float]]:
    out: dict[int, dict[str, float]] = {}
    for line in _rows(path):
        f = line.split()
        if len(f) < 5:
            continue
        width, height, params = float(f[2]), float(f[3]), [float(p) for p in f[4:]]
        # the first parameter is the (x) focal length of every COLMAP model; the principal point
        # comes after one focal (SIMPLE_*) or two (PINHOLE, OPENCV ...)
        two_focals = f[1] not in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE")
        cx, cy = (params[2], params[3]) if two_focals and len(params) > 3 else (params[1], params[2])
        out[int(f[0])] = {"width": width, "height": height, "focal": params[0], "cx": cx, "cy": cy}
    return out


def _images(path: Path, cameras: dict[int, dict[str, float]]) -> list[dict[str, Any]]:
    rows = _rows(path)
    out: list[dict[str, Any]] = []
    for header in rows[0::2]:
        f = header.split(maxsplit=9)  # the name is the rest of the line: it may hold spaces
        if len(f) < 10:
            continue
        qw, qx, qy, qz, tx, ty, tz = (float(v) for v in f[1:8])
        r = quaternion_matrix(qw, qx, qy, qz)
        t = (tx, ty, tz)
        centre = [-sum(r[k][i] * t[k] for k in range(3)) for i in range(3)]  # C = -R^T t
        cam = cameras.get(int(f[8]), {"width": 1.0, "height": 1.0, "focal": 1.0, "cx": 0.5, "cy": 0.5})
        out.append(
            {
                "name": f[9],
                "center": [round(c, 6) for c in centre],
                "rotation": [[round(v, 8) for v in row] for row in r],
                **cam,
            }
        )
    return out


def _points(path: Path) -> tuple[list[float], list[int]]:
    xyz: list[float] = []
    rgb: list[int] = []
    for line in _rows(path):
        f = line.split(maxsplit=8)
        if len(f) < 7:
            continue
        xyz.extend(round(float(v), 5) for v in f[1:4])
        rgb.extend(int(v) for v in f[4:7])
    return xyz, rgb


def read_scene(model_dir: Path) -> dict[str, Any]:
    """``{"points": N, "xyz": [x0, y0, z0, ...], "rgb": [r0, g0, b0, ...], "cameras": [...]}``;
    each camera: ``name``, ``center`` (world), ``rotation`` (world to camera, rows), ``width``,
    ``height``, ``focal``, ``cx``, ``cy`` in pixels. Raises NotFound without a model."""
    sparse = model_dir / "sparse" / "0"
    files = [sparse / n for n in ("cameras.txt", "images.txt", "points3D.txt")]
    if not all(p.is_file() for p in files):
        raise NotFound("the project has no model with registered images yet: POST .../reconstruct")
    cameras = _cameras(files[0])
    images = _images(files[1], cameras)
    xyz, rgb = _points(files[2])
    return {"points": len(xyz) // 3, "xyz": xyz, "rgb": rgb, "cameras": images}
