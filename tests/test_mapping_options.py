"""A survey's mapper runs lighter global bundle adjustments, while a project of a few dozen
photos keeps COLMAP's own schedule: the ground scenes' table was measured with it."""

from __future__ import annotations

from pathlib import Path

import pycolmap
import pytest

from geomatch.metadata import ImageMeta
from geomatch.options import DEFAULTS, GLOBAL_MAPPER_IMAGES, MAPPERS
from geomatch.sfm.colmapdb import ColmapDatabase
from geomatch.sfm.mapping import (
    LARGE_BA_GROWTH,
    LARGE_BA_REFINEMENTS,
    LARGE_PROJECT_IMAGES,
    incremental_options,
    pick_mapper,
    pixel_scale,
)

pytestmark = pytest.mark.unit


def test_a_small_project_keeps_colmaps_global_adjustments() -> None:
    colmap = pycolmap.IncrementalPipelineOptions()
    opts = incremental_options(LARGE_PROJECT_IMAGES - 1, 3, 30, 0)
    assert opts.ba_global_frames_ratio == colmap.ba_global_frames_ratio
    assert opts.ba_global_points_ratio == colmap.ba_global_points_ratio
    assert opts.ba_global_max_refinements == colmap.ba_global_max_refinements
    redundant = colmap.mapper.ba_global_ignore_redundant_points3D
    assert opts.mapper.ba_global_ignore_redundant_points3D == redundant


def test_a_survey_runs_fewer_and_lighter_global_adjustments() -> None:
    colmap = pycolmap.IncrementalPipelineOptions()
    opts = incremental_options(LARGE_PROJECT_IMAGES, 3, 30, 0)
    assert colmap.ba_global_frames_ratio < LARGE_BA_GROWTH
    assert opts.ba_global_frames_ratio == pytest.approx(LARGE_BA_GROWTH)
    assert opts.ba_global_points_ratio == pytest.approx(LARGE_BA_GROWTH)
    assert opts.ba_global_max_refinements == LARGE_BA_REFINEMENTS < colmap.ba_global_max_refinements
    assert opts.mapper.ba_global_ignore_redundant_points3D


def test_the_run_options_reach_the_mapper() -> None:
    opts = incremental_options(10, 5, 15, 7)
    assert (opts.min_model_size, opts.mapper.abs_pose_min_num_inliers, opts.random_seed) == (5, 15, 7)


def test_auto_maps_a_large_project_globally_and_a_small_one_incrementally() -> None:
    """The ground scenes and the drone sets (a few dozen photos) keep the incremental mapper that
    their tables were measured with; a survey of hundreds of photos gets the global one, whose
    time does not grow with a bundle adjustment per image."""
    assert pick_mapper("auto", GLOBAL_MAPPER_IMAGES - 1) == "incremental"
    assert pick_mapper("auto", GLOBAL_MAPPER_IMAGES) == "global"
    assert pick_mapper("incremental", 10_000) == "incremental"  # asked for: kept
    assert pick_mapper("global", 3) == "global"
    assert DEFAULTS["mapper"] == "auto" and "auto" in MAPPERS


def test_a_project_with_tiled_pairs_triangulates_what_only_two_images_share() -> None:
    """An aerial image's matches with the other aerial images are mostly seen by those two alone;
    without their points a ground photo that reaches the project through it cannot register.
    Ground-only projects keep COLMAP's choice."""
    assert incremental_options(10, 3, 20, 0, tiled=True).triangulation.ignore_two_view_tracks is False
    colmap = pycolmap.IncrementalPipelineOptions().triangulation.ignore_two_view_tracks
    assert incremental_options(10, 3, 30, 0).triangulation.ignore_two_view_tracks == colmap


def test_reprojection_thresholds_of_large_photos_are_held_at_the_working_size(tmp_path: Path) -> None:
    """A drone's 4000 px originals are mapped with the thresholds their 2000 px working copies
    would get; photos up to that size keep COLMAP's own."""
    colmap = pycolmap.IncrementalPipelineOptions()
    for name, (w, h), scale in (("small", (1536, 1024), 1.0), ("original", (4000, 2250), 2.0)):
        with ColmapDatabase(tmp_path / f"{name}.db") as db:
            db.add_image("a.jpg", ImageMeta(w, h, "DJI", "FC300S", 0.8 * w))
        assert pixel_scale(tmp_path / f"{name}.db") == pytest.approx(scale)
        opts = incremental_options(10, 3, 30, 0, px_scale=scale)
        assert opts.mapper.filter_max_reproj_error == pytest.approx(
            scale * colmap.mapper.filter_max_reproj_error
        )
        assert opts.triangulation.complete_max_reproj_error == pytest.approx(
            scale * colmap.triangulation.complete_max_reproj_error
        )
