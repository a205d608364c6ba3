"""A north-up raster grid in a projected CRS: where its pixels are and how to read a raster on it.

Rows run south from the grid's north edge, columns east from its west edge, and a pixel's value
belongs to its centre (GeoTIFF's PixelIsArea, the affine ``from_origin(west, north, res, res)``).
Grids of one map share their corner, so a tile's pixels and the whole map's are the same pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from affine import Affine
from scipy import ndimage


@dataclass(frozen=True)
class Grid:
    west: float
    north: float
    res: float  # metres per pixel
    width: int
    height: int

    @classmethod
    def covering(cls, west: float, south: float, east: float, north: float, res: float) -> Grid:
        """The grid at ``res`` whose corner lies on a multiple of ``res`` and covers the box."""
        w0 = math.floor(west / res) * res
        n0 = math.ceil(north / res) * res
        width = max(1, math.ceil((east - w0) / res))
        height = max(1, math.ceil((n0 - south) / res))
        return cls(w0, n0, res, width, height)

    @property
    def transform(self) -> Affine:
        return Affine(self.res, 0.0, self.west, 0.0, -self.res, self.north)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(west, south, east, north)."""
        return (self.west, self.north - self.height * self.res, self.west + self.width * self.res, self.north)

    def centres(
        self, row0: int, row1: int, col0: int, col1: int, step: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """Eastings and northings (2D, rows x cols) of the pixel centres of a window, every
        ``step``-th pixel from (row0, col0) (the window may reach past the grid)."""
        cols = np.arange(col0, col1, step, dtype=np.float64)
        rows = np.arange(row0, row1, step, dtype=np.float64)
        e = self.west + (cols + 0.5) * self.res
        n = self.north - (rows + 0.5) * self.res
        return np.meshgrid(e, n)

    def pixel_of(self, e: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fractional (row, col) of positions, pixel centres at integers."""
        col = (np.asarray(e, np.float64) - self.west) / self.res - 0.5
        row = (self.north - np.asarray(n, np.float64)) / self.res - 0.5
        return row, col

    def sample(self, raster: np.ndarray, e: np.ndarray, n: np.ndarray) -> np.ndarray:
        """``raster`` (height x width, on this grid) at positions, bilinear; past the edge the
        edge's value."""
        row, col = self.pixel_of(e, n)
        out = ndimage.map_coordinates(raster, [row.ravel(), col.ravel()], order=1, mode="nearest")
        return np.asarray(out, np.float64).reshape(np.shape(e))
