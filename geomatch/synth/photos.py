"""Photos shipped with scikit-image: textures of the synthetic scenes, and warped-photo pairs with a
known homography (the metrics on them: :mod:`geomatch.eval.homography`).

Photos come from scikit-image's bundled data module, so tests and benchmarks need no download.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

# bundled with scikit-image (no download); grey images are stacked to RGB
PHOTOS = (
    "astronaut",
    "coffee",
    "rocket",
    "chelsea",
    "camera",
    "immunohistochemistry",
    "brick",
    "gravel",
    "moon",
    "coins",
    "clock",
    "hubble_deep_field",
    "retina",
    "cell",
    "grass",
    "motorcycle_left",
    "motorcycle_right",
)


def photo(name: str) -> np.ndarray:
    """An (H, W, 3) uint8 photo shipped by scikit-image."""
    import skimage.data as data

    if name.startswith("motorcycle_"):
        left, right, _ = data.stereo_motorcycle()
        img = left if name.endswith("left") else right
    else:
        img = getattr(data, name)()
    img = np.asarray(img)
    if img.dtype != np.uint8:
        img = (255 * (img.astype(np.float64) / max(float(img.max()), 1e-9))).astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    return np.ascontiguousarray(img[:, :, :3])


def random_homography(width: int, height: int, rng: np.random.Generator, strength: float = 0.2) -> np.ndarray:
    """A homography that keeps the image mostly in view: corners moved by up to ``strength`` of the
    size, plus a rotation of up to 25 degrees and a scale change of up to 1.4x about the centre."""
    corners = np.array([[0, 0], [width - 1, 0], [width - 1, height - 1], [0, height - 1]], np.float64)
    jitter = rng.uniform(-strength, strength, size=(4, 2)) * np.array([width, height])
    moved = corners + jitter
    angle = np.deg2rad(rng.uniform(-25, 25))
    scale = np.exp(rng.uniform(np.log(1 / 1.4), np.log(1.4)))
    c = np.array([width / 2, height / 2])
    R = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]) * scale
    moved = (moved - c) @ R.T + c
    return cv2.getPerspectiveTransform(corners.astype(np.float32), moved.astype(np.float32))


@dataclass(frozen=True)
class WarpedPair:
    name: str
    image0: np.ndarray
    image1: np.ndarray
    H: np.ndarray  # maps pixels of image0 to image1 (pixel centres at integers)


def warped_pair(name: str, seed: int, strength: float = 0.2, max_side: int | None = None) -> WarpedPair:
    img = photo(name)
    if max_side is not None and max(img.shape[:2]) > max_side:
        s = max_side / max(img.shape[:2])
        img = cv2.resize(
            img, (round(img.shape[1] * s), round(img.shape[0] * s)), interpolation=cv2.INTER_AREA
        )
    h, w = img.shape[:2]
    rng = np.random.default_rng(seed)
    H = random_homography(w, h, rng, strength)
    warped = cv2.warpPerspective(img, H, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return WarpedPair(f"{name}#{seed}", img, warped, H)


def warped_pairs(
    count: int, seed: int = 0, strength: float = 0.2, max_side: int | None = 640
) -> list[WarpedPair]:
    return [warped_pair(PHOTOS[i % len(PHOTOS)], seed + i, strength, max_side) for i in range(count)]
