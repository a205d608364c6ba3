"""The JSON shapes of the REST API (pydantic): what OpenAPI at /docs shows.

Values are checked once more by the use cases (the gRPC server shares those checks); here the
models only fix the shape and reject unknown fields, so a typo is a 422 rather than ignored.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, create_model

from geomatch import options


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


def _option_fields(pairs_list: bool) -> dict[str, Any]:
    """One optional field per project option of ``geomatch.options`` (None: the default)."""
    fields: dict[str, Any] = {}
    for name in options.PROJECT_OPTIONS:
        o = options.OPTIONS[name]
        kind: Any = o.type
        examples: list[Any] = [o.default]
        if name == "pairs" and pairs_list:
            kind = str | list[list[str]]
            examples = [o.default, [["a.jpg", "b.jpg"]]]
        description = o.help
        if o.choices:
            description = f"{' | '.join(o.choices)}: {o.help}"
        description += f" (default {o.default})"
        fields[name] = (kind | None, Field(None, examples=examples, description=description))
    return fields


ProjectConfig = create_model("ProjectConfig", __base__=_Strict, **_option_fields(pairs_list=False))


class ProjectCreate(_Strict):
    name: str = Field(..., examples=["campus"])
    config: ProjectConfig | None = None


class ProjectOut(BaseModel):
    id: str
    name: str
    config: dict[str, Any]
    created_at: datetime
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


MatchIn = create_model(
    "MatchIn",
    __base__=_Strict,
    **_option_fields(pairs_list=True),
    reconstruct=(
        bool,
        Field(False, description="also queue a reconstruct job that starts when matching succeeds"),
    ),
)


class ReconstructIn(_Strict):
    mapper: str | None = Field(
        None, examples=[options.DEFAULTS["mapper"]], description=" | ".join(options.MAPPERS)
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
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


class JobAccepted(BaseModel):
    job_id: str
    reconstruct_job_id: str | None = None


class Error(BaseModel):
    detail: str
