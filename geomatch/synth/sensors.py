"""What a synthetic photo's camera would record besides the pixels: a GNSS fix, a drone's
barometric height and gimbal angles, written into the image's EXIF and DJI XMP: a PNG for the
ray-cast scenes (:func:`save_png`), a JPEG as a drone or phone writes it for the survey flights
(:func:`save_jpeg`, with DJI's flight yaw).

The scenes' metres are East-North-Up around :data:`GPS_ORIGIN`, so a camera centre is already a
position in that frame; a fix is the centre perturbed by N(0, sigma) east and north and
N(0, GPS_VERTICAL_FACTOR sigma) up (consumer GNSS is worse vertically), converted to WGS84. A
drone's relative altitude (a barometer's height above take-off, exact without GPS) gets its own
N(0, baro sigma). Each draw comes from a generator of its own, so asking for one leaves the
scene, its renders and the other draws as they were.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image
from PIL.PngImagePlugin import PngInfo

from ..geo.geodesy import EnuFrame
from ..metadata import ImageMeta, dji_xmp, exif_for, gps_exif, up_in_camera
from .camera import Camera, gimbal_angles

GPS_ORIGIN = EnuFrame(47.3769, 8.5417, 408.0)  # Zurich; the scene's (0, 0, 0), ellipsoidal height
GPS_NOISE_M = 1.5  # consumer GNSS, per axis horizontally: a survey flight's default
GPS_VERTICAL_FACTOR = 1.5  # vertical GNSS noise over horizontal
# a DJI barometer's relative altitude over one short flight: decimetres (per image, independent)
BARO_NOISE_M = 0.3


def gps_fixes(cams: list[Camera], sigma: float, seed: int) -> dict[str, np.ndarray]:
    """Noisy ENU positions of the camera centres. A generator of its own (not the scene's), so
    that asking for GPS leaves the scene and its renders bit-identical."""
    rng = np.random.default_rng([seed, 0x675])
    scale = np.array([sigma, sigma, GPS_VERTICAL_FACTOR * sigma])
    return {c.name: c.centre + rng.normal(0.0, 1.0, 3) * scale for c in cams}


def baro_heights(cams: list[Camera], sigma: float, seed: int) -> dict[str, float]:
    """Noisy relative altitudes of the aerial cameras (take-off at the ground, z = 0), from a
    generator of their own: adding them leaves the GPS draws as they were."""
    rng = np.random.default_rng([seed, 0xBA0])
    return {c.name: float(c.centre[2] + rng.normal(0.0, sigma)) for c in cams if c.aerial}


def xmp_ups(cams: list[Camera]) -> dict[str, np.ndarray]:
    """The world's up in each aerial camera as ``geomatch run`` reads it from the XMP this module
    writes (gimbal angles to the XMP's 0.1 deg, through metadata.up_in_camera): the gravity
    benchmarks and tests georeference with, without rendering a scene."""
    out = {}
    for c in cams:
        if c.aerial:
            pitch, yaw, roll = (round(a, 1) for a in gimbal_angles(c.R))
            up = up_in_camera(
                ImageMeta(1, 1, gimbal_pitch_deg=pitch, gimbal_yaw_deg=yaw, gimbal_roll_deg=roll)
            )
            if up is not None:
                out[c.name] = up
    return out


def save_png(
    path: Path,
    image: np.ndarray,
    cam: Camera,
    gps_enu: np.ndarray | None = None,
    height: float | None = None,
) -> None:
    """PNG with the EXIF a camera would write (exact focal length, one device per capture type,
    the GPS fix at ``gps_enu`` metres in :data:`GPS_ORIGIN`'s frame when given) and, for aerial
    images, the DJI XMP a drone would (relative altitude, ``height`` or the true one, gimbal
    pitch, yaw and roll)."""
    info = PngInfo()
    if cam.aerial:
        h = float(cam.centre[2]) if height is None else height
        info.add_itxt("XML:com.adobe.xmp", dji_xmp(h, *gimbal_angles(cam.R)))
    model = "synth-drone" if cam.aerial else "synth-handheld"
    exif = exif_for("geomatch", model, float(cam.K[0, 0]) / 100.0, 100.0)
    if gps_enu is not None:
        lat, lon, alt = GPS_ORIGIN.to_geodetic(np.asarray(gps_enu, np.float64))
        gps_exif(exif, float(lat), float(lon), float(alt))
    Image.fromarray(image).save(path, exif=exif.tobytes(), pnginfo=info)


def save_jpeg(
    path: Path,
    image: np.ndarray,
    cam: Camera,
    gps_enu: np.ndarray | None,
    height: float | None = None,
    yaw_error_deg: float = 0.0,
    model: str | None = None,
) -> None:
    """JPEG with the EXIF a camera writes (focal length, GPS at ``gps_enu`` in GPS_ORIGIN's ENU)
    and, for a drone's photo, DJI's XMP: relative altitude ``height``, the gimbal's angles and
    the flight yaw, the yaws off by the compass's ``yaw_error_deg``. A ``model`` named is a
    camera of that name with no XMP at all (a compact camera on a fixed-wing: EXIF GPS only)."""
    exif = exif_for(
        "geomatch",
        model or ("synth-drone" if cam.aerial else "synth-phone"),
        float(cam.K[0, 0]) / 100.0,
        100.0,
    )
    if gps_enu is not None:
        lat, lon, alt = GPS_ORIGIN.to_geodetic(np.asarray(gps_enu, np.float64))
        gps_exif(exif, float(lat), float(lon), float(alt))
    xmp = b""
    if cam.aerial and model is None:
        pitch, yaw, roll = gimbal_angles(cam.R)
        yaw = (yaw + yaw_error_deg + 180.0) % 360.0 - 180.0
        h = float(cam.centre[2]) if height is None else height
        xmp = (
            dji_xmp(h, pitch, yaw, roll)
            .replace(
                "drone-dji:GimbalPitchDegree",
                f'drone-dji:FlightYawDegree="{yaw:+.1f}" drone-dji:GimbalPitchDegree',
            )
            .encode()
        )
    # Pillow writes the XMP into an APP1 segment, where drones put it (an empty one: none)
    Image.fromarray(image).save(path, quality=92, exif=exif.tobytes(), xmp=xmp)
