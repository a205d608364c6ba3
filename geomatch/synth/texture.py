"""Surface textures for the ray-cast scenes: photo patches that no other place in a scene shares.

Structure-from-motion folds a reconstruction onto itself where two surfaces look alike, so every
surface gets content of its own: a patch of a photo shipped by scikit-image, colour-shifted and
marked with random shapes (corners at every scale for the detectors). :func:`sample_texture` is
the renderers' bilinear lookup into such a texture.
"""

from __future__ import annotations

import cv2
import numpy as np

# the photos (photos.photo) the textures are cut from
TEXTURES = (
    "astronaut",
    "coffee",
    "rocket",
    "chelsea",
    "immunohistochemistry",
    "hubble_deep_field",
    "retina",
    "motorcycle_left",
    "camera",
    "brick",
    "gravel",
    "coins",
    "clock",
    "cell",
    "moon",
    "grass",
    "logo",
)
# what a ray that meets nothing sees
SKY = np.array([200.0, 215.0, 235.0])


def scribble(img: np.ndarray, rng: np.random.Generator, n: int, max_radius: int | None = None) -> None:
    """Random coloured shapes drawn in place: unique, corner-rich marks at every scale."""
    h, w = img.shape[:2]
    max_radius = max_radius or w // 24
    for _ in range(n):
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        r = int(rng.integers(3, max(4, max_radius)))
        kind = rng.integers(3)
        if kind == 0:
            cv2.circle(img, (x, y), r, colour, -1 if rng.random() < 0.6 else 2, cv2.LINE_AA)
        elif kind == 1:
            cv2.rectangle(img, (x, y), (x + r, y + int(rng.integers(3, 2 * r + 4))), colour, -1)
        else:
            pts = (np.array([x, y]) + rng.integers(-2 * r, 2 * r + 1, (3, 2))).astype(np.int32)
            cv2.polylines(img, [pts], False, colour, int(rng.integers(1, 4)), cv2.LINE_AA)


def patches(img: np.ndarray, n: int) -> list[np.ndarray]:
    """The photo cut into n x n disjoint patches: used once each, no two surfaces share content."""
    h, w = img.shape[:2]
    return [
        img[i * h // n : (i + 1) * h // n, j * w // n : (j + 1) * w // n] for i in range(n) for j in range(n)
    ]


def unique_texture(src: np.ndarray, size: int, rng: np.random.Generator, shapes: int = 60) -> np.ndarray:
    """A photo patch, colour-shifted and marked with random shapes."""
    img = cv2.resize(src, (size, size), interpolation=cv2.INTER_CUBIC)
    gain = rng.uniform(0.7, 1.2, 3)
    img = np.clip(img.astype(np.float32) * gain + rng.uniform(-25, 25, 3), 0, 255).astype(np.uint8)
    img = np.ascontiguousarray(img)
    scribble(img, rng, shapes)
    return img


def sample_texture(
    tex: np.ndarray, x: np.ndarray, y: np.ndarray, border: int = cv2.BORDER_REFLECT
) -> np.ndarray:
    """Bilinear texture lookups at (x, y) texel coordinates; cv2.remap wants a 2-D map under 32767
    a side, so the points are laid out in rows of 4096."""
    n = x.size
    cols = 4096
    rows = -(-n // cols)
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n], my[:n] = x, y
    out = cv2.remap(tex, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR, borderMode=border)
    return out.reshape(-1, 3)[:n]
