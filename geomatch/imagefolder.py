"""The images of a run's folder: which files they are, and their decoded pixels kept within a
memory budget."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .imageio import read_image
from .lru import ByteLRU
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


class Images:
    """Decoded images of a folder, as many as ``budget_mb`` holds (least recently used go first):
    a 12 MP photo decodes to 36 MB, so a count bound would be a gigabyte on real projects."""

    def __init__(self, folder: Path, budget_mb: float = 256.0) -> None:
        self.folder = Path(folder)
        self._cache: ByteLRU[str, np.ndarray] = ByteLRU(budget_mb)

    def __getitem__(self, name: str) -> np.ndarray:
        img = self._cache.get(name)
        if img is None:
            img = read_image(self.folder / name)
            self._cache.put(name, img)
        return img

    def nbytes(self) -> int:
        return self._cache.nbytes()

    def clear(self) -> None:
        self._cache.clear()

    def __len__(self) -> int:
        return len(self._cache)
