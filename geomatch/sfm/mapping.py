"""Reconstruction with COLMAP (pycolmap): verification of what is unverified, mapping, export.

Pairs written by colmapdb.py are verified as they are written; ``verify`` catches pairs of a
database filled by other means. Mapping is COLMAP's incremental mapper for projects of a few dozen
images and its global mapper (GLOMAP's, merged into COLMAP 4) for larger ones (``auto``,
:func:`pick_mapper`), or either on request; the incremental mapper's later models that share
an image with its first are joined into it (modeljoin.py). The largest model is exported as
``sparse/0`` (binary and text, so both COLMAP and tools that parse text read it), ``points.ply``
and ``summary.json``; other models, if any, go to ``sparse/1`` ...
"""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
from tqdm import tqdm

from ..geo import georef, gpscheck
from ..geo.gps import GpsFixes
from ..geo.priorba import adjust_to_fixes, with_residuals
from ..imageio import working_scale
from ..memory import return_freed_memory
from ..options import (
    GLOBAL_MAPPER_IMAGES,
    MAPPERS,
    MIN_POSE_INLIERS,
    TILED_MIN_POSE_INLIERS,
)
from .colmaplog import colmap_log
from .leftovers import (
    Continuation,
    hold_to_fixes,
    leave_out_unvouched,
    place_leftovers,
    register_leftovers,
    rejoin_blocks,
    replace_misplaced,
)
from .modelagree import Agreement, agreement
from .modeljoin import Join, join_models
from .pairpose import Placement
from .sqlitecopy import snapshot_sqlite
from .thinmatches import per_image_budget, thin_matches
from .trackrefine import SURVEY, refine_tracks
from .viewgraph_filter import filter_database

# from this many images on, the incremental mapper's global bundle adjustments are lighter: they
# leave out the 3D points whose cameras other points already hold (COLMAP's
# ba_global_ignore_redundant_points3D), run when the model has grown by LARGE_BA_GROWTH in images
# or points since the last one instead of COLMAP's 10 %, and refine LARGE_BA_REFINEMENTS time(s)
# (COLMAP: up to 5). Why: global adjustments are most of a survey's mapping time and grow with the
# model, while the local adjustment after each image keeps the new cameras right in between; on the
# drone surveys the lighter ones give the same cameras, points and GPS fit (docs/benchmarks.md,
# "Drone surveys beside COLMAP SIFT"). Projects of a few dozen photos (the ground scenes) keep
# COLMAP's defaults.
LARGE_PROJECT_IMAGES = 40
LARGE_BA_GROWTH = 1.3
LARGE_BA_REFINEMENTS = 1
# a tiled project is mapped up to this many times (from the seeds after the run's) while its model
# contradicts its pairs' rotations (modelagree.py); each attempt costs seconds on such a project
MAPPING_ATTEMPTS = 4


def _size(rec: pycolmap.Reconstruction) -> tuple[int, int]:
    return (rec.num_reg_images(), rec.num_points3D())


def sfm_stats(rec: pycolmap.Reconstruction, n_images: int) -> dict[str, Any]:
    return {
        "registered": int(rec.num_reg_images()),
        "images": int(n_images),
        "points3D": int(rec.num_points3D()),
        "observations": int(rec.compute_num_observations()),
        "mean_track_length": float(rec.compute_mean_track_length()) if rec.num_points3D() else 0.0,
        "mean_observations_per_image": float(rec.compute_mean_observations_per_reg_image())
        if rec.num_reg_images()
        else 0.0,
        "mean_reprojection_error": float(rec.compute_mean_reprojection_error())
        if rec.num_points3D()
        else 0.0,
        "track_lengths": track_length_histogram(rec),
    }


TRACK_BINS = (2, 3, 4, 5, 6, 11, 21)  # lower edges: 2, 3, 4, 5, 6-10, 11-20, 21+


def track_length_histogram(rec: pycolmap.Reconstruction) -> dict[str, int]:
    """Points by the number of photos that see them: a mean hides whether a model is many short
    tracks (weak geometry) or fewer long ones, which is what a survey's accuracy rests on."""
    lengths = np.fromiter((p.track.length() for p in rec.points3D.values()), np.int64, rec.num_points3D())
    out: dict[str, int] = {}
    for lo, hi in zip(TRACK_BINS, (*TRACK_BINS[1:], None), strict=True):
        label = str(lo) if hi == lo + 1 else (f"{lo}+" if hi is None else f"{lo}-{hi - 1}")
        sel = lengths >= lo if hi is None else (lengths >= lo) & (lengths < hi)
        out[label] = int(sel.sum())
    return out


def verify(database: Path, verbose: bool = False) -> int:
    """Verify matched pairs that have no two-view geometry yet; returns how many were verified."""
    db = pycolmap.Database.open(str(database))
    try:
        names = {im.image_id: im.name for im in db.read_all_images()}
        pending = [pycolmap.pair_id_to_image_pair(p) for p in db.read_all_matches()[0]]
        pending = [(a, b) for a, b in pending if not db.exists_two_view_geometry(a, b)]
    finally:
        db.close()
    if pending:
        with tempfile.TemporaryDirectory() as tmp:
            pairs_path = Path(tmp) / "pairs.txt"
            pairs_path.write_text("".join(f"{names[a]} {names[b]}\n" for a, b in pending))
            with colmap_log(verbose):
                pycolmap.verify_matches(str(database), str(pairs_path))
    return len(pending)


def pick_mapper(mapper: str, n_images: int) -> str:
    """The mapper ``auto`` means for a project of ``n_images``: the incremental mapper adds one
    image at a time with a bundle adjustment after each, so its time grows faster than the
    images; the global mapper solves all rotations and positions at once and adjusts once. On
    small projects (the ground scenes, the drone sets of 18 and 75 photos) the incremental one
    is what every table was measured with; from GLOBAL_MAPPER_IMAGES on the global one placed a
    synthetic survey's cameras at least as well in a fraction of the time."""
    if mapper != "auto":
        return mapper
    return "global" if n_images >= GLOBAL_MAPPER_IMAGES else "incremental"


def pixel_scale(database: Path) -> float:
    """Photo pixels per working pixel of the project's largest photo (1 up to WORKING_SIDE).

    Why: COLMAP's reprojection thresholds are in photo pixels, made for SIFT found at the photo's
    size. Our points are placed at the network's size and then aligned on the photos at most
    WORKING_SIDE px wide (trackrefine.py): on larger photos (a drone's 4000 px originals) the
    thresholds are held at what they are at that size, where every set was tuned, instead of
    rejecting points for errors below the precision they were found with."""
    db = pycolmap.Database.open(str(database))
    try:
        side = max((max(c.width, c.height) for c in db.read_all_cameras()), default=0)
    finally:
        db.close()
    return working_scale(side)


def incremental_options(
    n_images: int,
    min_model_size: int,
    min_pose_inliers: int,
    seed: int,
    tiled: bool = False,
    px_scale: float = 1.0,
) -> pycolmap.IncrementalPipelineOptions:
    """COLMAP's incremental mapper as a project of ``n_images`` gets it (LARGE_PROJECT_IMAGES).
    With ``tiled`` aerial x ground pairs it also triangulates the matches that only two images
    share (COLMAP leaves them out): an aerial image's matches with the other aerial images, and
    those of two ground photos that no third one sees, are mostly such, and without their points
    a ground photo reaching the project through an aerial image has nothing to register from."""
    opts = pycolmap.IncrementalPipelineOptions()
    opts.min_model_size = min_model_size
    opts.random_seed = seed
    opts.mapper.abs_pose_min_num_inliers = min_pose_inliers
    opts.triangulation.ignore_two_view_tracks = not tiled
    # photo pixels: held at the working size's (pixel_scale)
    opts.mapper.init_max_error *= px_scale
    opts.mapper.abs_pose_max_error *= px_scale
    opts.mapper.filter_max_reproj_error *= px_scale
    opts.triangulation.merge_max_reproj_error *= px_scale
    opts.triangulation.complete_max_reproj_error *= px_scale
    if n_images >= LARGE_PROJECT_IMAGES:
        opts.mapper.ba_global_ignore_redundant_points3D = True
        opts.ba_global_frames_ratio = LARGE_BA_GROWTH
        opts.ba_global_points_ratio = LARGE_BA_GROWTH
        opts.ba_global_max_refinements = LARGE_BA_REFINEMENTS
    return opts


@dataclass(frozen=True)
class MappingSettings:
    """How a project is mapped: what both runners give :func:`reconstruct` (the pipeline's
    ``mapping_settings`` makes them from the options and the plan). ``min_pose_inliers`` 0 is
    COLMAP's 30, or 20 where the project has tiled aerial x ground pairs (``tiled``;
    options.TILED_MIN_POSE_INLIERS), which also keeps two-view tracks and runs the leftover passes
    and re-maps. ``loop_check`` / ``tree_check``: the view graph's checks (viewgraph.py);
    ``track_refine``: each track's keypoints aligned on the photos (trackrefine.py); ``survey``: every
    photo is aerial, and the track refinement takes the settings of such projects
    (trackrefine.SURVEY); ``bridges``: the images the project tiled, the only ones a join of two
    models may rest on alone (modeljoin.join_models; None: any image). ``verbose`` lets COLMAP's
    own log through (colmaplog.py); ``progress`` shows a bar of registered images instead, the one
    line a user watching a terminal needs: neither changes the model."""

    mapper: str = "auto"
    min_model_size: int = 3
    min_pose_inliers: int = 0
    loop_check: bool = True
    tree_check: bool = True
    track_refine: bool = True
    tiled: bool = False
    survey: bool = False
    bridges: tuple[str, ...] | None = None
    seed: int = 0
    verbose: bool = field(default=False, compare=False)
    progress: bool = field(default=False, compare=False)

    def as_dict(self) -> dict[str, Any]:
        """The settings that shape the model, as the summary records them."""
        return {k: v for k, v in asdict(self).items() if k not in ("verbose", "progress")}


def reconstruct(
    database: Path,
    image_dir: Path,
    out: Path,
    settings: MappingSettings | None = None,
    gps: GpsFixes | None = None,
    up: Mapping[str, np.ndarray] | None = None,
) -> dict[str, Any]:
    """Map, export the largest model (``out``: sparse/, points.ply) and return the summary, which
    its caller completes and writes (geomatch.pipeline.outputs).

    With ``gps`` every model with three or more registered images that have a fix is moved into
    the fixes' ENU frame (geo/georef.py) before it is written, so ``sparse/``, ``points.ply`` and the
    summary are all in ENU metres; the summary says whether the largest model was
    (``georeferenced``) and how well its cameras fit their fixes (``alignment``). A model the global
    mapper made (a large survey) is then bundle-adjusted with the inlier fixes as position priors
    (geo/priorba.py; ``prior_adjustment``), since its shape bends where a similarity cannot follow.

    The mapper reads a private copy of the database in which the pairs that the view graph's
    loops or its spanning tree of the strongest pairs reject (viewgraph.py) are marked
    degenerate, for the global mapper its matches are thinned to a memory budget
    (thinmatches.py), and then, with ``track_refine``, each track's keypoints are aligned on the
    photos (trackrefine.py); ``database`` itself keeps every verified pair and the matcher's keypoints,
    and the summary lists the dropped pairs (``view_graph``), the moved points
    (``track_refinement``) and the kept matches (``thinning``). ``up``: each photo's up in its
    camera frame where the photo knows it (upright.image_up), which the view graph holds a pair's
    rotation to.
    """
    settings = settings or MappingSettings()
    mapper, min_model_size, seed = settings.mapper, settings.min_model_size, settings.seed
    min_pose_inliers, tiled, survey = settings.min_pose_inliers, settings.tiled, settings.survey
    loop_check, tree_check, track_refine = settings.loop_check, settings.tree_check, settings.track_refine
    verbose, progress, bridges = settings.verbose, settings.progress, settings.bridges
    if mapper not in MAPPERS:
        raise ValueError(f"unknown mapper {mapper!r}; choose from {', '.join(MAPPERS)}")
    # seconds per stage, so a slow project says which stage to look at
    stages: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(stage: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        stages[stage] = round(now - clock, 2)
        clock = now

    verify(database, verbose)
    lap("verify")
    bridge_names = frozenset(bridges) if bridges is not None else None
    work = out / ".mapping"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    mapped = work / "database.db"
    snapshot_sqlite(database, mapped)
    checked = loop_check or tree_check
    report = filter_database(str(mapped), loops=loop_check, tree=tree_check, up=up) if checked else None
    lap("view_graph")
    db = pycolmap.Database.open(str(mapped))
    try:
        all_names = sorted(im.name for im in db.read_all_images())
    finally:
        db.close()
    n_images = len(all_names)
    px_scale = pixel_scale(mapped)
    requested, mapper = mapper, pick_mapper(mapper, n_images)
    # thinned before the refinement, which then aligns only the observations the mapper will see
    thinned = thin_matches(mapped, per_image_budget(n_images)) if mapper == "global" else None
    lap("thinning")
    refined = refine_tracks(mapped, image_dir, SURVEY if survey else None) if track_refine else None
    return_freed_memory()  # the stages' peaks do not stack on each other's freed heap
    lap("track_refine")
    joins: list[Join] = []
    placements: list[Placement] = []
    agreed: Agreement | None = None
    left_out: list[str] = []
    attempts = 1
    bar = tqdm(total=n_images, desc=f"mapping ({mapper})", unit="image", disable=not progress)
    with bar, colmap_log(verbose):
        if mapper == "incremental":

            def attempt(k: int) -> tuple[list[pycolmap.Reconstruction], list[Join], list[Placement]]:
                options = incremental_options(
                    n_images,
                    min_model_size,
                    min_pose_inliers or (TILED_MIN_POSE_INLIERS if tiled else MIN_POSE_INLIERS),
                    seed + k,
                    tiled,
                    px_scale,
                )
                into = work if k == 0 else work / f"attempt_{k}"
                into.mkdir(parents=True, exist_ok=True)
                found = pycolmap.incremental_mapping(
                    str(mapped),
                    str(image_dir),
                    str(into),
                    options,
                    initial_image_pair_callback=lambda: bar.update(2),
                    next_image_callback=lambda: bar.update(1),
                )
                ordered = sorted(found.values(), key=_size, reverse=True)
                found_list, joins = join_models(
                    ordered, mapped, image_dir, into / "joined", options, bridge_names
                )
                placements: list[Placement] = []
                if tiled and found_list:
                    more = Continuation(mapped, image_dir, options, n_images, bridge_names)
                    if report is not None:
                        found_list, rejoined = rejoin_blocks(found_list, report, more, into / "rejoined")
                        joins = joins + rejoined
                    found_list[0] = register_leftovers(found_list[0], more, into)
                    found_list[0], placements = place_leftovers(found_list[0], more, into / "placed")
                    if report is not None:
                        found_list[0], replaced = replace_misplaced(
                            found_list[0], report, more, into / "replaced"
                        )
                        placements += replaced
                        found_list[0], doubted[k] = leave_out_unvouched(
                            found_list[0], report, into / "vouched"
                        )
                return found_list, joins, placements

            # a tiled project's model is held to its pairs' rotations (modelagree.py): one that
            # contradicts them or lacks images is mapped again from the next seed, and the
            # attempt whose model agrees best is kept
            tries = MAPPING_ATTEMPTS if tiled and report is not None else 1
            best_score = None
            doubted: dict[int, list[str]] = {}  # per attempt, cameras left out (leftovers.py)
            for k in range(tries):
                found_list_k, joins_k, placements_k = attempt(k)
                held = (
                    agreement(found_list_k[0], report.kept_rotations, report.kept_inliers)
                    if found_list_k and report is not None
                    else None
                )
                score = held.score if held is not None else -1
                if best_score is None or score > best_score:
                    best_score, agreed = score, held
                    found_list, joins, placements = found_list_k, joins_k, placements_k
                    left_out = doubted.get(k, [])
                attempts = k + 1
                if held is not None and held.clean and found_list_k[0].num_reg_images() >= n_images:
                    break
            models = dict(enumerate(found_list))
        else:
            gopts = pycolmap.GlobalPipelineOptions()
            if hasattr(gopts, "random_seed"):
                gopts.random_seed = seed
            models = pycolmap.global_mapping(str(mapped), str(image_dir), str(work), gopts)
        best_count = max((r.num_reg_images() for r in models.values()), default=0)
        bar.n = best_count  # the bar ends at the largest model's count (the callbacks count tries)
        bar.refresh()
    return_freed_memory()
    lap("mapper")
    ranked = sorted(models.values(), key=_size, reverse=True)
    alignments = [
        georef.align(rec, gps.enu, up_cam=gps.up, heights=gps.heights) if gps is not None else None
        for rec in ranked
    ]
    lap("georeference")
    adjusted = None
    if mapper == "global" and gps is not None and alignments and alignments[0] is not None:
        # a large survey's globally mapped shape bends where a similarity cannot follow (priorba.py)
        adjusted = adjust_to_fixes(ranked[0], gps.enu, alignments[0])
        if adjusted is not None:
            alignments[0] = with_residuals(ranked[0], gps.enu, alignments[0])
        lap("prior_adjustment")
    fixed_check: gpscheck.GpsCheck | None = None
    if gps is not None and ranked and alignments[0] is not None:
        # a camera far beyond the fixes' fitted noise is a wrong registration: taken out, the
        # mapper carried on (it and the images still out may find their right poses), and what is
        # still beyond taken out for good (geo/gpscheck.py, leftovers.hold_to_fixes)
        fixed_check = gpscheck.check(ranked[0], gps.enu)
        if fixed_check is not None and (fixed_check.offenders or ranked[0].num_reg_images() < n_images):
            floor = min_pose_inliers or (TILED_MIN_POSE_INLIERS if tiled else MIN_POSE_INLIERS)
            more = Continuation(
                mapped,
                image_dir,
                incremental_options(n_images, min_model_size, floor, seed, tiled, px_scale),
                n_images,
            )
            before = _size(ranked[0])
            with colmap_log(verbose):
                ranked[0], fixed_check = hold_to_fixes(ranked[0], gps.enu, fixed_check, more, work / "gps")
            if fixed_check.offenders or _size(ranked[0]) != before:
                again = georef.align(ranked[0], gps.enu, up_cam=gps.up, heights=gps.heights)
                alignments[0] = again if again is not None else alignments[0]
        lap("gps_check")
    sparse = out / "sparse"
    shutil.rmtree(sparse, ignore_errors=True)
    for i, rec in enumerate(ranked):
        d = sparse / str(i)
        d.mkdir(parents=True)
        rec.write_binary(str(d))
        if i == 0:
            rec.write_text(str(d))
    shutil.rmtree(work, ignore_errors=True)
    summary: dict[str, Any] = {"mapper": mapper, "mapper_requested": requested, "models": len(ranked)}
    summary["view_graph"] = report.as_dict() if report is not None else None
    summary["joined_models"] = [j.as_dict() for j in joins if not j.refused]
    # blocks a join would have placed against the pairs they have with the rest: left apart
    summary["joins_refused"] = [j.as_dict() for j in joins if j.refused]
    summary["placed_from_pairs"] = [p.as_dict() for p in placements]
    summary["mapping_attempts"] = attempts
    summary["pair_agreement"] = agreed.as_dict() if agreed is not None else None
    summary["unvouched_left_out"] = left_out
    summary["track_refinement"] = refined
    summary["thinning"] = thinned
    summary["mapping_seconds"] = stages
    summary["prior_adjustment"] = adjusted.as_dict() if adjusted is not None else None
    summary["gps_check"] = fixed_check.as_dict() if fixed_check is not None else None
    summary.update(georef.summary_fields(gps, alignments[0] if alignments else None))
    if ranked:
        best = ranked[0]
        best.export_PLY(str(out / "points.ply"))
        if gps is not None and alignments[0] is not None:
            georef.ply_origin_comment(out / "points.ply", gps.frame)
        summary.update(sfm_stats(best, n_images))
        summary["registered_names"] = sorted(im.name for im in best.images.values() if im.has_pose)
        summary["unregistered_names"] = sorted(set(all_names) - set(summary["registered_names"]))
    else:
        (out / "points.ply").unlink(missing_ok=True)
        summary.update(
            registered=0, images=n_images, points3D=0, mean_track_length=0.0, mean_reprojection_error=0.0
        )
        summary["registered_names"] = []
        summary["unregistered_names"] = all_names
    summary["mapping_settings"] = settings.as_dict()
    return summary
