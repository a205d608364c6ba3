"""Cloud-Optimized GeoTIFFs, by rasterio (GDAL) and rio-cogeo, not by hand: what WebODM, QGIS
and tile servers open and stream by ranges.

The map is written tile by tile into a plain tiled GeoTIFF beside the target (a window at a
time, so the whole raster is never in memory), then rio-cogeo rewrites it as a COG with internal
overviews (DEFLATE: lossless, and it keeps the alpha band as a band, as ODM's orthophoto has it)
and the temporary goes; the target appears whole by a rename.
"""

from __future__ import annotations

import math
import os
import uuid
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pyproj
import rasterio
from rasterio.enums import ColorInterp
from rasterio.io import DatasetWriter
from rasterio.windows import Window
from rio_cogeo.cogeo import cog_translate, cog_validate
from rio_cogeo.profiles import cog_profiles

from .grid import Grid

BLOCK = 512
OVERVIEW_SIDE = 256


def _crs(crs: pyproj.CRS) -> rasterio.crs.CRS:
    epsg = crs.to_epsg()
    return rasterio.crs.CRS.from_epsg(epsg) if epsg else rasterio.crs.CRS.from_wkt(crs.to_wkt())


@contextmanager
def tiled_writer(
    path: Path, grid: Grid, crs: pyproj.CRS, bands: int, dtype: str, nodata: float | None = None
) -> Iterator[DatasetWriter]:
    """A temporary tiled GeoTIFF on ``grid`` to write windows into; on leaving, converted to a COG
    at ``path`` (the temporary removed either way)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}-{uuid.uuid4().hex[:8]}.tmp.tif")
    profile: dict[str, Any] = {
        "driver": "GTiff",
        "width": grid.width,
        "height": grid.height,
        "count": bands,
        "dtype": dtype,
        "crs": _crs(crs),
        "transform": grid.transform,
        "tiled": True,
        "blockxsize": BLOCK,
        "blockysize": BLOCK,
        "compress": "deflate",
        "BIGTIFF": "IF_SAFER",
    }
    if nodata is not None:
        profile["nodata"] = nodata
    try:
        with rasterio.open(tmp, "w", **profile) as dst:
            if bands == 4:
                dst.colorinterp = [ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.alpha]
            yield dst
        to_cog(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_window(dst: DatasetWriter, data: np.ndarray, row0: int, col0: int) -> None:
    """``data`` (rows, cols) or (rows, cols, bands) at (row0, col0)."""
    arr = data[..., None] if data.ndim == 2 else data
    window = Window(col0, row0, arr.shape[1], arr.shape[0])
    dst.write(np.moveaxis(arr, -1, 0), window=window)


def overview_levels(width: int, height: int, smallest: int = OVERVIEW_SIDE) -> int:
    """Halvings until the raster is at most ``smallest`` pixels a side (a viewer's first look)."""
    return max(0, math.ceil(math.log2(max(width, height) / smallest))) if max(width, height) > smallest else 0


def to_cog(src: Path, dest: Path) -> None:
    profile = dict(cog_profiles["deflate"])
    profile["blockxsize"] = profile["blockysize"] = BLOCK
    with rasterio.open(src) as s:
        levels = overview_levels(s.width, s.height)
    part = dest.with_name(f".{dest.stem}-{uuid.uuid4().hex[:8]}.part.tif")
    try:
        with warnings.catch_warnings():
            # rio-cogeo multiplies affines with `*`, which affine 3 marks as pending deprecation
            warnings.simplefilter("ignore", PendingDeprecationWarning)
            cog_translate(
                str(src),
                str(part),
                profile,
                quiet=True,
                overview_level=levels,
                overview_resampling="average",
                use_cog_driver=False,
            )
        os.replace(part, dest)
    finally:
        part.unlink(missing_ok=True)


def is_cog(path: Path) -> tuple[bool, list[str], list[str]]:
    """rio-cogeo's verdict: valid, errors, warnings."""
    valid, errors, notes = cog_validate(str(path), quiet=True)
    return bool(valid), list(errors), list(notes)
