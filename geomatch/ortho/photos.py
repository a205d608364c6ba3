"""The registered photos as the map reads them: decoded at working size once, kept in a cache
bounded in bytes (a thousand photos do not fit in memory, and a tile needs only the dozen that
see it), and positions projected into them.

Working size: the scale at which a photo pixel covers about one orthophoto pixel (no finer than
the photo itself), so a coarser map decodes smaller photos (JPEG's DCT scaling in read_image).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..imageio import read_image
from ..memory import ByteLRU
from .survey import OrthoError, View


class PhotoCache:
    """Photos by name at working size (``scale`` of the camera's pixels), least recently used
    out beyond ``budget_mb``."""

    def __init__(self, images: Path, budget_mb: float) -> None:
        self.images = images
        self._cache: ByteLRU[tuple[str, int], np.ndarray] = ByteLRU(budget_mb)
        self.decoded = 0  # photos decoded, for the record (a photo decoded twice counts twice)

    def get(self, view: View, scale: float) -> np.ndarray:
        side = max(16, round(max(view.width, view.height) * min(1.0, scale)))
        key = (view.name, side)
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        path = self.images / view.name
        if not path.is_file():
            raise OrthoError(f"photo {view.name} is not in {self.images}: pass the run's images")
        img = read_image(path, max_side=side)
        self.decoded += 1
        self._cache.put(key, img)
        return img

    def nbytes(self) -> int:
        return self._cache.nbytes()


def to_pixels(view: View, img: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP pixels of the camera (centres at .5) -> column, row of ``img`` (the photo at any
    size; centres at integers, as cv2.remap reads them)."""
    sx = img.shape[1] / view.width
    sy = img.shape[0] / view.height
    return uv[:, 0] * sx - 0.5, uv[:, 1] * sy - 0.5


def in_frame(view: View, uv: np.ndarray, depth: np.ndarray, border: float = 0.5) -> np.ndarray:
    """Projections that land inside the photo (``border`` pixels in) in front of the camera."""
    u, v = uv[:, 0], uv[:, 1]
    return (
        (depth > 0)
        & np.isfinite(u)
        & np.isfinite(v)
        & (u >= border)
        & (v >= border)
        & (u <= view.width - border)
        & (v <= view.height - border)
    )
