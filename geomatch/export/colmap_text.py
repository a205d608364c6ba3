"""COLMAP's text model (cameras.txt, images.txt, points3D.txt), for tools that parse text rather
than COLMAP's binary files; written by pycolmap, so it is COLMAP's own format."""

from __future__ import annotations

from pathlib import Path

import pycolmap

from .source import Source


def write(source: Source, dest: Path) -> list[Path]:
    dest.mkdir(parents=True, exist_ok=True)
    pycolmap.Reconstruction(str(source.model)).write_text(str(dest))
    return sorted(p for p in dest.iterdir() if p.suffix == ".txt")
