"""The georeferenced point cloud as LAZ: what WebODM, Potree, PDAL and CloudCompare open.

LAS 1.4, point format 7 (coordinates, 16-bit RGB, GPS time), compressed by lazrs, with the CRS
recorded as an OGC WKT VLR (laspy's ``add_crs``), coordinates absolute in the model's projected
system (``georef.ModelFrame``) at millimetre scale, offset at the cloud's minimum so that every
coordinate fits LAS's 32-bit integers. A model that is not georeferenced has no LAZ: its
coordinates name no place, and a CRS-less cloud is what drone tools refuse to place on a map.
"""

from __future__ import annotations

import json
from pathlib import Path

import laspy
import numpy as np
import pycolmap

from .georef import ModelFrame, model_frame
from .source import ExportError, Source

SCALE = 0.001  # metres per LAS integer step: survey precision, far below any model's noise
LAZ_NAME = "odm_georeferenced_model.laz"  # ODM's name, which WebODM looks for


def model_points(model: Path) -> tuple[np.ndarray, np.ndarray]:
    """The model's 3D points (N, 3) and their colours (N, 3) uint8, by point id."""
    rec = pycolmap.Reconstruction(str(model))
    ids = sorted(rec.points3D)
    xyz = np.array([rec.points3D[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([rec.points3D[i].color for i in ids], dtype=np.uint8).reshape(-1, 3)
    return xyz, rgb


def write_laz(path: Path, xyz: np.ndarray, rgb: np.ndarray, frame: ModelFrame) -> Path:
    """Model points ``xyz`` with colours ``rgb`` written to ``path`` in ``frame``'s projected CRS."""
    projected = frame.to_projected(xyz)
    header = laspy.LasHeader(point_format=7, version="1.4")
    header.add_crs(frame.crs)
    header.scales = np.array([SCALE, SCALE, SCALE])
    header.offsets = np.floor(projected.min(axis=0)) if len(projected) else np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = projected[:, 0], projected[:, 1], projected[:, 2]
    # LAS colours are 16 bit: 8-bit values scaled to the full range (255 -> 65535)
    colour = rgb.astype(np.uint16) * 257
    las.red, las.green, las.blue = colour[:, 0], colour[:, 1], colour[:, 2]
    path.parent.mkdir(parents=True, exist_ok=True)
    las.write(str(path), laz_backend=laspy.LazBackend.Lazrs)
    return path


def frame_of(source: Source) -> ModelFrame | None:
    if source.summary is None:
        return None
    return model_frame(json.loads(source.summary.read_text()))


def write(source: Source, dest: Path) -> list[Path]:
    """``geomatch export --format laz``: the LAZ alone."""
    frame = frame_of(source)
    if frame is None:
        raise ExportError("the laz export needs a georeferenced model (GPS fixes or ground control points)")
    xyz, rgb = model_points(source.model)
    return [write_laz(dest / LAZ_NAME, xyz, rgb, frame)]
