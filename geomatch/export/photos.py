"""What the drone tools read about each photo: ``images.json`` (ODM's list of photo metadata) and
the per-photo facts that ``shots.geojson`` and ``cameras.json`` share (make, model, size, capture
time, GPS fix), read from the photos themselves when the export has them."""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pycolmap
from PIL import Image

EXIF_IFD, DATETIME_ORIGINAL, DATETIME = 0x8769, 36867, 306


@dataclass(frozen=True)
class Photo:
    name: str
    width: int
    height: int
    make: str = ""
    model: str = ""
    capture_ms: int | None = None  # EXIF DateTimeOriginal, as UTC milliseconds (EXIF has no zone)
    latitude: float | None = None
    longitude: float | None = None
    altitude: float | None = None


def capture_ms(path: Path) -> int | None:
    """EXIF DateTimeOriginal (else DateTime) in milliseconds since 1970, read as UTC."""
    try:
        with Image.open(path) as im:
            exif = im.getexif()
            raw = exif.get_ifd(EXIF_IFD).get(DATETIME_ORIGINAL) or exif.get(DATETIME)
    except (OSError, ValueError):
        return None
    if not isinstance(raw, str):
        return None
    try:
        when = datetime.strptime(raw.strip().rstrip("\x00"), "%Y:%m:%d %H:%M:%S").replace(tzinfo=UTC)
    except ValueError:
        return None
    return int(when.timestamp() * 1000)


def read_photo(name: str, width: int, height: int, images: Path | None) -> Photo:
    """The photo's facts; its size only when the export has no images folder or no such file."""
    path = images / name if images is not None else None
    if path is None or not path.is_file():
        return Photo(name, width, height)
    # imported here: geomatch.metadata loads OpenCV (its image reader's errors), which the API
    # process that serves exports does not load until a photo is read
    from ..metadata import read_metadata

    m = read_metadata(path)
    return Photo(
        name, width, height, m.make, m.model, capture_ms(path), m.latitude, m.longitude, m.altitude_m
    )


def read_photos(rec: pycolmap.Reconstruction, images: Path | None) -> dict[str, Photo]:
    """Every image of the model, registered or not, by name."""
    out = {}
    for im in rec.images.values():
        cam = rec.cameras[im.camera_id]
        out[im.name] = read_photo(im.name, int(cam.width), int(cam.height), images)
    return out


def images_json(rec: pycolmap.Reconstruction, photos: dict[str, Photo]) -> list[dict[str, Any]]:
    """ODM's images.json: one object per photo, with the keys ODM writes that we know."""
    registered = {im.name for im in rec.images.values() if im.has_pose}
    rows = []
    for name in sorted(photos):
        p = photos[name]
        rows.append(
            {
                "filename": name,
                "width": p.width,
                "height": p.height,
                "camera_make": p.make,
                "camera_model": p.model,
                "orientation": 1,
                "latitude": p.latitude,
                "longitude": p.longitude,
                "altitude": p.altitude,
                "capture_time": p.capture_ms,
                "band_name": "RGB",
                "band_index": 0,
                "registered": name in registered,
            }
        )
    return rows


def write_images_json(path: Path, rec: pycolmap.Reconstruction, photos: dict[str, Photo]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(images_json(rec, photos), indent=1))
    return path
