"""The undistorted COLMAP folder that OpenMVS's ``InterfaceCOLMAP`` reads.

pycolmap has no writer of OpenMVS's own ``scene.mvs``, so this is COLMAP's image undistorter
(``pycolmap.undistort_images``, output type COLMAP): ``images/`` undistorted, ``sparse/`` with
PINHOLE cameras, ``stereo/`` (patch-match configuration), exactly what
``InterfaceCOLMAP -i DIR -o scene.mvs --image-folder DIR/images`` converts.
"""

from __future__ import annotations

from pathlib import Path

import pycolmap

from ..sfm.colmaplog import colmap_log
from .source import Source


def write(source: Source, dest: Path) -> list[Path]:
    assert source.images is not None  # checked by export()
    dest.mkdir(parents=True, exist_ok=True)
    with colmap_log(False):
        pycolmap.undistort_images(str(dest), str(source.model), str(source.images), output_type="COLMAP")
    return sorted(p for p in dest.rglob("*") if p.is_file())
