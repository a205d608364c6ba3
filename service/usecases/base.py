"""What every use case shares: the service's parts, the tenant's project, the option checks and
the staging of an uploaded file (uploads and the two-image match pass the same checks)."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from geomatch.options import PROJECT_OPTIONS, defaults
from geomatch_core.config import Settings
from geomatch_core.errors import Conflict, InvalidRequest, JobsOpen, NotFound, TooLarge
from geomatch_core.locks import LockFactory
from geomatch_core.models import Job, Project
from geomatch_core.queue import JobQueue
from geomatch_core.storage import Storage
from geomatch_core.store import MetadataStore

from ..ids import known_id
from ..ratelimit import RateLimiter
from ..slots import FairSlots
from ..validation import ImageInfo, check_image, check_option

# a project's configuration and a match job's options: geomatch.options holds them, with defaults
DEFAULTS: dict[str, Any] = defaults(PROJECT_OPTIONS)
_CHUNK = 1 << 20


@dataclass
class Staged:
    """An uploaded file written to a temporary file and checked, not yet in the project."""

    name: str
    path: Path
    sha256: str
    size: int
    info: ImageInfo
    capture: str | None = None


def check_config(config: dict[str, Any]) -> dict[str, Any]:
    """Validated project config / match options; raises InvalidRequest naming the bad key."""
    unknown = sorted(set(config) - set(DEFAULTS))
    if unknown:
        raise InvalidRequest(f"unknown option(s) {', '.join(unknown)}; known: {', '.join(DEFAULTS)}")
    out: dict[str, Any] = {}
    for k, v in config.items():
        if v is None:
            continue
        out[k] = v if k == "pairs" and isinstance(v, list) else check_option(k, v)
    return out


def choice(key: str, value: Any, allowed: Sequence[str]) -> str:
    if value not in allowed:
        raise InvalidRequest(f"{key} must be one of {', '.join(allowed)}, not {value!r}")
    return str(value)


class Context:
    """The parts that every use case of one ``Service`` shares: one store, storage, queue, set of
    locks and settings, and the limits that hold across concerns (a tenant's request rate, the
    heavy calls in flight), so that each concern's object sees the same ones."""

    def __init__(
        self,
        settings: Settings,
        store: MetadataStore,
        storage: Storage,
        queue: JobQueue,
        locks: LockFactory,
    ) -> None:
        self.settings = settings
        self.store = store
        self.storage = storage
        self.queue = queue
        self.locks = locks
        self.on_upload: Callable[[int, int], object] | None = None  # (new images, bytes): metrics
        self.rate = RateLimiter(settings.rate_per_s, settings.rate_burst)
        # the work the API does itself, in the caller's thread (pictures it waits for, exports,
        # snapshots): bounded, so that one tenant's calls cannot hold every thread of the server
        self.heavy = FairSlots("heavy calls", settings.heavy_slots, settings.heavy_tenant_slots)


OPEN = ("queued", "running")
HEAVY_JOBS = ("localize", "reconstruct")  # minutes of a worker each: GEOMATCH_MAX_OPEN_JOBS counts them


def staged_bytes(s: Session, tenant_id: str) -> int:
    """Bytes of the photos the tenant's unfinished localize jobs hold staged (not added to a
    project): they are on the server's disk as long as the job runs, and count against the stored
    bytes quota as images do. Read off the jobs' options (bounded by GEOMATCH_MAX_OPEN_JOBS)."""
    rows = s.scalars(
        select(Job.options).where(Job.tenant_id == tenant_id, Job.kind == "localize", Job.state.in_(OPEN))
    )
    return sum(int(o.get("staged_bytes") or 0) for o in rows if isinstance(o, dict))


def check_open_jobs(s: Session, settings: Settings, tenant_id: str, adding: int = 1) -> None:
    """JobsOpen (429, Retry-After) when ``adding`` more localize or reconstruct jobs would take the
    tenant past ``Settings.max_open_jobs`` unfinished ones: 15 localize requests of one tenant had
    another tenant's match wait 10-17 s behind them."""
    limit = settings.max_open_jobs
    if not limit:
        return
    rows = s.scalars(
        select(Job.id).where(Job.tenant_id == tenant_id, Job.kind.in_(HEAVY_JOBS), Job.state.in_(OPEN))
    ).all()
    if len(rows) + adding > limit:
        raise JobsOpen(
            f"this key's tenant has {len(rows)} unfinished localize and reconstruct jobs, and may have "
            f"{limit} at once (GEOMATCH_MAX_OPEN_JOBS): retry when one has ended, or cancel one",
            retry_after_s=10,
        )


class UseCases:
    """One concern's use cases over the shared :class:`Context`, with the lookups and the staging
    that every concern needs."""

    def __init__(self, ctx: Context) -> None:
        self.ctx = ctx

    def _project(self, s: Session, tenant_id: str, project_id: str) -> Project:
        """The tenant's project: every use case that takes a project id looks it up here."""
        p = s.get(Project, known_id("project", project_id))
        if p is None or p.tenant_id != tenant_id:
            raise NotFound(f"project {project_id} not found")
        return p

    def _owned(self, tenant_id: str, project_id: str) -> None:
        """NotFound unless the tenant has this project."""
        with self.ctx.store.session() as s:
            self._project(s, tenant_id, project_id)

    @contextmanager
    def _unless_deleted(self, tenant_id: str, project_id: str) -> Iterator[None]:
        """A write to a project that a concurrent delete removes under it: NotFound.

        The project is checked when the write starts, but nothing holds it until the write commits
        (SQLite has no row locks, and a lock on PostgreSQL's row would make every delete wait for
        uploads), so the delete may win in between. The write then trips on what the delete took
        away: the foreign key of the row it inserts (IntegrityError), the images it counted (none
        left: InvalidRequest), the succeeded match it needs (Conflict) or the folder it moves files
        into (OSError). If the project is gone by then, that is the answer; otherwise the error was
        the write's own and goes out as it is."""
        try:
            yield
        except (IntegrityError, InvalidRequest, Conflict, OSError):
            self._owned(tenant_id, project_id)
            raise

    def _stage(self, name: str, stream: BinaryIO) -> Staged:
        fd, tmp = self.ctx.storage.temp_file()
        h, size = hashlib.sha256(), 0
        try:
            with os.fdopen(fd, "wb") as f:
                while chunk := stream.read(_CHUNK):
                    size += len(chunk)
                    if size > self.ctx.settings.max_upload_bytes:
                        raise TooLarge(
                            f"{name}: larger than the upload limit of "
                            f"{self.ctx.settings.max_upload_bytes // (1024 * 1024)} MiB"
                        )
                    h.update(chunk)
                    self.ctx.storage.check_space(len(chunk))
                    f.write(chunk)
            info = check_image(tmp, name, self.ctx.settings.max_pixels)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return Staged(name, tmp, h.hexdigest(), size, info)
