"""The JSON shapes of the REST API (pydantic): what OpenAPI at /docs shows.

Values are checked once more by the use cases (the gRPC server shares those checks); here the
models fix the shape, the JSON types and, in the schema, each value's choices, range or pattern, so
that what OpenAPI calls valid is what the server takes. Unknown fields are refused (a typo is a 422
rather than ignored) and nothing is coerced (``"640"`` is not a size, ``true`` is not a radius,
``"yes"`` is not a boolean). A JSON integer still passes where a number is asked, and a number
with no fraction (``640.0``) where an integer is, as JSON Schema defines them.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Annotated, Any

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    PlainSerializer,
    WithJsonSchema,
    create_model,
)

from geomatch import options

from .. import validation
from ..usecases.gcp import MAX_CHECKPOINT_NAME, MAX_CHECKPOINTS


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)


def _utc(t: datetime) -> str:
    t = t.replace(tzinfo=UTC) if t.tzinfo is None else t.astimezone(UTC)
    return t.isoformat(timespec="microseconds").replace("+00:00", "Z")


# Every timestamp out of the API: UTC, "Z", always six decimals, whichever store the row came from
# and whether it was just written (POST) or read back (GET).
Timestamp = Annotated[
    datetime,
    PlainSerializer(_utc, return_type=str, when_used="json"),
    WithJsonSchema({"type": "string", "format": "date-time", "examples": ["2025-01-31T12:00:00.000000Z"]}),
]


# What options.parse_plan takes, as a pattern built from options.PAIR_KINDS (ASCII digits and
# white space: the JSON Schema dialect's \\d and \\s are narrower than Python's, and the schema must
# not promise what the server refuses); a union may name a kind twice (parse_plan: the larger K)
_WS = r"[ \t\n\r]*"


def pair_spec_pattern(kinds: Sequence[options.PairKind]) -> str:
    alone = "|".join(k.name for k in kinds if not k.takes_k)
    part = _WS + "(?:" + "|".join(k.name for k in kinds if k.takes_k) + r"):0*[1-9][0-9]*" + _WS
    return rf"^(?:{_WS}(?:{alone}){_WS}|{part}(?:\+{part})*)$"


PAIR_SPEC_PATTERN = pair_spec_pattern(options.PAIR_KINDS)


def _option_schema(o: options.Option) -> dict[str, Any]:
    """The option's choices or range in JSON Schema, from ``geomatch.options``."""
    if o.choices:
        return {"type": "string", "enum": list(o.choices)}
    if o.name == "pairs":
        return {"type": "string", "pattern": PAIR_SPEC_PATTERN}
    kind = {int: "integer", float: "number", str: "string"}[o.type]
    span = {k: v for k, v in (("minimum", o.low), ("maximum", o.high)) if v is not None}
    if o.type is int:
        span = {k: int(v) for k, v in span.items()}
    if o.zero and span:  # 0 means something ("full size") below the range
        return {"type": kind, "anyOf": [{"const": 0}, span]}
    return {"type": kind, **span}


def _checked(name: str) -> Any:
    """options.check as a validator: the value the use case would store, or a ValueError whose
    message names the option as the use cases' do (pydantic shows it in the 422). A list of pairs
    passes: the use case checks its names against the project's images."""

    def check(value: Any) -> Any:
        if isinstance(value, list):
            return value
        if name == "pairs" and not re.fullmatch(PAIR_SPEC_PATTERN, value):
            raise ValueError(f"bad pairs {value!r}: use {options.PAIR_SPEC_WORDS} (K >= 1) or a union")
        return options.check(name, value)

    return AfterValidator(check)


# a match job's explicit pairs: two different names of the project's images each
PAIR_LIST_SCHEMA = {
    "type": "array",
    "minItems": 1,
    "items": {
        "type": "array",
        "items": {"type": "string"},
        "minItems": 2,
        "maxItems": 2,
        "uniqueItems": True,
    },
}


def _integral(value: Any) -> Any:
    """640.0 is an integer to JSON Schema (a number whose fraction is zero), so it is one here."""
    return int(value) if isinstance(value, float) and value.is_integer() else value


def option_type(name: str, pairs_list: bool = False) -> Any:
    o = options.OPTIONS[name]
    if name == "pairs" and pairs_list:
        schema = {"anyOf": [_option_schema(o), PAIR_LIST_SCHEMA]}
        return Annotated[str | list[list[str]], _checked(name), WithJsonSchema(schema)]
    if o.type is int:
        return Annotated[int, BeforeValidator(_integral), _checked(name), WithJsonSchema(_option_schema(o))]
    return Annotated[o.type, _checked(name), WithJsonSchema(_option_schema(o))]


def _option_fields(pairs_list: bool) -> dict[str, Any]:
    """One optional field per project option of ``geomatch.options`` (None: the default)."""
    fields: dict[str, Any] = {}
    for name in options.PROJECT_OPTIONS:
        o = options.OPTIONS[name]
        kind: Any = option_type(name, pairs_list)
        examples: list[Any] = [o.default]
        if name == "pairs" and pairs_list:
            examples = [o.default, [["a.jpg", "b.jpg"]]]
        description = o.help
        if o.choices:
            description = f"{' | '.join(o.choices)}: {o.help}"
        description += f" (default {o.default})"
        fields[name] = (kind | None, Field(None, examples=examples, description=description))
    return fields


if TYPE_CHECKING:  # models made at run time, field by field from the options: to a checker, strict models

    class ProjectConfig(_Strict): ...

    class MatchIn(_Strict): ...

else:
    ProjectConfig = create_model("ProjectConfig", __base__=_Strict, **_option_fields(pairs_list=False))


class ProjectCreate(_Strict):
    name: Annotated[
        str,
        WithJsonSchema(
            {
                "type": "string",
                "minLength": 1,
                "maxLength": validation.MAX_PROJECT_NAME,
                "pattern": validation.PROJECT_NAME_PATTERN,
            }
        ),
    ] = Field(
        ...,
        examples=["campus"],
        description="stripped of white space at both ends; no control characters",
    )
    config: ProjectConfig | None = None


class ProjectOut(BaseModel):
    id: str
    name: str
    config: dict[str, Any]
    created_at: Timestamp
    images: int
    has_model: bool


class ImageOut(BaseModel):
    id: str
    name: str
    width: int
    height: int
    capture: str = Field(description="aerial | ground | auto, as uploaded")
    sha256: str
    size_bytes: int
    format: str
    aerial: bool | None = Field(description="resolved by the first match job (EXIF/XMP for auto)")
    created: bool = Field(description="false when the same bytes were already in the project")


class ImagesOut(BaseModel):
    images: list[ImageOut]


if not TYPE_CHECKING:
    MatchIn = create_model(
        "MatchIn",
        __base__=_Strict,
        **_option_fields(pairs_list=True),
        reconstruct=(
            bool,
            Field(False, description="also queue a reconstruct job that starts when matching succeeds"),
        ),
    )


CheckpointCount = Annotated[int, Field(ge=0, le=MAX_CHECKPOINTS), BeforeValidator(_integral)]


def _unique(names: list[str]) -> list[str]:
    if len(set(names)) != len(names):
        raise ValueError("a check point is named twice")
    return names


CheckpointNames = Annotated[
    list[Annotated[str, Field(min_length=1, max_length=MAX_CHECKPOINT_NAME)]],
    Field(min_length=1, max_length=MAX_CHECKPOINTS, json_schema_extra={"uniqueItems": True}),
    AfterValidator(_unique),
]


class ReconstructIn(_Strict):
    # a type built at run time from the options (choices, checks, schema), which pydantic reads
    mapper: option_type("mapper") | None = Field(  # type: ignore[valid-type]
        None, examples=[options.DEFAULTS["mapper"]], description=" | ".join(options.MAPPERS)
    )
    min_pose_inliers: option_type("min_pose_inliers") | None = Field(  # type: ignore[valid-type]
        None, examples=[60], description=options.OPTIONS["min_pose_inliers"].help
    )
    ortho: option_type("ortho") | None = Field(  # type: ignore[valid-type]
        None, examples=["on"], description=" | ".join(options.ORTHO) + ": " + options.OPTIONS["ortho"].help
    )
    ortho_gsd: option_type("ortho_gsd") | None = Field(  # type: ignore[valid-type]
        None, examples=[0.05], description=options.OPTIONS["ortho_gsd"].help
    )
    checkpoints: CheckpointCount | CheckpointNames | None = Field(
        None,
        examples=[2, ["gcp03", "gcp07"]],
        description="ground control points held out of the fit and judged after it (the summary's "
        "`gcp`: residuals and check-point RMSE): their names in the project's GCP file, or how many, "
        "spread over the points' sorted names; needs a GCP file (PUT .../gcp). 0: none",
    )


class GcpOut(BaseModel):
    """A project's GCP file (OpenDroneMap's gcp_list.txt) as read against its images."""

    crs: str = Field(description="the file's coordinate system, as PROJ writes it")
    frame: str | None = Field(
        description="the metric frame the points are fitted in: the file's own when it is projected, "
        "else the UTM zone of its points; null with `error`"
    )
    points: list[str] = Field(description="the usable points: each seen in two or more of the images")
    unusable: dict[str, str] = Field(description="point name -> why it cannot be used")
    problems: list[str] = Field(description="one line per problem found, naming its line or point")
    size_bytes: int = Field(description="of the stored file")
    error: str | None = Field(
        None,
        description="GET: why the stored file no longer fits the project's images (a reconstruct "
        "then leaves the model in its own frame)",
    )


class Progress(BaseModel):
    done: int
    total: int


class JobOut(BaseModel):
    id: str
    project_id: str
    kind: str
    state: str = Field(description="queued | running | succeeded | failed | cancelled")
    progress: Progress
    error: str | None
    options: dict[str, Any]
    result: dict[str, Any] | None
    after_job_id: str | None = Field(description="the job this one waits for")
    created_at: Timestamp
    started_at: Timestamp | None
    finished_at: Timestamp | None


class JobsOut(BaseModel):
    jobs: list[JobOut] = Field(description="newest first")


class JobAccepted(BaseModel):
    job_id: str
    reconstruct_job_id: str | None = None


class Error(BaseModel):
    detail: str


class PairOut(BaseModel):
    name0: str
    name1: str
    matches: int = Field(description="matches the matcher wrote")
    inliers: int = Field(description="matches verified by the pair's two-view geometry")


class PairsOut(BaseModel):
    pairs: list[PairOut]


class SceneCamera(BaseModel):
    name: str
    center: list[float] = Field(description="camera centre in model coordinates")
    rotation: list[list[float]] = Field(description="world-to-camera rotation, 3 rows")
    width: float
    height: float
    focal: float = Field(description="focal length in pixels")
    cx: float
    cy: float


class SceneOut(BaseModel):
    points: int = Field(description="number of 3D points")
    xyz: list[float] = Field(description="x, y, z of each point, flat")
    rgb: list[int] = Field(description="r, g, b (0-255) of each point, flat")
    cameras: list[SceneCamera] = Field(description="the registered images")


# -- localize ----------------------------------------------------------------------------------
class Pose(BaseModel):
    qvec: list[float] = Field(description="rotation world to camera as a unit quaternion w, x, y, z")
    tvec: list[float] = Field(description="translation world to camera, model units")


class Wgs84(BaseModel):
    lat: float = Field(description="degrees north")
    lon: float = Field(description="degrees east")
    alt: float = Field(description="metres, the model's height reference")
    heading_deg: float | None = Field(None, description="the view direction, degrees clockwise from north")


class LocalizedCamera(BaseModel):
    model: str = Field(description="COLMAP camera model, e.g. SIMPLE_RADIAL")
    width: int
    height: int
    params: list[float] = Field(description="COLMAP's parameters of that model, pixels")


class LocalizationOut(BaseModel):
    """One photo's answer. ``localized`` false: no pose (``reason`` says why); the pose fields are
    then null, never a guess."""

    name: str
    localized: bool
    reason: str | None = Field(None, description="why not localized, or what lowered the confidence")
    cam_from_world: Pose | None = None
    center: list[float] | None = Field(None, description="camera centre in the model's frame")
    wgs84: Wgs84 | None = Field(None, description="when the model is georeferenced")
    inliers: int = Field(0, description="2D-3D correspondences the pose explains")
    matches: int = Field(0, description="2D-3D correspondences tried")
    reprojection_error_px: float | None = None
    confidence: str = Field("none", description="high | low | none")
    supporting_images: list[str] = Field(default_factory=list, description="model images it matched")
    camera: LocalizedCamera | None = None
    seconds: float | None = Field(None, description="time spent on this photo")
    candidates: list[str] = Field(default_factory=list, description="model images it was matched with")
    inlier_ratio: float | None = Field(None, description="inliers over the correspondences tried")
    focal_source: str | None = Field(None, description="model | exif | estimated: where its focal came from")


class LocalizeOut(BaseModel):
    job_id: str = Field(description="GET /v1/jobs/{job_id} reads it (its result holds the answers)")
    state: str = Field(description="queued | running | succeeded | failed | cancelled")
    progress: Progress = Field(description="photos done of those sent")
    error: str | None = None
    localizations: list[LocalizationOut] | None = Field(
        None, description="one per photo, in the order sent, once the job succeeded (200); null with 202"
    )
