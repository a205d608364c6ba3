"""``cameras.json``: the model's cameras in OpenSfM's format, which ODM's tools read (``--cameras``
reuses a calibration) and WebODM offers for download.

OpenSfM normalises by the image's larger side: ``focal`` = f / max(w, h) and the principal point
``c_x`` = (cx - w / 2) / max(w, h), both in the same pixel convention as COLMAP's (the centre of
the top-left pixel at 0.5). COLMAP's radial distortion and OpenSfM's Brown model both act on
normalised camera coordinates, so ``k1`` (and ``k2``) carry over; a camera model with tangential
or higher terms maps them by name. A camera is keyed as OpenSfM keys one: ``v2 make model width
height projection focal``, lower case, so a second export of the same camera finds the same key.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pycolmap

from .photos import Photo

# COLMAP's parameter names -> OpenSfM's Brown parameters (what is not named stays 0)
_DISTORTION = {"k": "k1", "k1": "k1", "k2": "k2", "k3": "k3", "p1": "p1", "p2": "p2"}


def opensfm_camera(camera: pycolmap.Camera) -> dict[str, Any]:
    """One camera in OpenSfM's ``brown`` projection (the model ODM writes for drone cameras)."""
    w, h = int(camera.width), int(camera.height)
    size = float(max(w, h))
    names = [n.strip() for n in camera.params_info.split(",")]
    params = dict(zip(names, (float(v) for v in camera.params), strict=False))
    out: dict[str, Any] = {
        "projection_type": "brown",
        "width": w,
        "height": h,
        "focal_x": float(camera.focal_length_x) / size,
        "focal_y": float(camera.focal_length_y) / size,
        "c_x": (float(camera.principal_point_x) - w / 2.0) / size,
        "c_y": (float(camera.principal_point_y) - h / 2.0) / size,
        "k1": 0.0,
        "k2": 0.0,
        "p1": 0.0,
        "p2": 0.0,
        "k3": 0.0,
    }
    for name, value in params.items():
        if name in _DISTORTION:
            out[_DISTORTION[name]] = value
    return out


def camera_key(camera: pycolmap.Camera, photo: Photo | None) -> str:
    make = (photo.make if photo and photo.make else "unknown").strip().lower()
    model = (photo.model if photo and photo.model else f"camera{camera.camera_id}").strip().lower()
    focal = float(camera.focal_length_x) / max(int(camera.width), int(camera.height))
    return f"v2 {make} {model} {int(camera.width)} {int(camera.height)} brown {focal:.4f}"


def camera_keys(rec: pycolmap.Reconstruction, photos: dict[str, Photo]) -> dict[int, str]:
    """Each COLMAP camera's OpenSfM key, named after the first of its photos (by name)."""
    first: dict[int, Photo] = {}
    for im in sorted(rec.images.values(), key=lambda i: i.name):
        first.setdefault(im.camera_id, photos.get(im.name) or Photo(im.name, 0, 0))
    keys: dict[int, str] = {}
    for cam_id, cam in rec.cameras.items():
        key = camera_key(cam, first.get(cam_id))
        # two COLMAP cameras of one device (refined apart) keep apart: the id breaks the tie
        keys[cam_id] = key if key not in keys.values() else f"{key} {cam_id}"
    return keys


def cameras_json(rec: pycolmap.Reconstruction, photos: dict[str, Photo]) -> dict[str, Any]:
    keys = camera_keys(rec, photos)
    return {keys[i]: opensfm_camera(rec.cameras[i]) for i in sorted(rec.cameras)}


def write_cameras_json(path: Path, rec: pycolmap.Reconstruction, photos: dict[str, Photo]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(cameras_json(rec, photos), indent=1))
    return path
