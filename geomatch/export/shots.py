"""``shots.geojson``: one point per registered photo, where WebODM draws the camera frusta and the
photo pop-ups over the map and the 3D view.

Each feature sits at the camera centre on WGS84 (longitude, latitude, ellipsoidal or the GCP
file's height) and carries what ODM writes there: ``filename``, ``camera`` (its key in
``cameras.json``), ``focal`` (OpenSfM's normalised focal length), ``width``, ``height``,
``capture_time`` (EXIF, milliseconds), ``translation`` (the centre in the point cloud's projected
CRS) and ``rotation`` (OpenSfM's world-to-camera rotation as an axis-angle vector, in the projected
system's axes: the frusta then face where the LAZ's points are).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
from scipy.spatial.transform import Rotation

from .georef import ModelFrame
from .opensfm import camera_keys
from .photos import Photo


def shots_geojson(
    rec: pycolmap.Reconstruction, frame: ModelFrame, photos: dict[str, Photo]
) -> dict[str, Any]:
    keys = camera_keys(rec, photos)
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    if not images:
        return {"type": "FeatureCollection", "features": []}
    centres = np.stack([np.asarray(im.projection_center(), np.float64) for im in images])
    projected, wgs84 = frame.to_projected(centres), frame.to_wgs84(centres)
    turn = frame.projected_from_model(centres.mean(axis=0))
    features = []
    for im, centre, lonlath in zip(images, projected, wgs84, strict=True):
        cam = rec.cameras[im.camera_id]
        cam_from_model = np.asarray(im.cam_from_world().rotation.matrix(), np.float64)
        rotvec = Rotation.from_matrix(cam_from_model @ turn.T).as_rotvec()
        photo = photos.get(im.name)
        features.append(
            {
                "type": "Feature",
                "properties": {
                    "filename": im.name,
                    "camera": keys[im.camera_id],
                    "focal": float(cam.focal_length_x) / max(int(cam.width), int(cam.height)),
                    "width": int(cam.width),
                    "height": int(cam.height),
                    "capture_time": photo.capture_ms if photo else None,
                    "translation": [float(v) for v in centre],
                    "rotation": [float(v) for v in rotvec],
                },
                "geometry": {"type": "Point", "coordinates": [float(v) for v in lonlath]},
            }
        )
    return {"type": "FeatureCollection", "features": features}


def write_shots(
    path: Path, rec: pycolmap.Reconstruction, frame: ModelFrame, photos: dict[str, Photo]
) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(shots_geojson(rec, frame, photos), indent=1))
    return path
