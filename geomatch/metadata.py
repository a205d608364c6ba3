"""What an image file says about its camera: EXIF focal length and device, GPS, DJI XMP altitude and pitch.

The focal length becomes COLMAP's prior (``has_prior_focal_length``); make/model/size group
images into one shared camera per device; relative altitude or gimbal pitch says whether an
image is aerial, which decides tiling; the GPS fix (EXIF GPSInfo, DJI XMP AbsoluteAltitude)
becomes a position prior and puts the model in a real-world frame (geo/gps.py, geo/georef.py).

Every number is read field by field, and one that is malformed (a rational 0/0, text that is not
a number) or absurd (infinite, a latitude past the pole, an altitude in space) is dropped alone,
with a warning naming the image and the field: the rest of the file still counts, and a job never
fails on what a camera wrote (an altitude of 0/0 read as NaN would otherwise reach the
georeferencing's SVD and fail a whole reconstruct).
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from .imageio import ImageReadError

log = logging.getLogger(__name__)
AERIAL_MIN_ALTITUDE_M = 10.0  # relative altitude (above take-off) from which a photo is aerial
AERIAL_MAX_PITCH_DEG = -30.0  # gimbal pitch at or below this (looking down) marks a photo aerial

# EXIF tags (ExifIFD unless noted)
_MAKE, _MODEL = 0x010F, 0x0110  # IFD0
_EXIF_IFD = 0x8769
_FOCAL, _FOCAL35 = 0x920A, 0xA405
_FP_XRES, _FP_UNIT = 0xA20E, 0xA210
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # FocalPlaneResolutionUnit -> mm per unit
_GPS_IFD = 0x8825
_GPS_LAT_REF, _GPS_LAT, _GPS_LON_REF, _GPS_LON, _GPS_ALT_REF, _GPS_ALT = 1, 2, 3, 4, 5, 6

# What a value can be and still describe a photograph: beyond these it is a writer's bug, never
# a place or an attitude. Altitudes span the deepest ocean trench to the edge of space (metres);
# a height above take-off ten kilometres either way; DJI writes angles in (-180, 180], and some
# writers give a yaw in [0, 360).
ALTITUDE_RANGE_M = (-11_000.0, 100_000.0)
RELATIVE_ALTITUDE_RANGE_M = (-10_000.0, 10_000.0)
PITCH_RANGE_DEG = ROLL_RANGE_DEG = (-180.0, 180.0)
YAW_RANGE_DEG = (-360.0, 360.0)
MAX_FOCAL_PER_SIDE = 1000.0  # a focal length over 1000 long sides is a 0.06 degree field of view


@dataclass(frozen=True)
class ImageMeta:
    width: int
    height: int
    make: str = ""
    model: str = ""
    focal_px: float | None = None  # from EXIF, None when the file does not say
    relative_altitude_m: float | None = None
    gimbal_pitch_deg: float | None = None
    latitude: float | None = None  # degrees, north positive (EXIF GPSInfo)
    longitude: float | None = None  # degrees, east positive
    # metres: DJI XMP AbsoluteAltitude where present (the drone's fused altitude), else EXIF
    # GPSAltitude; None when neither says (a fix without altitude is still a horizontal prior)
    altitude_m: float | None = None
    gimbal_yaw_deg: float | None = None  # DJI XMP, clockwise from north
    gimbal_roll_deg: float | None = None  # DJI XMP, positive: the image's right side down

    @property
    def has_gps(self) -> bool:
        return self.latitude is not None and self.longitude is not None

    @property
    def lat_lon(self) -> tuple[float, float] | None:
        """(latitude, longitude) in degrees; None without a fix."""
        if self.latitude is None or self.longitude is None:
            return None
        return self.latitude, self.longitude

    @property
    def device(self) -> tuple[str, str, int, int, float | None]:
        """Images with the same device key share one COLMAP camera (and its intrinsics)."""
        return (self.make, self.model, self.width, self.height, self.focal_px)

    @property
    def has_device(self) -> bool:
        return bool(self.make or self.model) and self.focal_px is not None

    @property
    def aerial_hint(self) -> bool | None:
        """True/False when the metadata decides it, None when it is silent."""
        if self.relative_altitude_m is not None:
            return self.relative_altitude_m >= AERIAL_MIN_ALTITUDE_M
        if self.gimbal_pitch_deg is not None:
            return self.gimbal_pitch_deg <= AERIAL_MAX_PITCH_DEG
        return None


NADIR_PITCH_DEG = -85.0  # at or below, roll barely moves "up" in the image (cos 85 deg = 0.09)


def gimbal_rotation(pitch_deg: float, yaw_deg: float, roll_deg: float) -> np.ndarray:
    """cam_from_world rotation (world ENU; camera x right, y down, z forward) of DJI gimbal
    angles: pitch of the optical axis above the horizon (-90 nadir), yaw clockwise from north of
    the image's top-forward direction, roll positive with the image's right side down
    (synth.camera.gimbal_angles is the inverse)."""
    p, y, r = np.radians(pitch_deg), np.radians(yaw_deg), np.radians(roll_deg)
    h = np.array([np.sin(y), np.cos(y), 0.0])  # heading
    z = np.array([np.cos(p) * h[0], np.cos(p) * h[1], np.sin(p)])
    ydown = np.array([np.sin(p) * h[0], np.sin(p) * h[1], -np.cos(p)])
    x = np.cross(ydown, z)
    return np.stack([np.cos(r) * x + np.sin(r) * ydown, -np.sin(r) * x + np.cos(r) * ydown, z])


def camera_from_gimbal(meta: ImageMeta) -> np.ndarray | None:
    """The gimbal's cam_from_world rotation (gimbal_rotation); None without pitch and yaw. A
    missing roll is 0: DJI gimbals hold the horizon level."""
    if meta.gimbal_pitch_deg is None or meta.gimbal_yaw_deg is None:
        return None
    return gimbal_rotation(meta.gimbal_pitch_deg, meta.gimbal_yaw_deg, meta.gimbal_roll_deg or 0.0)


def up_in_camera(meta: ImageMeta) -> np.ndarray | None:
    """The world's up direction in the camera's frame (x right, y down, z forward) from the
    gimbal's pitch and roll (DJI XMP), or None when the file does not say. A DJI gimbal levels
    itself against gravity with the drone's IMU: pitch and roll are good to a fraction of a
    degree, while yaw follows the compass (degrees off near steel and power lines) and is not
    used (up in the camera does not depend on it). Without a roll only a near-nadir pitch
    decides (roll then hardly matters)."""
    p = meta.gimbal_pitch_deg
    if p is None or (meta.gimbal_roll_deg is None and p > NADIR_PITCH_DEG):
        return None
    return gimbal_rotation(p, 0.0, meta.gimbal_roll_deg or 0.0)[:, 2]


def _xmp_value(xmp: str, key: str) -> str | None:
    """The text of ``key`` (attribute form ``drone-dji:Key="1.0"`` or element form
    ``<drone-dji:Key>1.0</drone-dji:Key>``); None when absent. _number turns it into a number."""
    m = re.search(rf'{key}\s*=\s*"([^"]*)"', xmp) or re.search(rf"{key}>\s*([^<]*?)\s*<", xmp)
    return m.group(1).strip() if m else None


def _xmp_text(im: Image.Image) -> str:
    for key in ("xmp", "XML:com.adobe.xmp"):
        raw = im.info.get(key)
        if raw:
            return raw.decode("utf-8", "replace") if isinstance(raw, bytes) else str(raw)
    return ""


def _number(
    image: str, field: str, read: Callable[[], float | None], low: float, high: float
) -> float | None:
    """One metadata value in [low, high], or None: when the file does not hold it (``read``
    answers None) and, with a warning naming the image and field, when it is malformed
    (``read`` raises) or absurd (not finite, out of range)."""
    try:
        value = read()
    except (TypeError, ValueError, ZeroDivisionError, OverflowError, IndexError) as e:
        log.warning("%s: %s ignored: not a number (%s)", image, field, e)
        return None
    if value is None:
        return None
    if not (math.isfinite(value) and low <= value <= high):
        log.warning("%s: %s ignored: %r is not a number in [%g, %g]", image, field, value, low, high)
        return None
    return value


def read_metadata(path: str | Path) -> ImageMeta:
    """Raises ImageReadError for a file that is not an image; odd metadata is simply absent
    (malformed or absurd fields with a warning, _number)."""
    name = Path(path).name
    try:
        im = Image.open(path)
    except (OSError, ValueError) as e:
        raise ImageReadError(f"{path}: not a readable image ({e})") from None
    with im:
        w, h = im.size
        exif = im.getexif()
        sub = exif.get_ifd(_EXIF_IFD) if exif else {}
        make = str(exif.get(_MAKE, "")).strip("\x00 ") if exif else ""
        model = str(exif.get(_MODEL, "")).strip("\x00 ") if exif else ""
        focal = _number(
            name, "EXIF focal length", lambda: _focal_px(sub, w, h), 1e-9, MAX_FOCAL_PER_SIDE * max(w, h)
        )
        xmp = _xmp_text(im)
        lat, lon, gps_alt = _gps(name, exif.get_ifd(_GPS_IFD) if exif else {})

    def dji(key: str, low_high: tuple[float, float]) -> float | None:
        raw = _xmp_value(xmp, key) if xmp else None
        return _number(name, f"XMP {key}", lambda: None if raw is None else float(raw), *low_high)

    alt = dji("RelativeAltitude", RELATIVE_ALTITUDE_RANGE_M)
    pitch = dji("GimbalPitchDegree", PITCH_RANGE_DEG)
    abs_alt = dji("AbsoluteAltitude", ALTITUDE_RANGE_M)
    yaw = dji("GimbalYawDegree", YAW_RANGE_DEG)
    roll = dji("GimbalRollDegree", ROLL_RANGE_DEG)
    return ImageMeta(
        w, h, make, model, focal, alt, pitch, lat, lon, abs_alt if abs_alt is not None else gps_alt, yaw, roll
    )


# EXIF values are Any: whatever the file holds (ints, rationals, bytes, tuples of them); float()
# decides whether one is a number, and _number catches what it raises


def _dms(value: Any, ref: object, negative: str) -> float:
    """Degrees of an EXIF (degrees, minutes, seconds) triple; raises ValueError on a malformed
    one (minutes or seconds past 60, a rational 0/0 that Pillow reads as NaN)."""
    d, m, sec = (float(v) for v in value)
    if not all(math.isfinite(v) for v in (d, m, sec)) or not (0 <= m <= 60 and 0 <= sec <= 60):
        raise ValueError(f"{d!r} deg {m!r} min {sec!r} s")
    deg = d + m / 60.0 + sec / 3600.0
    if isinstance(ref, bytes):
        ref = ref.decode("ascii", "replace")
    return -deg if str(ref).strip("\x00 ").upper() == negative else deg


def _altitude(value: Any, ref: object) -> float:
    alt = float(value)
    below = ref in (1, b"\x01") or (isinstance(ref, bytes) and ref[:1] == b"\x01")
    return -alt if below else alt


def _gps(image: str, gps: Mapping[int, Any]) -> tuple[float | None, float | None, float | None]:
    """Latitude, longitude (degrees) and altitude (metres) of an EXIF GPSInfo IFD; a field that
    is missing is None, and so is one that is malformed or absurd (with a warning, _number). A
    camera without a fix writes zeros or nothing; a fix needs both its latitude and longitude."""
    if not gps or _GPS_LAT not in gps or _GPS_LON not in gps:
        return None, None, None
    lat = _number(
        image, "EXIF GPSLatitude", lambda: _dms(gps[_GPS_LAT], gps.get(_GPS_LAT_REF, "N"), "S"), -90, 90
    )
    lon = _number(
        image, "EXIF GPSLongitude", lambda: _dms(gps[_GPS_LON], gps.get(_GPS_LON_REF, "E"), "W"), -180, 180
    )
    if lat is None or lon is None:
        return None, None, None
    read_alt = (
        (lambda: _altitude(gps[_GPS_ALT], gps.get(_GPS_ALT_REF, 0))) if _GPS_ALT in gps else (lambda: None)
    )
    return lat, lon, _number(image, "EXIF GPSAltitude", read_alt, *ALTITUDE_RANGE_M)


def gps_exif(exif: Image.Exif, lat: float, lon: float, alt: float) -> Image.Exif:
    """Add a GPSInfo IFD (degrees/minutes/seconds, altitude with its sign in GPSAltitudeRef) to
    ``exif``, as a camera with a fix writes it; seconds carry 1e-6 arcsec (~3e-5 m)."""

    def dms(v: float) -> tuple[float, float, float]:
        v = abs(v)
        d = int(v)
        m = int((v - d) * 60.0)
        return float(d), float(m), round((v - d - m / 60.0) * 3600.0, 6)

    gps = exif.get_ifd(_GPS_IFD)
    gps[_GPS_LAT_REF] = "N" if lat >= 0 else "S"
    gps[_GPS_LAT] = dms(lat)
    gps[_GPS_LON_REF] = "E" if lon >= 0 else "W"
    gps[_GPS_LON] = dms(lon)
    gps[_GPS_ALT_REF] = b"\x00" if alt >= 0 else b"\x01"
    gps[_GPS_ALT] = round(abs(alt), 3)
    return exif


def _focal_px(sub: Mapping[int, Any], width: int, height: int) -> float | None:
    """Pixels, from the focal length and the focal plane's resolution, else from the 35 mm
    equivalent; None when neither is stated (a zero is how many cameras say "unknown").
    Raises on malformed values (_number reports them)."""
    if _FOCAL in sub and _FP_XRES in sub:
        mm_per_unit = _UNIT_MM.get(int(sub.get(_FP_UNIT, 2)))
        f_mm, px_per_unit = float(sub[_FOCAL]), float(sub[_FP_XRES])
        if mm_per_unit and f_mm != 0 and px_per_unit != 0:
            return f_mm * px_per_unit / mm_per_unit
    if _FOCAL35 in sub and float(sub[_FOCAL35]) != 0:
        # 35 mm equivalent: the long side of the 36 x 24 mm frame is the long side of the image
        return float(sub[_FOCAL35]) / 36.0 * max(width, height)
    return None


def exif_for(make: str, model: str, focal_mm: float, px_per_mm: float) -> Image.Exif:
    """EXIF block stating a focal length exactly (focal mm x focal-plane px/mm), for synthetic images."""
    exif = Image.Exif()
    exif[_MAKE] = make
    exif[_MODEL] = model
    sub = exif.get_ifd(_EXIF_IFD)
    sub[_FOCAL] = focal_mm
    sub[_FP_XRES] = px_per_mm
    sub[_FP_UNIT] = 4
    return exif


def dji_xmp(
    relative_altitude: float,
    gimbal_pitch: float,
    gimbal_yaw: float | None = None,
    gimbal_roll: float | None = None,
) -> str:
    angles = "".join(
        f'drone-dji:{key}="{value:+.1f}" '
        for key, value in (("GimbalYawDegree", gimbal_yaw), ("GimbalRollDegree", gimbal_roll))
        if value is not None
    )
    return (
        '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
        '<rdf:Description xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/" '
        f'drone-dji:RelativeAltitude="{relative_altitude:+.2f}" {angles}'
        f'drone-dji:GimbalPitchDegree="{gimbal_pitch:+.1f}"/>'
        "</rdf:RDF></x:xmpmeta>"
    )
