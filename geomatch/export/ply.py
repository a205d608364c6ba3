"""The model's 3D points with their colours as PLY (COLMAP's own export: binary little-endian,
x y z as double, red green blue as uchar), the point cloud every viewer (MeshLab, CloudCompare,
Blender) opens; in COLMAP's world, as the model."""

from __future__ import annotations

from pathlib import Path

import pycolmap

from .source import Source


def write(source: Source, dest: Path) -> list[Path]:
    dest.mkdir(parents=True, exist_ok=True)
    out = dest / "points.ply"
    pycolmap.Reconstruction(str(source.model)).export_PLY(str(out))
    return [out]
