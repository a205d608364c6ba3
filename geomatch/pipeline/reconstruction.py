"""Map a project: its COLMAP database to a model (geomatch.sfm.mapping), moved into the frame of
its ground control points where it has some (geomatch.geo.gcp), with its survey report, written
once as summary.json (outputs.finish). Both runners (``geomatch run`` and a reconstruct job) map
through :func:`map_project` with settings from :func:`mapping_settings`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..geo import gcp as gcpgeo
from ..geo.gcpfile import GcpError, GcpFile, read_gcp_file
from ..geo.gcpreport import failed
from ..options import DEFAULTS
from ..sfm import mapping
from ..sfm.colmapdb import ColmapDatabase
from ..sfm.mapping import MappingSettings
from ..sfm.upright import image_up
from .plan import Plan
from .project import ProjectImages

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ControlPoints:
    """A project's ground control points: the text of its file (OpenDroneMap's gcp_list.txt), the
    points held out of the fit to judge it (by name, or how many), and how a fit that failed is
    told in the summary (the service takes its server's paths out)."""

    text: str
    checkpoints: Sequence[str] | int = 0
    explain: Callable[[Exception], str] = field(default=repr, compare=False)


def mapping_settings(
    values: Mapping[str, Any], plan: Plan, verbose: bool = False, progress: bool = False
) -> MappingSettings:
    """The mapper's settings from option values by name (a run's options, a reconstruct job's) and
    the project's plan, which says whether it has tiled pairs and is a survey: the one place
    either runner gets them, so a project is mapped alike whichever runs it."""
    base = MappingSettings()
    return MappingSettings(
        mapper=str(values.get("mapper", DEFAULTS["mapper"])),
        min_model_size=int(values.get("min_model_size", base.min_model_size)),
        min_pose_inliers=int(values.get("min_pose_inliers", DEFAULTS["min_pose_inliers"])),
        loop_check=bool(values.get("loop_check", base.loop_check)),
        tree_check=bool(values.get("tree_check", base.tree_check)),
        track_refine=bool(values.get("track_refine", base.track_refine)),
        tiled=plan.tiled,
        survey=plan.survey,
        bridges=plan.tiled_images,
        verbose=verbose,
        progress=progress,
    )


def map_project(
    db_path: Path,
    images: ProjectImages,
    plan: Plan,
    out: Path,
    settings: MappingSettings,
    control: ControlPoints | None = None,
    fields: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Map the project whose database is ``db_path`` into ``out`` (sparse/, points.ply) and return
    its summary, which outputs.finish writes. ``fields``: what the runner adds to the summary (a
    run's options and timings, a job's id); a ``timings`` there gets ``mapping``."""
    t0 = time.perf_counter()
    with ColmapDatabase(db_path) as db:
        stats, priors = db.stats(), db.pose_priors()
    # each photo's up where it is known (its gimbal, a survey's nadir camera): the view graph holds
    # the pairs' rotations to it
    up = image_up(images.metas, plan.survey)
    summary = mapping.reconstruct(db_path, images.folder, out, settings, gps=images.fixes, up=up)
    summary["database"] = stats
    summary["pose_priors"] = priors
    summary.update(plan.summary_fields())
    if control is not None:
        georeference_by_gcps(summary, out, control, images)
    extra = dict(fields or {})
    timings = {**extra.pop("timings", {}), "mapping": time.perf_counter() - t0}
    summary.update(extra, timings=timings)
    return summary


def georeference_by_gcps(
    summary: dict[str, Any], out: Path, control: ControlPoints, images: ProjectImages
) -> None:
    """Move the model in ``out`` into the frame of the control points (read against the project's
    images as they are now) and judge it at the check points (geomatch.geo.gcp). Whatever keeps
    the points from being used (a file that no longer fits the images, too few points placed in
    the model, numbers the fit cannot take) leaves the model in the frame the mapping gave it and
    goes into the summary's ``gcp`` as ``error``: the reconstruction itself succeeded."""
    # the model keeps the file it was georeferenced by: its exports place the points by it
    (out / "gcp_list.txt").write_text(control.text, encoding="utf-8")
    gcps: GcpFile | None = None
    try:
        gcps = read_gcp_file(control.text, images.sizes())
        gcpgeo.georeference_summary(summary, out, gcps, control.checkpoints)
    except GcpError as e:
        summary["gcp"] = failed(gcps, f"the project's GCP file: {e}")
    except Exception as e:  # numbers the fit cannot take: the model stays as mapped
        log.warning("GCP georeferencing failed: %r", e)
        summary["gcp"] = failed(gcps, f"the GCP georeferencing failed ({control.explain(e)})")
