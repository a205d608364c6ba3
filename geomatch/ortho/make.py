"""The map of a run folder: ``odm_dem/dsm.tif`` and ``odm_orthophoto/odm_orthophoto.tif`` (ODM's
names and places, so that the node's all.zip and the drone tools find them), a small preview PNG
for the console, and ``summary.json``'s ``ortho`` record (GSD, extent, CRS, what it cost).

Steps: the survey (survey.py) -> the DSM (dsm.py) -> the GSD -> exposure gains (gains.py) -> the
orthophoto tile by tile (mosaic.py) into a COG (cog.py). Memory is the photos' cache, one tile
and the DSM, whatever the number of photos.

The GSD, unless given: the survey's, the median over the photos of their height over the DSM
below them divided by their focal length, at the photos' working size (a photo longer than
``imageio.WORKING_SIDE`` is read at that size, as the run matched it): a 4000 px original gives a
map at twice its own pixel, a quarter of the pixels, which is what the sparse DSM's detail
supports. Each photo is then decoded at the scale where its pixel is about a map pixel.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from PIL import Image

from ..export.mapfiles import DSM, ORTHOPHOTO, PREVIEW
from ..imageio import working_scale
from ..report import survey_report
from .cog import tiled_writer, write_window
from .dsm import NODATA, build_dsm
from .gains import exposure_gains
from .grid import Grid
from .mosaic import Mosaic, footprint, render_tile
from .overlay import GCP_FILE, overlay
from .photos import PhotoCache
from .survey import OrthoError, Survey, open_survey
from .targets import measure

ORTHO_PATH, DSM_PATH = ORTHOPHOTO, DSM  # where ODM has them (export.mapfiles)
PREVIEW_PATH = PREVIEW
PREVIEW_SIDE = 1024
MAX_PIXELS = 4_000_000_000  # an orthophoto beyond this is a wrong GSD, not a survey
DSM_CELLS_PER_GSD = 4.0  # the DSM is never finer than this many map pixels


@dataclass(frozen=True)
class MapOptions:
    gsd: float | None = None  # metres per orthophoto pixel; None: the survey's (module docstring)
    tile: int = 1024  # orthophoto pixels a side per tile
    cache_mb: float = 512.0  # decoded photos kept
    dsm_cell: float | None = None  # metres; None: from the points' density


@dataclass
class MapResult:
    orthophoto: Path
    dsm: Path
    preview: Path
    record: dict[str, Any] = field(default_factory=dict)


def survey_gsd(survey: Survey, ground: np.ndarray) -> tuple[float, np.ndarray]:
    """The survey's GSD at working size and each photo's own GSD at full size (metres)."""
    heights = np.array([v.centre[2] for v in survey.views]) - ground
    focals = np.array([v.focal for v in survey.views])
    native = np.maximum(heights, 0.0) / focals
    work = native * np.array([working_scale(max(v.width, v.height)) for v in survey.views])
    positive = work[work > 0]
    if positive.size == 0:
        raise OrthoError("no camera is above the ground the model's points make: not an aerial survey")
    return float(np.median(positive)), native


def read_image_dir(run: Path) -> Path | None:
    summary = run / "summary.json"
    if not summary.is_file():
        return None
    recorded = json.loads(summary.read_text()).get("image_dir")
    return Path(recorded) if recorded else None


def tiles(grid: Grid, size: int) -> list[tuple[int, int, int, int]]:
    """Windows (row0, row1, col0, col1) row by row, each row the other way from the last (the
    photos of a tile's neighbour are still in the cache)."""
    out = []
    for i, r0 in enumerate(range(0, grid.height, size)):
        cols = list(range(0, grid.width, size))
        for c0 in reversed(cols) if i % 2 else cols:
            out.append((r0, min(grid.height, r0 + size), c0, min(grid.width, c0 + size)))
    return out


def write_preview(ortho: Path, dest: Path, side: int = PREVIEW_SIDE) -> tuple[int, int]:
    """The orthophoto at most ``side`` pixels a side, RGBA PNG, read from the COG's overviews."""
    with rasterio.open(ortho) as src:
        f = min(1.0, side / max(src.width, src.height))
        shape = (src.count, max(1, round(src.height * f)), max(1, round(src.width * f)))
        data = src.read(out_shape=shape, resampling=rasterio.enums.Resampling.average)
    tmp = dest.with_name(f".{dest.name}.part")
    Image.fromarray(np.moveaxis(data, 0, -1).astype(np.uint8), "RGBA").save(tmp, format="PNG")
    os.replace(tmp, dest)
    return shape[2], shape[1]


@dataclass
class Prepared:
    """Everything before the tiles: the mosaic every tile reads, the photos' cache, the survey's
    own GSD and the seconds spent (DSM, gains)."""

    mosaic: Mosaic
    photos: PhotoCache
    auto_gsd: float
    seconds: dict[str, float]


def prepare(run: Path, images: str | Path | None, opts: MapOptions) -> Prepared:
    """The survey of ``run``, its DSM, the GSD, the exposure gains and each photo's footprint."""
    t0 = time.perf_counter()
    survey = open_survey(run)
    image_dir = Path(images) if images is not None else read_image_dir(run)
    if image_dir is None or not image_dir.is_dir():
        raise OrthoError(f"the map needs the run's photos: {image_dir} is not a folder (pass --images)")
    if opts.gsd is not None and not (opts.gsd > 0 and np.isfinite(opts.gsd)):
        raise OrthoError(f"the GSD must be a positive number of metres, not {opts.gsd}")

    # the DSM: at the density of the points, never finer than a few map pixels
    ground0 = np.full(len(survey.views), float(np.median(survey.points[:, 2])))
    gsd0, _ = survey_gsd(survey, ground0)
    dsm = build_dsm(survey.points, DSM_CELLS_PER_GSD * (opts.gsd or gsd0), cell=opts.dsm_cell)
    centres = np.array([v.centre for v in survey.views])
    auto_gsd, native = survey_gsd(survey, dsm.at(centres[:, 0], centres[:, 1]))
    gsd = opts.gsd or auto_gsd
    t_dsm = time.perf_counter()

    w, s, e, n = dsm.grid.bounds
    grid = Grid.covering(w, s, e, n, gsd)
    if grid.width * grid.height > MAX_PIXELS:
        raise OrthoError(
            f"an orthophoto of {grid.width} x {grid.height} pixels at {gsd:.4f} m: choose a coarser GSD"
        )
    scales = np.clip(np.where(native > 0, native / gsd, 1.0), 0.02, 1.0)
    photos = PhotoCache(image_dir, opts.cache_mb)
    gains = exposure_gains(survey, dsm, photos)
    boxes = np.array([footprint(v, survey, dsm) for v in survey.views])
    pad = 0.05 * np.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1])[:, None] + dsm.cell
    boxes = boxes + pad * np.array([-1.0, -1.0, 1.0, 1.0])
    t_gains = time.perf_counter()
    mosaic = Mosaic(survey, dsm, grid, boxes, gains, scales)
    return Prepared(mosaic, photos, auto_gsd, {"dsm": t_dsm - t0, "gains": t_gains - t_dsm})


def make_map(
    run: str | Path,
    images: str | Path | None = None,
    out: str | Path | None = None,
    options: MapOptions | None = None,
) -> MapResult:
    """The DSM, orthophoto and preview of the run folder ``run`` (written under ``out``, default
    ``run``), its ``summary.json`` given the ``ortho`` record when ``out`` is the run."""
    opts = options or MapOptions()
    run = Path(run)
    dest = Path(out) if out is not None else run
    t0 = time.perf_counter()
    prep = prepare(run, images, opts)
    mosaic, photos = prep.mosaic, prep.photos
    survey, dsm, grid, gains = mosaic.survey, mosaic.dsm, mosaic.grid, mosaic.gains
    gsd, auto_gsd = grid.res, prep.auto_gsd
    w, s, e, n = dsm.grid.bounds
    t_gains = time.perf_counter()

    ortho_path, dsm_path, preview_path = dest / ORTHO_PATH, dest / DSM_PATH, dest / PREVIEW_PATH
    with tiled_writer(dsm_path, dsm.grid, survey.crs, 1, "float32", nodata=NODATA) as dst:
        write_window(dst, dsm.as_raster(), 0, 0)
    with tiled_writer(ortho_path, grid, survey.crs, 4, "uint8") as dst:
        for r0, r1, c0, c1 in tiles(grid, opts.tile):
            write_window(dst, render_tile(mosaic, photos, r0, r1, c0, c1), r0, c0)
    t_ortho = time.perf_counter()
    preview_size = write_preview(ortho_path, preview_path)

    targets = measure_targets(run, survey, ortho_path)
    lonlat = survey.frame.to_wgs84(survey.model_from_projected(np.array([[w, s, 0.0], [e, n, 0.0]])))
    record: dict[str, Any] = {
        "orthophoto": ORTHO_PATH.as_posix(),
        "dsm": DSM_PATH.as_posix(),
        "preview": {
            "path": PREVIEW_PATH.as_posix(),
            "width": preview_size[0],
            "height": preview_size[1],
            **overlay(run, survey, grid),
        },
        "gsd_m": gsd,
        "gsd_auto_m": auto_gsd,
        "dsm_cell_m": dsm.cell,
        "crs": crs_name(survey.crs),
        "frame": survey.frame.kind,
        "size_px": [grid.width, grid.height],
        "bounds": [w, s, e, n],
        "bounds_wgs84": [float(lonlat[0, 0]), float(lonlat[0, 1]), float(lonlat[1, 0]), float(lonlat[1, 1])],
        "extent_m": [e - w, n - s],
        "area_m2": float(dsm.valid.sum()) * dsm.cell**2,
        "photos": len(survey.views),
        "dsm_points": dsm.points_used,
        "dsm_points_rejected": dsm.points_rejected,
        "gains": {"min": float(gains.min()), "max": float(gains.max())},
        "photos_decoded": photos.decoded,
        "options": {k: v for k, v in asdict(opts).items()},
        "seconds": {
            "dsm": round(prep.seconds["dsm"], 3),
            "gains": round(prep.seconds["gains"], 3),
            "orthophoto": round(t_ortho - t_gains, 3),
            "total": round(time.perf_counter() - t0, 3),
        },
    }
    if targets is not None:
        record["gcp_targets"] = targets
    if dest == run:
        record_in_summary(run, record)
    return MapResult(ortho_path, dsm_path, preview_path, record)


def crs_name(crs: Any) -> str:
    """``EPSG:n`` where PROJ knows the system by a code (what the GeoTIFF records), else its text."""
    epsg = crs.to_epsg()
    return f"EPSG:{epsg}" if epsg else str(crs.to_string())


def measure_targets(run: Path, survey: Survey, ortho: Path) -> dict[str, Any] | None:
    """A GCP model's targets found on its orthophoto (targets.py), or None without GCPs."""
    gcp_file = run / GCP_FILE
    fit = json.loads((run / "summary.json").read_text()).get("gcp") or {}
    if survey.frame.kind != "GCP" or not gcp_file.is_file() or not fit.get("points"):
        return None
    sizes = {v.name: (v.width, v.height) for v in survey.views}
    return measure(ortho, gcp_file.read_text(), sizes, fit)


def record_in_summary(run: Path, record: dict[str, Any]) -> None:
    """``summary.json`` with the ``ortho`` record, replaced whole (a reader sees old or new)."""
    path = run / "summary.json"
    summary = json.loads(path.read_text())
    summary["ortho"] = record
    if "report" in summary:  # the report the run or job wrote, with the map now
        summary["report"] = survey_report(summary)
    tmp = path.with_name(f".{path.name}.ortho.part")
    tmp.write_text(json.dumps(summary, indent=1))
    os.replace(tmp, path)


def map_step(run: Path, images: str | Path | None = None, gsd: float | None = None) -> dict[str, Any]:
    """The map as a stage of ``geomatch run --ortho`` or a reconstruct job with ``ortho``: its
    record (written into the run's summary.json as ``ortho``), or ``{"skipped": why}`` when the
    model cannot have a map (not georeferenced, too few points), recorded the same way: the model
    is the run's product and stays good without a map."""
    try:
        return make_map(run, images, options=MapOptions(gsd=gsd or None)).record
    except OrthoError as e:
        record: dict[str, Any] = {"skipped": str(e)}
        record_in_summary(run, record)
        return record
