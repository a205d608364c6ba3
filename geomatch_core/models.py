"""Metadata tables: tenants, API keys, projects, images, jobs, the pairs of match jobs and the
photos their plans extract ahead.

Files (images, COLMAP databases, models) are not here but under the storage root; rows point to
them by project id and image name. ``JobPair`` rows make match progress exact under redelivery:
a pair counts once, when its row flips to done, whichever worker and however often it ran.
"""

from __future__ import annotations

import uuid
from datetime import UTC, datetime
from typing import Any, ClassVar

from sqlalchemy import (
    JSON,
    Boolean,
    DateTime,
    ForeignKey,
    Integer,
    String,
    Text,
    UniqueConstraint,
    false,
    text,
)
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column
from sqlalchemy.types import TypeDecorator

JOB_STATES = ("queued", "running", "succeeded", "failed", "cancelled")
TERMINAL_STATES = ("succeeded", "failed", "cancelled")


def new_id() -> str:
    return uuid.uuid4().hex


def now() -> datetime:
    return datetime.now(UTC)


def as_utc(t: datetime) -> datetime:
    """A naive value is UTC: every value is written by ``now()``, and SQLite drops the zone."""
    return t.replace(tzinfo=UTC) if t.tzinfo is None else t.astimezone(UTC)


class UTCDateTime(TypeDecorator[datetime]):
    """Timestamps are aware UTC in and out, whichever store keeps them: SQLite keeps no zone and
    hands back naive values, PostgreSQL hands them back in the session's time zone. Without this a
    row read back (GET) did not look like the row just written (POST)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        return None if value is None else as_utc(value)

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        return None if value is None else as_utc(value)


class Base(DeclarativeBase):
    type_annotation_map: ClassVar[dict[Any, Any]] = {dict[str, Any]: JSON, datetime: UTCDateTime()}


class Tenant(Base):
    __tablename__ = "tenants"
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    name: Mapped[str] = mapped_column(String(200), unique=True)
    created_at: Mapped[datetime] = mapped_column(default=now)


class ApiKey(Base):
    __tablename__ = "api_keys"
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    tenant_id: Mapped[str] = mapped_column(ForeignKey("tenants.id", ondelete="CASCADE"), index=True)
    prefix: Mapped[str] = mapped_column(String(16))  # shown in listings to tell keys apart
    digest: Mapped[str] = mapped_column(String(64), unique=True)  # sha256 of the key
    created_at: Mapped[datetime] = mapped_column(default=now)
    revoked_at: Mapped[datetime | None] = mapped_column(default=None)


class Project(Base):
    __tablename__ = "projects"
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    tenant_id: Mapped[str] = mapped_column(ForeignKey("tenants.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(200))
    config: Mapped[dict[str, Any]] = mapped_column(default=dict)
    created_at: Mapped[datetime] = mapped_column(default=now)


class Image(Base):
    __tablename__ = "images"
    __table_args__ = (
        UniqueConstraint("project_id", "name", name="uq_image_name"),
        UniqueConstraint("project_id", "sha256", name="uq_image_sha256"),
    )
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    project_id: Mapped[str] = mapped_column(ForeignKey("projects.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(255))
    sha256: Mapped[str] = mapped_column(String(64))
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    size_bytes: Mapped[int] = mapped_column(Integer)
    format: Mapped[str] = mapped_column(String(16))
    capture: Mapped[str] = mapped_column(String(8))  # aerial | ground | auto, as uploaded
    aerial: Mapped[bool | None] = mapped_column(Boolean, default=None)  # resolved by a match job
    created_at: Mapped[datetime] = mapped_column(default=now)


class Job(Base):
    __tablename__ = "jobs"
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    project_id: Mapped[str] = mapped_column(ForeignKey("projects.id", ondelete="CASCADE"), index=True)
    tenant_id: Mapped[str] = mapped_column(String(32), index=True)
    kind: Mapped[str] = mapped_column(String(16))  # match | reconstruct | localize
    state: Mapped[str] = mapped_column(String(16), default="queued", index=True)
    options: Mapped[dict[str, Any]] = mapped_column(default=dict)
    planned: Mapped[bool] = mapped_column(Boolean, default=False)
    done: Mapped[int] = mapped_column(Integer, default=0)
    total: Mapped[int] = mapped_column(Integer, default=0)
    # a match job's pairs handed to the queue so far (idx < dispatched): a window over its pairs
    # (workers.jobs), so another job's steps never queue behind all of a long job's
    dispatched: Mapped[int] = mapped_column(Integer, default=0, server_default=text("0"))
    error: Mapped[str | None] = mapped_column(Text, default=None)
    result: Mapped[dict[str, Any] | None] = mapped_column(default=None)
    after_job_id: Mapped[str | None] = mapped_column(String(32), default=None, index=True)
    created_at: Mapped[datetime] = mapped_column(default=now)
    started_at: Mapped[datetime | None] = mapped_column(default=None)
    finished_at: Mapped[datetime | None] = mapped_column(default=None)


class JobPair(Base):
    __tablename__ = "job_pairs"
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), primary_key=True)
    idx: Mapped[int] = mapped_column(Integer, primary_key=True)
    name0: Mapped[str] = mapped_column(String(255))
    name1: Mapped[str] = mapped_column(String(255))
    tiled: Mapped[bool] = mapped_column(Boolean, default=False)
    aerial_first: Mapped[bool] = mapped_column(Boolean, default=True)
    # a side is aerial: matched at its best quarter turn (geomatch.matching.rotation); decided by
    # the plan, with the pair (migrate.py fills it in for rows planned before it was stored)
    rotate: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    # a survey's pair: each image's quarter turn into the project's frame (pipeline.turns); -1 where
    # the pair probes its own turn. Decided by the plan, with the pair
    turn0: Mapped[int] = mapped_column(Integer, default=-1, server_default=text("-1"))
    turn1: Mapped[int] = mapped_column(Integer, default=-1, server_default=text("-1"))
    # what the pair's matcher depends on besides the pair (pipeline.pair_sources.Pair): the project
    # has aerial images; every image of it is aerial. Decided by the plan, with the pair
    aerial_project: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    survey: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    done: Mapped[bool] = mapped_column(Boolean, default=False)
    matches: Mapped[int | None] = mapped_column(Integer, default=None)
    inliers: Mapped[int | None] = mapped_column(Integer, default=None)


class JobPhoto(Base):
    """A photo whose plan features a match job extracts before planning, in steps spread over the
    workers (``workers.photosteps``): which step (``chunk``) and what it extracts. The rows make
    the count of photos left exact under redelivery, as ``JobPair`` rows do for pairs."""

    __tablename__ = "job_photos"
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), primary_key=True)
    name: Mapped[str] = mapped_column(String(255), primary_key=True)
    chunk: Mapped[int] = mapped_column(Integer)
    # the quarter turn a survey's plan will likely score the photo at first (pipeline.turns); -1: none
    turn: Mapped[int] = mapped_column(Integer, default=-1)
    sparse: Mapped[bool] = mapped_column(Boolean, default=False)  # retrieval's upright features
    done: Mapped[bool] = mapped_column(Boolean, default=False)
