"""COLMAP's own synthetic dataset written into a database: exact matches and two-view geometries
of known cameras, for the checks that read a database and hold a model to it."""

from __future__ import annotations

from pathlib import Path

import pycolmap


def synthetic_database(path: Path, frames: int, points: int) -> pycolmap.Reconstruction:
    """One camera, ``frames`` images seeing all ``points``; every pair verified with every point
    as an inlier. Returns the true model; the database is written at ``path``."""
    opts = pycolmap.SyntheticDatasetOptions()
    opts.num_rigs, opts.num_cameras_per_rig, opts.num_frames_per_rig, opts.num_points3D = 1, 1, frames, points
    db = pycolmap.Database.open(str(path))
    try:
        return pycolmap.synthesize_dataset(opts, db)
    finally:
        db.close()
