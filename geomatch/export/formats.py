"""The export formats, one row each: the table that ``geomatch export`` (its choices and help), the
service's model formats (the use cases' checks, the REST schema, the gRPC conversion) and the gRPC
client read, so that a new format is its module, its row here and its line in the proto's
``ModelFormat`` enum (``tests/test_formats.py`` fails until the proto agrees with this table).

Standard library only: the service's API process and ``geomatch --help`` read the table, and a
writer's own imports (pycolmap, h5py) load when that format is written.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .source import Source

# what a format may read besides the model (``Source`` fields, checked before writing)
IMAGES, DATABASE = "images", "database"


@dataclass(frozen=True)
class ExportFormat:
    name: str  # geomatch export --format, REST ?format=, the gRPC client's name
    writer: str  # "module:function" that writes the folder: write(source, dest) -> files written
    needs: frozenset[str]  # IMAGES and / or DATABASE
    media_type: str  # what the service answers with (a zip of the folder, or model_file's type)
    help: str
    proto: int  # its number in the proto's ModelFormat enum, named MODEL_FORMAT_<NAME>
    # the service serves this file of its model folder, as the pipeline wrote it, instead of
    # zipping an export (the pipeline writes points.ply already)
    model_file: str | None = None
    # why a model folder may lack its model_file, for the service's 404
    missing: str = "no 3D points"

    @property
    def proto_name(self) -> str:
        return "MODEL_FORMAT_" + self.name.upper().replace("-", "_")

    def load(self) -> Callable[[Source, Path], list[Path]]:
        """The writer, imported now: each format pulls only what it needs."""
        module, _, function = self.writer.partition(":")
        write: Callable[[Source, Path], list[Path]] = getattr(importlib.import_module(module), function)
        return write


_ZIP = "application/zip"
FORMATS: dict[str, ExportFormat] = {
    f.name: f
    for f in (
        ExportFormat(
            "nerfstudio",
            "geomatch.export.nerfstudio:write",
            frozenset({IMAGES}),  # copied into the folder
            _ZIP,
            "transforms.json + images",
            4,
        ),
        ExportFormat(
            "colmap-text", "geomatch.export.colmap_text:write", frozenset(), _ZIP, "COLMAP text model", 5
        ),
        ExportFormat(
            "ply",
            "geomatch.export.ply:write",
            frozenset(),
            "application/octet-stream",
            "points",
            2,
            model_file="points.ply",
        ),
        ExportFormat(
            "hloc",
            "geomatch.export.hloc:write",
            frozenset({DATABASE}),  # the keypoints and verified matches
            _ZIP,
            "features.h5 + matches.h5 + pairs.txt",
            6,
        ),
        ExportFormat(
            "openmvs",
            "geomatch.export.openmvs:write",
            frozenset({IMAGES}),  # undistorted into the folder
            _ZIP,
            "undistorted COLMAP folder for OpenMVS's InterfaceCOLMAP",
            7,
        ),
        # the photos are read when present (make, model, capture time), not needed
        ExportFormat(
            "odm",
            "geomatch.export.odm:write",
            frozenset(),
            _ZIP,
            "OpenDroneMap's layout: georeferenced LAZ, shots.geojson, cameras.json, images.json, "
            "stats.json, report PDF, GCP GeoJSON",
            8,
        ),
        ExportFormat(
            "laz",
            "geomatch.export.laz:write",
            frozenset(),
            _ZIP,
            "the georeferenced point cloud (LAZ, projected CRS, colours)",
            9,
        ),
        # the map: files the map step writes into the run folder (geomatch.ortho), served as they are
        ExportFormat(
            "orthophoto",
            "geomatch.export.mapfiles:write_orthophoto",
            frozenset(),
            "image/tiff",
            "the orthophoto (Cloud-Optimized GeoTIFF, RGBA, projected CRS), when the map was made",
            10,
            model_file="odm_orthophoto/odm_orthophoto.tif",
            missing="no map: reconstruct with the option ortho",
        ),
        ExportFormat(
            "dsm",
            "geomatch.export.mapfiles:write_dsm",
            frozenset(),
            "image/tiff",
            "the surface model (Cloud-Optimized GeoTIFF, float32 heights), when the map was made",
            11,
            model_file="odm_dem/dsm.tif",
            missing="no map: reconstruct with the option ortho",
        ),
        ExportFormat(
            "map-preview",
            "geomatch.export.mapfiles:write_preview",
            frozenset(),
            "image/png",
            "the orthophoto at most 1024 px a side (PNG with alpha), for a page to show",
            12,
            model_file="odm_orthophoto/preview.png",
            missing="no map: reconstruct with the option ortho",
        ),
    )
}


def register(fmt: ExportFormat) -> None:
    """Add a row (for a format defined outside this package, and for the tests that prove the
    surfaces follow the table); every surface built afterwards offers it."""
    if fmt.name in FORMATS:
        raise ValueError(f"export format {fmt.name!r} exists already")
    FORMATS[fmt.name] = fmt


def unregister(name: str) -> None:
    FORMATS.pop(name, None)


def choices_help() -> str:
    """The formats and what each writes, as one line of help."""
    return ", ".join(f"{f.name}: {f.help}" for f in FORMATS.values())
