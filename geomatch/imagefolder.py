"""The images of a run's folder: which files they are, and their decoded pixels kept within a
memory budget."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from .imageio import read_image, working_size
from .memory import ByteLRU
from .options import IMAGE_SUFFIXES


class PipelineError(ValueError):
    """Bad input to a run: no images, unknown names, bad pair spec."""


def list_images(folder: Path) -> list[str]:
    if not folder.is_dir():
        raise PipelineError(f"{folder}: not a directory")
    names = sorted(
        str(p.relative_to(folder))
        for p in folder.rglob("*")
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
    )
    if len(names) < 2:
        raise PipelineError(f"{folder}: found {len(names)} image(s); need at least 2")
    return names


# (x scale, y scale) from working to photo pixels, and the photo's (width, height)
PhotoScale = tuple[float, float, tuple[int, int]]


def to_photo(size: tuple[int, int], max_side: int | None) -> PhotoScale | None:
    """How a photo of ``size`` (width, height) read at ``max_side`` maps back to its own pixels;
    None when it is read as stored."""
    w, h = working_size(*size, max_side)
    if (w, h) == size:
        return None
    return size[0] / w, size[1] / h, size


def photo_size(path: Path) -> tuple[int, int]:
    """(width, height) of a photo as stored, from its header."""
    with Image.open(path) as im:
        return int(im.size[0]), int(im.size[1])


class Images:
    """Decoded images of a folder, as many as ``budget_mb`` holds (least recently used go first):
    a 12 MP photo decodes to 36 MB, so a count bound would be a gigabyte on real projects."""

    def __init__(self, folder: Path, budget_mb: float = 256.0, max_side: int | None = None) -> None:
        """``max_side``: photos with a longer side beyond it are kept at it (imageio.WORKING_SIDE):
        what is matched of them is in working pixels then, which :meth:`to_photo` maps back."""
        self.folder = Path(folder)
        self.max_side = max_side
        self._cache: ByteLRU[str, np.ndarray] = ByteLRU(budget_mb)
        self._sizes: dict[str, tuple[int, int]] = {}  # (width, height) as stored, once read

    def __getitem__(self, name: str) -> np.ndarray:
        img = self._cache.get(name)
        if img is None:
            img = read_image(self.folder / name, self.max_side)
            if self.max_side and name not in self._sizes:  # decoded above: a readable image
                self._sizes[name] = photo_size(self.folder / name)
            self._cache.put(name, img)
        return img

    def to_photo(self, name: str) -> PhotoScale | None:
        """(x, y scale from working to photo pixels, the photo's (width, height)) of an image read
        below its stored size; None when it is read as stored."""
        size = self._sizes.get(name)
        return to_photo(size, self.max_side) if size is not None else None

    def nbytes(self) -> int:
        return self._cache.nbytes()

    def clear(self) -> None:
        self._cache.clear()

    def __len__(self) -> int:
        return len(self._cache)
