"""Reading images and preparing network inputs.

Images are used in their stored pixel orientation (EXIF orientation is not applied), which is
what COLMAP does, so keypoints written to a COLMAP database line up with what COLMAP reads.
"""

from __future__ import annotations

import hashlib
import io
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from PIL import Image

MAX_PIXELS = 250_000_000  # beyond this a file is treated as a decompression bomb
# Pillow's own guard warns above MAX_IMAGE_PIXELS (89.5 MP by default) and refuses twice that, which
# would reject real 100-150 MP aerial frames; it is set to our limit so that the two agree.
Image.MAX_IMAGE_PIXELS = MAX_PIXELS


# The longer side a run works at on larger photos (the matcher's input, the aerial crops, the track
# refinement; the mapper's pixel thresholds are held at it): the matcher finds its points at 640 px,
# so a 2000 px copy still resolves a fifth of a network pixel, and every drone set was tuned on
# 2000 px copies of its photos. A 4000 px original decodes to it at half scale straight from the
# JPEG (a quarter of the pixels to decode, hash, turn and keep).
WORKING_SIDE = 2000


class ImageReadError(ValueError):
    """The input is missing, empty, truncated, too large or not an image."""


def read_image(source: str | os.PathLike[str] | bytes, max_side: int | None = None) -> np.ndarray:
    """Decode to an (H, W, 3) uint8 RGB array, or raise ImageReadError with a one-line reason.
    ``max_side``: a larger photo comes back with its longer side this long (working_size), decoded
    at the smallest JPEG DCT scale that still covers it and area-resized from there."""
    if isinstance(source, bytes):
        name, data = "<bytes>", source
    else:
        path = Path(source)
        name = str(path)
        if not path.exists():
            raise ImageReadError(f"{name}: no such file")
        if not path.is_file():
            raise ImageReadError(f"{name}: not a file")
        data = path.read_bytes()
    if not data:
        raise ImageReadError(f"{name}: empty file")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(data)) as im:
                if im.width * im.height > MAX_PIXELS:
                    raise ImageReadError(f"{name}: {im.width}x{im.height} exceeds {MAX_PIXELS} pixels")
                target = working_size(im.width, im.height, max_side)
                if target != (im.width, im.height):
                    im.draft("RGB", target)
                im.load()
                rgb = im.convert("RGB")
    except ImageReadError:
        raise
    except (
        OSError,
        SyntaxError,
        ValueError,
        Image.DecompressionBombError,
        Image.DecompressionBombWarning,
    ) as e:
        raise ImageReadError(f"{name}: not a readable image ({e})") from None
    arr = np.array(rgb, dtype=np.uint8)  # writable: torch.from_numpy warns on read-only
    if max_side and (arr.shape[1], arr.shape[0]) != target:
        arr = np.ascontiguousarray(cv2.resize(arr, target, interpolation=cv2.INTER_AREA))
    if arr.shape[0] < 16 or arr.shape[1] < 16:
        raise ImageReadError(f"{name}: {arr.shape[1]}x{arr.shape[0]} is too small to match (min 16x16)")
    return arr


def working_scale(long_side: int) -> float:
    """Photo pixels per working pixel for a photo whose longer side is ``long_side`` (1 up to
    WORKING_SIDE): what COLMAP's pixel thresholds are scaled by for such a photo."""
    return max(1.0, long_side / WORKING_SIDE)


def working_size(width: int, height: int, max_side: int | None) -> tuple[int, int]:
    """(width, height) of a photo read at ``max_side`` (None: as stored)."""
    if not max_side or max(width, height) <= max_side:
        return width, height
    f = max_side / max(width, height)
    return max(1, round(width * f)), max(1, round(height * f))


def read_gray(path: str | os.PathLike[str], max_side: int | None) -> tuple[np.ndarray, tuple[float, float]]:
    """The photo's luminance as float32 in [0, 1], its longer side at most ``max_side`` (None: as
    stored), and the scale (working px per photo px, x and y). Why not read_image and a resize: a
    JPEG decodes straight to its luminance at 1/2, 1/4 or 1/8 size (Pillow's draft: the DCT is
    scaled, the colour planes are never built), which on 12 MP originals is several times faster
    than a full decode, and the step that needs it (trackrefine.py) reads every photo again."""
    name = str(path)
    try:
        with Image.open(path) as im:
            w, h = im.size
            if w * h > MAX_PIXELS:
                raise ImageReadError(f"{name}: {w}x{h} exceeds {MAX_PIXELS} pixels")
            tw, th = working_size(w, h, max_side)
            if (tw, th) != (w, h):
                im.draft("L", (tw, th))  # the smallest DCT scale that still covers the target
            gray = np.asarray(im.convert("L"), dtype=np.float32) / 255.0
    except ImageReadError:
        raise
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as e:
        raise ImageReadError(f"{name}: not a readable image ({e})") from None
    if gray.shape != (th, tw):
        gray = np.asarray(cv2.resize(gray, (tw, th), interpolation=cv2.INTER_AREA), np.float32)
    return gray, (tw / w, th / h)


def image_key(image: np.ndarray) -> str:
    """Content hash of the decoded pixels: the feature cache key."""
    h = hashlib.sha256()
    h.update(str(image.shape).encode())
    h.update(np.ascontiguousarray(image).data)  # the buffer itself: no copy of the pixels
    return h.hexdigest()


@dataclass(frozen=True)
class Prepared:
    tensor: torch.Tensor  # (1, 3, H, W) float in [0, 1]
    original_size: tuple[int, int]  # (W, H)
    scale: tuple[float, float]  # network px per original px, x and y

    def to_original(self, points: torch.Tensor) -> np.ndarray:
        """Network-input pixels -> original pixels (pixel centres at integers in both)."""
        sx, sy = self.scale
        p = points.detach().double().cpu().numpy().reshape(-1, 2)
        return np.stack([(p[:, 0] + 0.5) / sx - 0.5, (p[:, 1] + 0.5) / sy - 0.5], 1)

    def from_original(self) -> np.ndarray:
        """3x3 map from original pixels to network pixels."""
        sx, sy = self.scale
        return np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1.0]])


def prepare(image: np.ndarray, resize: int | None, device: torch.device, multiple: int = 16) -> Prepared:
    """Resize so the longer side is ``resize`` (None: keep), each side rounded to ``multiple``."""
    h, w = image.shape[:2]
    s = 1.0 if not resize else resize / max(h, w)
    nw = max(multiple, round(w * s / multiple) * multiple)
    nh = max(multiple, round(h * s / multiple) * multiple)
    if (nw, nh) != (w, h):
        interp = cv2.INTER_AREA if nw * nh < w * h else cv2.INTER_LINEAR
        image = cv2.resize(image, (nw, nh), interpolation=interp)
    t = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float().div(255.0)
    return Prepared(t.to(device), (w, h), (nw / w, nh / h))


def snap_radius(radius: float, resize: int | None, long_side: int) -> float:
    """Consolidation radius in original pixels, from ``radius`` in network pixels (as
    ``geomatch run --snap-radius``): it grows with the downscale, since a match is no more precise
    than the resolution it was found at. ``long_side``: the image's longer side."""
    if radius <= 0:
        return 0.0
    return radius * (long_side / resize if resize else 1.0)
