"""What the use cases take and give: plain values, free of the database rows and of any
transport (REST and gRPC turn them into their own shapes)."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from typing import Any, BinaryIO

import numpy as np

from geomatch_core.models import TERMINAL_STATES, Image, Job


@dataclass(frozen=True)
class Upload:
    name: str | None
    stream: BinaryIO
    capture: str | None = None  # this file's capture; None: the request's


@dataclass(frozen=True)
class ProjectView:
    id: str
    name: str
    config: dict[str, Any]
    created_at: datetime
    images: int
    has_model: bool


@dataclass(frozen=True)
class ImageView:
    id: str
    name: str
    width: int
    height: int
    capture: str
    sha256: str
    size_bytes: int
    format: str
    aerial: bool | None
    created: bool = False  # False when an identical upload already existed


@dataclass(frozen=True)
class JobView:
    id: str
    project_id: str
    kind: str
    state: str
    done: int
    total: int
    error: str | None
    options: dict[str, Any]
    result: dict[str, Any] | None
    after_job_id: str | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None

    @property
    def terminal(self) -> bool:
        return self.state in TERMINAL_STATES


@dataclass(frozen=True)
class GcpView:
    """A project's ground control points file, read against its images (``geomatch.geo.gcpfile``'s
    summary): ``points``, the usable ones; ``unusable``, the others and why; ``problems``, one line
    each. ``error``: why the stored file no longer fits the images (then ``frame`` is None)."""

    crs: str
    frame: str | None
    points: list[str]
    unusable: dict[str, str]
    problems: list[str]
    size_bytes: int
    error: str | None = None


@dataclass(frozen=True)
class ReportView:
    """A model's survey report (geomatch.report.survey_report) and the name of its project."""

    project_name: str
    report: dict[str, Any]


@dataclass(frozen=True)
class MatchRequest:
    pairs: str | list[list[str]] | None = None
    method: str | None = None
    resize: int | None = None
    tiling: str | None = None
    snap_radius: float | None = None
    camera: str | None = None
    reconstruct: bool = False  # queue a reconstruct job that starts when matching succeeds
    mapper: str | None = None
    min_pose_inliers: int | None = None  # that reconstruct job's PnP minimum (0: auto)
    ortho: str | None = None  # that reconstruct job's map (geomatch.ortho)
    ortho_gsd: float | None = None
    # that reconstruct job's check points (names, or how many), as ``start_reconstruct`` takes them
    checkpoints: list[str] | int | None = None


@dataclass(frozen=True)
class PairMatchView:
    """Matches of two images in their original pixels, as ``geomatch.matching.matcher.MatchResult``."""

    keypoints0: np.ndarray  # (N, 2) float32
    keypoints1: np.ndarray  # (N, 2) float32
    scores: np.ndarray  # (N,) float32
    F: np.ndarray  # (3, 3), x1^T F x0 = 0; zeros when it could not be fitted
    sizes: tuple[tuple[int, int], tuple[int, int]]  # (width, height) of each image
    method: str
    tiled: bool
    timings: dict[str, float]


def image_view(i: Image, created: bool = False) -> ImageView:
    return ImageView(
        i.id, i.name, i.width, i.height, i.capture, i.sha256, i.size_bytes, i.format, i.aerial, created
    )


def job_view(j: Job) -> JobView:
    return JobView(
        id=j.id,
        project_id=j.project_id,
        kind=j.kind,
        state=j.state,
        done=j.done,
        total=j.total,
        error=j.error,
        options=dict(j.options or {}),
        result=j.result,
        after_job_id=j.after_job_id,
        created_at=j.created_at,
        started_at=j.started_at,
        finished_at=j.finished_at,
    )
