"""The surface model: a raster of heights from the sparse model's points.

Sparse points are few (a few per square metre at best) and some are wrong (a match between two
similar roof corners lands metres above or below the roof), so:

- resolution from density: a cell holds a few points on average (``POINTS_PER_CELL`` over the
  points' convex hull), never finer than the orthophoto's pixel;
- per cell the median height (robust where a few points are off);
- outliers out first: a point further from the median of its neighbourhood (5 x 5 cells) than
  ``OUTLIER_MADS`` of that neighbourhood's spread (and at least a cell's width) goes, so a lone
  spike or pit does not make a cell, while a roof edge (where the neighbourhood's spread is the
  building's height) stays;
- holes filled by linear interpolation between the cells that have points (a Delaunay mesh of
  their centres), nearest outside it; everything outside the points' hull grown by
  ``MARGIN_CELLS`` is no-data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import interpolate, spatial

from .grid import Grid
from .survey import OrthoError

POINTS_PER_CELL = 4.0
OUTLIER_MADS = 4.0
WINDOW = 5  # cells, the neighbourhood of the outlier test
MARGIN_CELLS = 2
NODATA = -9999.0  # what ODM's dsm.tif marks no-data with


class DsmError(OrthoError):
    """The points cannot make a surface (too few, all on a line)."""


@dataclass(frozen=True)
class Dsm:
    grid: Grid
    height: np.ndarray  # (rows, cols) float64, filled everywhere (nearest beyond the hull)
    valid: np.ndarray  # (rows, cols) bool: inside the points' hull (grown by the margin)
    points_used: int
    points_rejected: int

    @property
    def cell(self) -> float:
        return self.grid.res

    def at(self, e: np.ndarray, n: np.ndarray) -> np.ndarray:
        return self.grid.sample(self.height, e, n)

    def inside(self, e: np.ndarray, n: np.ndarray) -> np.ndarray:
        """Whether positions fall in valid cells (nearest cell)."""
        row, col = self.grid.pixel_of(e, n)
        r = np.clip(np.rint(row).astype(np.int64), 0, self.grid.height - 1)
        c = np.clip(np.rint(col).astype(np.int64), 0, self.grid.width - 1)
        ok = (row > -0.5) & (row < self.grid.height - 0.5) & (col > -0.5) & (col < self.grid.width - 0.5)
        return ok & self.valid[r, c]

    def as_raster(self) -> np.ndarray:
        """float32 heights with NODATA outside the valid area, for the GeoTIFF."""
        return np.where(self.valid, self.height, NODATA).astype(np.float32)


def hull_area(en: np.ndarray) -> float:
    if len(en) < 3:
        return 0.0
    try:
        return float(spatial.ConvexHull(en).volume)  # a 2D hull's volume is its area
    except spatial.QhullError:  # all points on a line
        return 0.0


def density_cell(en: np.ndarray, floor: float) -> float:
    """The cell at which the points' hull holds ``POINTS_PER_CELL`` points per cell."""
    area = hull_area(en)
    if area <= 0:
        raise DsmError("the model's points lie on a line: no surface to grid")
    return max(math.sqrt(area * POINTS_PER_CELL / len(en)), floor)


def cell_medians(idx: np.ndarray, z: np.ndarray, ncells: int) -> tuple[np.ndarray, np.ndarray]:
    """Median height per flat cell index (NaN for empty cells) and the points per cell."""
    order = np.lexsort((z, idx))
    si, sz = idx[order], z[order]
    cells, start, count = np.unique(si, return_index=True, return_counts=True)
    lo = sz[start + (count - 1) // 2]
    hi = sz[start + count // 2]
    med = np.full(ncells, np.nan)
    med[cells] = (lo + hi) / 2
    counts = np.zeros(ncells, np.int64)
    counts[cells] = count
    return med, counts


def neighbourhood(med: np.ndarray, window: int = WINDOW, rows: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """Per cell the median of the cell medians in its window and their median absolute
    deviation (NaN where the window is empty), computed in bands of ``rows`` rows so that the
    stack of shifted copies stays small."""
    h, w = med.shape
    r = window // 2
    padded = np.pad(med, r, constant_values=np.nan)
    centre = np.full((h, w), np.nan)
    spread = np.full((h, w), np.nan)
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        stack = np.stack(
            [padded[r0 + dy : r1 + dy, dx : dx + w] for dy in range(window) for dx in range(window)]
        )
        empty = np.all(np.isnan(stack), axis=0)
        stack[:, empty] = 0.0  # all-NaN windows: no warning, marked NaN below
        c = np.nanmedian(stack, axis=0)
        s = np.nanmedian(np.abs(stack - c[None]), axis=0)
        c[empty], s[empty] = np.nan, np.nan
        centre[r0:r1], spread[r0:r1] = c, s
    return centre, spread


def build_dsm(points: np.ndarray, min_cell: float, cell: float | None = None) -> Dsm:
    """The DSM of projected points (N, 3) at ``cell`` metres (None: from the points' density,
    at least ``min_cell``)."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    points = points[np.all(np.isfinite(points), axis=1)]
    if len(points) < 3:
        raise DsmError(f"{len(points)} points: too few for a surface")
    en = points[:, :2]
    if cell is None:
        cell = density_cell(en, min_cell)
    margin = MARGIN_CELLS * cell
    lo, hi = en.min(axis=0) - margin, en.max(axis=0) + margin
    grid = Grid.covering(lo[0], lo[1], hi[0], hi[1], cell)
    row, col = grid.pixel_of(en[:, 0], en[:, 1])
    r = np.clip(np.rint(row).astype(np.int64), 0, grid.height - 1)
    c = np.clip(np.rint(col).astype(np.int64), 0, grid.width - 1)
    flat = r * grid.width + c
    ncells = grid.width * grid.height
    z = points[:, 2]

    med, _ = cell_medians(flat, z, ncells)
    centre, spread = neighbourhood(med.reshape(grid.height, grid.width))
    limit = np.maximum(OUTLIER_MADS * 1.4826 * spread, cell).ravel()
    dev = np.abs(z - centre.ravel()[flat])
    keep = ~(dev > limit[flat])  # NaN (nothing around) keeps the point
    med, _ = cell_medians(flat[keep], z[keep], ncells)
    heights = med.reshape(grid.height, grid.width)

    has = np.isfinite(heights)
    if has.sum() < 3:
        raise DsmError("too few cells with points for a surface")
    rr, cc = np.nonzero(has)
    known = np.column_stack([rr, cc]).astype(np.float64)
    vals = heights[has]
    gr, gc = np.mgrid[0 : grid.height, 0 : grid.width]
    query = np.column_stack([gr.ravel(), gc.ravel()]).astype(np.float64)
    try:
        filled = interpolate.LinearNDInterpolator(known, vals)(query)
    except spatial.QhullError:  # the cells on a line: nearest only
        filled = np.full(len(query), np.nan)
    gap = ~np.isfinite(filled)
    if gap.any():
        filled[gap] = interpolate.NearestNDInterpolator(known, vals)(query[gap])
    height = filled.reshape(grid.height, grid.width)

    valid = hull_mask(grid, en, MARGIN_CELLS)
    return Dsm(grid, height, valid, int(keep.sum()), int((~keep).sum()))


def hull_mask(grid: Grid, en: np.ndarray, grow: int) -> np.ndarray:
    """The cells inside the points' convex hull, grown by ``grow`` cells."""
    row, col = grid.pixel_of(en[:, 0], en[:, 1])
    pts = np.column_stack([col, row]).astype(np.float32)
    mask = np.zeros((grid.height, grid.width), np.uint8)
    hull = cv2.convexHull(pts)
    cv2.fillConvexPoly(mask, np.rint(hull).astype(np.int32), 1)
    if grow > 0:
        k = 2 * grow + 1
        return np.asarray(cv2.dilate(mask, np.ones((k, k), np.uint8)), bool)
    return mask.astype(bool)
