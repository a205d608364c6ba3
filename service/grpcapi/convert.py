"""Between messages and the use cases' views and requests: the gRPC twin of ``schemas.py``."""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping
from datetime import UTC, datetime
from typing import Any

from google.protobuf import struct_pb2, timestamp_pb2

from geomatch import options
from geomatch.export.formats import FORMATS, ExportFormat

from ..usecases.outputs import model_formats
from ..usecases.views import GcpView, ImageView, JobView, MatchRequest, PairMatchView, ProjectView
from .framing import CAPTURES
from .pb import pb2

CONFIG_FIELDS = options.PROJECT_OPTIONS  # ProjectConfig's fields, and SubmitMatchingRequest's but pairs
PAIR_FIELDS = options.PAIR_OPTIONS  # MatchPairOptions' fields
# SubmitReconstructionRequest's mapping options; its mapper is start_reconstruct's own argument
MAPPING_FIELDS = tuple(n for n in options.RECONSTRUCT_OPTIONS if n != "mapper")
CAPTURE_ENUM = {"auto": pb2.CAPTURE_AUTO, "aerial": pb2.CAPTURE_AERIAL, "ground": pb2.CAPTURE_GROUND}
JOB_KINDS = {
    "match": pb2.JOB_KIND_MATCH,
    "reconstruct": pb2.JOB_KIND_RECONSTRUCT,
    "localize": pb2.JOB_KIND_LOCALIZE,
}
JOB_STATES = {
    "queued": pb2.JOB_STATE_QUEUED,
    "running": pb2.JOB_STATE_RUNNING,
    "succeeded": pb2.JOB_STATE_SUCCEEDED,
    "failed": pb2.JOB_STATE_FAILED,
    "cancelled": pb2.JOB_STATE_CANCELLED,
}
JOB_STATE_NAMES = {v: k for k, v in JOB_STATES.items()}
# the service's own files of a model (geomatch.export.formats' rows name the others); unspecified
# is the archive
OWN_FORMATS = {"MODEL_FORMAT_UNSPECIFIED": "zip", "MODEL_FORMAT_ZIP": "zip", "MODEL_FORMAT_JSON": "json"}


def enum_problems(formats: Iterable[ExportFormat], enum: Mapping[str, int]) -> list[str]:
    """How the export table and the proto's ModelFormat (value name -> number) disagree: a row
    whose MODEL_FORMAT_<NAME> is missing or numbered otherwise, a value that no row and none of
    the service's own files names."""
    rows = {f.proto_name: f for f in formats}
    problems = [
        f"{name} ({f.name}, {f.proto} in the export table) is not in the proto's ModelFormat"
        if name not in enum
        else f"{name} is {enum[name]} in the proto, {f.proto} in the export table ({f.name})"
        for name, f in rows.items()
        if enum.get(name) != f.proto
    ]
    problems += [
        f"{name} of the proto's ModelFormat is no export format (geomatch.export.formats)"
        for name in enum
        if name not in rows and name not in OWN_FORMATS
    ]
    return problems


_problems = enum_problems(FORMATS.values(), dict(pb2.ModelFormat.items()))
assert not _problems, "; ".join(_problems)
MODEL_FORMATS = {pb2.ModelFormat.Value(name): fmt for name, fmt in OWN_FORMATS.items()} | {
    f.proto: f.name for f in FORMATS.values()
}
assert set(CAPTURES.values()) == set(CAPTURE_ENUM)
assert set(MODEL_FORMATS.values()) == set(model_formats())  # the REST formats but scene


def optional_fields(msg: Any, names: tuple[str, ...]) -> dict[str, Any]:
    """The ``optional`` fields the client set: unset means "the default", not zero or empty."""
    return {n: getattr(msg, n) for n in names if msg.HasField(n)}


def timestamp(t: datetime | None) -> timestamp_pb2.Timestamp | None:
    if t is None:
        return None
    ts = timestamp_pb2.Timestamp()
    ts.FromDatetime(t if t.tzinfo else t.replace(tzinfo=UTC))
    return ts


def struct(d: dict[str, Any] | None) -> struct_pb2.Struct | None:
    """JSON values as a Struct (numbers become doubles there; non-finite ones become null)."""
    if d is None:
        return None
    s = struct_pb2.Struct()
    s.update(json.loads(json.dumps(d, default=str), parse_constant=lambda c: None))
    return s


def project(p: ProjectView) -> pb2.Project:
    known = {k: v for k, v in p.config.items() if k in CONFIG_FIELDS}
    return pb2.Project(
        id=p.id,
        name=p.name,
        config=pb2.ProjectConfig(**known),
        created_at=timestamp(p.created_at),
        images=p.images,
        has_model=p.has_model,
    )


def image(i: ImageView) -> pb2.Image:
    msg = pb2.Image(
        id=i.id,
        name=i.name,
        width=i.width,
        height=i.height,
        capture=CAPTURE_ENUM.get(i.capture, pb2.CAPTURE_UNSPECIFIED),
        sha256=i.sha256,
        size_bytes=i.size_bytes,
        format=i.format,
        created=i.created,
    )
    if i.aerial is not None:
        msg.aerial = i.aerial
    return msg


def job(j: JobView) -> pb2.Job:
    msg = pb2.Job(
        id=j.id,
        project_id=j.project_id,
        kind=JOB_KINDS.get(j.kind, pb2.JOB_KIND_UNSPECIFIED),
        state=JOB_STATES.get(j.state, pb2.JOB_STATE_UNSPECIFIED),
        progress=pb2.Progress(done=j.done, total=j.total),
        options=struct(j.options),
        result=struct(j.result),
        created_at=timestamp(j.created_at),
        started_at=timestamp(j.started_at),
        finished_at=timestamp(j.finished_at),
    )
    if j.error is not None:
        msg.error = j.error
    if j.after_job_id is not None:
        msg.after_job_id = j.after_job_id
    return msg


def match_request(req: pb2.SubmitMatchingRequest) -> MatchRequest:
    pairs: str | list[list[str]] | None = None
    which = req.WhichOneof("pairs")
    if which == "pair_spec":
        pairs = req.pair_spec
    elif which == "pair_list":
        pairs = [[p.name0, p.name1] for p in req.pair_list.pairs]
    opts = optional_fields(req, tuple(n for n in CONFIG_FIELDS if n != "pairs"))
    return MatchRequest(pairs=pairs, reconstruct=req.reconstruct, **opts)


def checkpoints(req: pb2.SubmitReconstructionRequest) -> list[str] | int | None:
    """The request's check points: a count, names, or None (neither set)."""
    which = req.WhichOneof("checkpoints")
    if which == "checkpoint_count":
        return int(req.checkpoint_count)
    if which == "checkpoint_names":
        return list(req.checkpoint_names.names)
    return None


def gcp(g: GcpView) -> pb2.GcpSummary:
    msg = pb2.GcpSummary(
        crs=g.crs,
        frame=g.frame or "",
        points=g.points,
        unusable=g.unusable,
        problems=g.problems,
        size_bytes=g.size_bytes,
    )
    if g.error is not None:
        msg.error = g.error
    return msg


def model_summary(summary: dict[str, Any]) -> pb2.ModelSummary:
    def number(key: str) -> float:
        v = summary.get(key)
        return float(v) if isinstance(v, int | float) and math.isfinite(v) else 0.0

    return pb2.ModelSummary(
        registered=int(number("registered")),
        images=int(number("images")),
        points3d=int(number("points3D")),
        mean_track_length=number("mean_track_length"),
        mean_reprojection_error=number("mean_reprojection_error"),
        full=struct(summary),
    )


def pair_matches(m: PairMatchView) -> pb2.MatchPairResponse:
    return pb2.MatchPairResponse(
        keypoints0=m.keypoints0.reshape(-1).tolist(),
        keypoints1=m.keypoints1.reshape(-1).tolist(),
        scores=m.scores.reshape(-1).tolist(),
        fundamental=m.F.reshape(-1).tolist(),
        size0=pb2.ImageSize(width=m.sizes[0][0], height=m.sizes[0][1]),
        size1=pb2.ImageSize(width=m.sizes[1][0], height=m.sizes[1][1]),
        method=m.method,
        tiled=m.tiled,
        timings=m.timings,
    )


def _floats(value: Any) -> list[float]:
    return [float(x) for x in value] if isinstance(value, list | tuple) else []


def localization(a: Mapping[str, Any]) -> pb2.Localization:
    """One answer of a localize job's result (the library's ``Localization.to_json``)."""
    msg = pb2.Localization(
        name=str(a.get("name", "")),
        localized=bool(a.get("localized")),
        reason=str(a.get("reason") or ""),
        center=_floats(a.get("center")),
        inliers=int(a.get("inliers") or 0),
        matches=int(a.get("matches") or 0),
        confidence=str(a.get("confidence") or "none"),
        supporting_images=[str(n) for n in a.get("supporting_images") or []],
        seconds=float(a.get("seconds") or 0.0),
        candidates=[str(n) for n in a.get("candidates") or []],
        inlier_ratio=float(a.get("inlier_ratio") or 0.0),
        focal_source=str(a.get("focal_source") or ""),
    )
    pose = a.get("cam_from_world")
    if isinstance(pose, Mapping):
        msg.cam_from_world.CopyFrom(pb2.Pose(qvec=_floats(pose.get("qvec")), tvec=_floats(pose.get("tvec"))))
    geo = a.get("wgs84")
    if isinstance(geo, Mapping):
        msg.wgs84.CopyFrom(
            pb2.GeoPosition(lat=float(geo["lat"]), lon=float(geo["lon"]), alt=float(geo.get("alt") or 0.0))
        )
        if geo.get("heading_deg") is not None:
            msg.wgs84.heading_deg = float(geo["heading_deg"])
    if a.get("reprojection_error_px") is not None:
        msg.reprojection_error_px = float(a["reprojection_error_px"])
    camera = a.get("camera")
    if isinstance(camera, Mapping):
        msg.camera.CopyFrom(
            pb2.CameraIntrinsics(
                model=str(camera.get("model", "")),
                width=int(camera.get("width") or 0),
                height=int(camera.get("height") or 0),
                params=_floats(camera.get("params")),
            )
        )
    return msg
