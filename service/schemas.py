"""The JSON shapes of the REST API (pydantic): what OpenAPI at /docs shows.

Values are checked once more by the use cases (the gRPC server shares those checks); here the
models only fix the shape and reject unknown fields, so a typo is a 422 rather than ignored.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, ConfigDict, Field


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ProjectConfig(_Strict):
    pairs: str | None = Field(
        None, examples=["exhaustive"], description="exhaustive | sequential:K | retrieval:K"
    )
    method: str | None = Field(
        None, examples=["geo"], description="sparse | dense | concat | geo-noanchor | geo"
    )
    resize: int | None = Field(
        None, examples=[640], description="longer side fed to the networks; 0 = full size"
    )
    tiling: str | None = Field(None, description="auto | on | off (auto: aerial x ground pairs)")
    snap_radius: float | None = Field(None, description="keypoint consolidation radius, network pixels")
    camera: str | None = Field(None, description="auto (one camera per EXIF device) | per-image")
    mapper: str | None = Field(None, description="incremental | global")


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


class MatchIn(_Strict):
    pairs: str | list[list[str]] | None = Field(
        None, examples=["exhaustive", [["a.jpg", "b.jpg"]]], description="a spec or explicit name pairs"
    )
    method: str | None = Field(None, examples=["geo"])
    resize: int | None = Field(None, examples=[640])
    tiling: str | None = None
    snap_radius: float | None = None
    camera: str | None = None
    reconstruct: bool = Field(
        False, description="also queue a reconstruct job that starts when matching succeeds"
    )
    mapper: str | None = Field(None, description="mapper of that reconstruct job")


class ReconstructIn(_Strict):
    mapper: str | None = Field(None, examples=["incremental"], description="incremental | global")


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
