"""The application layer: every operation the API offers, free of any transport.

Routers (REST and gRPC) translate requests into these calls and the typed errors
of ``geomatch_core.errors`` into statuses. A use case validates everything before it stores or
enqueues anything, so a rejected request leaves no trace.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import shutil
import time
import uuid
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from sqlalchemy import delete, func, select
from sqlalchemy.exc import IntegrityError, OperationalError
from sqlalchemy.orm import Session

from geomatch.export.formats import DATABASE, FORMATS, ExportFormat
from geomatch.options import CAPTURES, PROJECT_OPTIONS, defaults
from geomatch.options import PAIR_OPTIONS as PAIR_OPTIONS  # what match_two accepts of DEFAULTS
from geomatch.sfm.sqlitecopy import snapshot_sqlite
from geomatch_core import jobstate
from geomatch_core.config import Settings
from geomatch_core.errors import (
    BadFile,
    Conflict,
    InsufficientStorage,
    InvalidRequest,
    NotFound,
    TooLarge,
    Unavailable,
)
from geomatch_core.locks import LockFactory
from geomatch_core.models import TERMINAL_STATES, Image, Job, Project
from geomatch_core.queue import ENTRY_STEP, MATCH_TWO, RENDER_PAIR, JobQueue
from geomatch_core.storage import Storage
from geomatch_core.store import MetadataStore

from . import auth
from .modelscene import read_scene
from .pairlist import PairView, read_pairs
from .validation import (
    ImageInfo,
    check_image,
    check_name,
    check_option,
    check_pair_list,
    check_project_name,
)

# a project's configuration and a match job's options: geomatch.options holds them, with defaults
DEFAULTS: dict[str, Any] = defaults(PROJECT_OPTIONS)


@dataclass(frozen=True)
class ModelFile:
    """A format served as a file of the model folder, as the pipeline or the job wrote it."""

    name: str
    file: str
    media_type: str
    help: str


def model_files() -> list[ModelFile]:
    """The archive, the export formats whose file the pipeline writes already (ply), the summary."""
    rows = [f for f in FORMATS.values() if f.model_file is not None]
    return [
        ModelFile("zip", "model.zip", "application/zip", "COLMAP binary + text"),
        *(ModelFile(f.name, f.model_file or "", f.media_type, f.help) for f in rows),
        ModelFile("json", "summary.json", "application/json", "summary"),
    ]


def export_formats() -> list[ExportFormat]:
    """The formats built from the model on first request and kept beside it as zips."""
    return [f for f in FORMATS.values() if f.model_file is None]


def model_formats() -> tuple[str, ...]:
    """Every format ``model_file`` answers (read at each call: the export table may grow)."""
    return (*(m.name for m in model_files()), *(f.name for f in export_formats()))


# how a stored image is served back (the validated format, never the client's claim)
IMAGE_MEDIA = {
    "jpeg": "image/jpeg",
    "png": "image/png",
    "tiff": "image/tiff",
    "bmp": "image/bmp",
    "webp": "image/webp",
}
_CHUNK = 1 << 20
_FULL = (
    "the storage is full (no space left on device): nothing of this upload was kept; "
    "retry when space is freed"
)


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
class MatchRequest:
    pairs: str | list[list[str]] | None = None
    method: str | None = None
    resize: int | None = None
    tiling: str | None = None
    snap_radius: float | None = None
    camera: str | None = None
    reconstruct: bool = False  # queue a reconstruct job that starts when matching succeeds
    mapper: str | None = None


@dataclass(frozen=True)
class PairMatches:
    """Matches of two images in their original pixels, as ``geomatch.matching.matcher.MatchResult``."""

    keypoints0: np.ndarray  # (N, 2) float32
    keypoints1: np.ndarray  # (N, 2) float32
    scores: np.ndarray  # (N,) float32
    F: np.ndarray  # (3, 3), x1^T F x0 = 0; zeros when it could not be fitted
    sizes: tuple[tuple[int, int], tuple[int, int]]  # (width, height) of each image
    method: str
    tiled: bool
    timings: dict[str, float]


@dataclass
class _Staged:
    name: str
    path: Path
    sha256: str
    size: int
    info: ImageInfo
    capture: str | None = None


@dataclass
class Readiness:
    ok: bool
    checks: dict[str, str] = field(default_factory=dict)


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


def _choice(key: str, value: Any, allowed: Sequence[str]) -> str:
    if value not in allowed:
        raise InvalidRequest(f"{key} must be one of {', '.join(allowed)}, not {value!r}")
    return str(value)


class Service:
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

    def authenticate(self, key: str | None) -> str:
        """The tenant id of an API key (Unauthenticated otherwise)."""
        return auth.authenticate(self.store, key)

    # -- projects --------------------------------------------------------------------------
    def create_project(self, tenant_id: str, name: str, config: dict[str, Any] | None = None) -> ProjectView:
        name = check_project_name(name)
        cfg = check_config(config or {})
        if isinstance(cfg.get("pairs"), list):
            raise InvalidRequest(
                "a project's default pairs is a spec (exhaustive, sequential:K, retrieval:K)"
            )
        with self.store.session() as s:
            p = Project(tenant_id=tenant_id, name=name, config=cfg)
            s.add(p)
            s.flush()
            return self._project_view(s, p)

    def list_projects(self, tenant_id: str) -> list[ProjectView]:
        with self.store.session() as s:
            rows = s.scalars(
                select(Project).where(Project.tenant_id == tenant_id).order_by(Project.created_at)
            ).all()
            return [self._project_view(s, p) for p in rows]

    def get_project(self, tenant_id: str, project_id: str) -> ProjectView:
        with self.store.session() as s:
            return self._project_view(s, self._project(s, tenant_id, project_id))

    def delete_project(self, tenant_id: str, project_id: str) -> None:
        """Of concurrent deletes of one project exactly one succeeds, the others find it gone: the
        row is deleted by one statement whose row count says who did it."""
        with self.store.session() as s:
            p = self._project(s, tenant_id, project_id)
            jobs = s.scalars(select(Job.id).where(Job.project_id == p.id)).all()
        for job_id in jobs:  # workers see their job gone or cancelled and stop
            jobstate.cancel(self.store, job_id, "project deleted")
        with self.store.session() as s:
            gone = s.execute(delete(Project).where(Project.id == project_id, Project.tenant_id == tenant_id))
            if gone.rowcount != 1:  # type: ignore[attr-defined]
                raise NotFound(f"project {project_id} not found")
        # the writer lock: a worker writing this project right now finishes before the files go
        with self.locks.project(project_id):
            self.storage.delete_project(project_id)

    def _project(self, s: Session, tenant_id: str, project_id: str) -> Project:
        p = s.get(Project, project_id)
        if p is None or p.tenant_id != tenant_id:
            raise NotFound(f"project {project_id} not found")
        return p

    def _project_view(self, s: Session, p: Project) -> ProjectView:
        n = s.scalar(select(func.count()).select_from(Image).where(Image.project_id == p.id)) or 0
        has_model = (self.storage.model_dir(p.id) / "summary.json").is_file()
        return ProjectView(p.id, p.name, dict(p.config), p.created_at, int(n), has_model)

    # -- images ----------------------------------------------------------------------------
    def upload_images(
        self, tenant_id: str, project_id: str, uploads: Iterable[Upload], capture: str = "auto"
    ) -> list[ImageView]:
        """All files or none: every file is validated before the first one is stored. ``uploads``
        may be a stream (gRPC): each file is read to its end before the next is asked for."""
        capture = _choice("capture", capture, CAPTURES)
        if not uploads:
            raise InvalidRequest("no files: send one or more multipart fields named 'files'")
        with self.store.session() as s:
            self._project(s, tenant_id, project_id)
        staged: list[_Staged] = []
        moved: list[Path] = []
        try:
            seen: set[str] = set()
            for up in uploads:
                name = check_name(up.name)
                if name in seen:
                    raise BadFile(f"{name}: sent twice in one request")
                seen.add(name)
                file_capture = None if up.capture is None else _choice("capture", up.capture, CAPTURES)
                staged.append(self._stage(name, up.stream))
                staged[-1].capture = file_capture
            if not staged:
                raise InvalidRequest("no images were sent")
            try:
                with self.store.session() as s:
                    self._project(s, tenant_id, project_id)
                    views = self._register(s, project_id, staged, capture, moved)
            except IntegrityError:  # a concurrent upload took a name or the bytes first
                raise Conflict(
                    "another upload of the same name or bytes was committed concurrently; retry"
                ) from None
            except OperationalError as e:  # SQLite's SQLITE_FULL: the metadata store's disk is full
                if "disk is full" in str(e.orig):
                    raise InsufficientStorage(_FULL) from None
                raise
        except OSError as e:
            for path in moved:
                path.unlink(missing_ok=True)
            if e.errno in (errno.ENOSPC, errno.EDQUOT):
                raise InsufficientStorage(_FULL) from None
            raise
        except BaseException:
            for path in moved:
                path.unlink(missing_ok=True)
            raise
        finally:
            for st in staged:
                st.path.unlink(missing_ok=True)
        new = [v for v in views if v.created]
        if self.on_upload is not None and new:
            self.on_upload(len(new), sum(v.size_bytes for v in new))
        return views

    def _stage(self, name: str, stream: BinaryIO) -> _Staged:
        fd, tmp = self.storage.temp_file()
        h, size = hashlib.sha256(), 0
        try:
            with os.fdopen(fd, "wb") as f:
                while chunk := stream.read(_CHUNK):
                    size += len(chunk)
                    if size > self.settings.max_upload_bytes:
                        raise TooLarge(
                            f"{name}: larger than the upload limit of "
                            f"{self.settings.max_upload_bytes // (1024 * 1024)} MiB"
                        )
                    h.update(chunk)
                    self.storage.check_space(len(chunk))
                    f.write(chunk)
            info = check_image(tmp, name, self.settings.max_pixels)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return _Staged(name, tmp, h.hexdigest(), size, info)

    def _register(
        self, s: Session, project_id: str, staged: list[_Staged], capture: str, moved: list[Path]
    ) -> list[ImageView]:
        shas = [st.sha256 for st in staged]
        names = [st.name for st in staged]
        by_sha = {
            i.sha256: i
            for i in s.scalars(select(Image).where(Image.project_id == project_id, Image.sha256.in_(shas)))
        }
        by_name = {
            i.name: i
            for i in s.scalars(select(Image).where(Image.project_id == project_id, Image.name.in_(names)))
        }
        views: list[ImageView] = []
        new: list[tuple[_Staged, Image]] = []
        for st in staged:
            same = by_sha.get(st.sha256)
            if same is not None:  # the same bytes again: idempotent, whatever the name
                views.append(_image_view(same, created=False))
                continue
            if st.name in by_name:
                raise Conflict(
                    f"{st.name}: an image of this name with other content is already in the project"
                )
            img = Image(
                project_id=project_id,
                name=st.name,
                sha256=st.sha256,
                width=st.info.width,
                height=st.info.height,
                size_bytes=st.size,
                format=st.info.format,
                capture=st.capture or capture,
            )
            by_sha[st.sha256] = img
            new.append((st, img))
            views.append(_image_view(img, created=True))
        s.add_all([img for _, img in new])
        s.flush()
        images_dir = self.storage.images_dir(project_id)
        images_dir.mkdir(parents=True, exist_ok=True)
        for st, img in new:
            dest = images_dir / img.name
            os.replace(st.path, dest)
            moved.append(dest)
        return [_image_view(by_sha[v.sha256], created=v.created) for v in views]

    def image_file(self, tenant_id: str, project_id: str, name: str) -> tuple[Path, str]:
        """An uploaded image's bytes and media type, for a browser to show it (thumbnails)."""
        with self.store.session() as s:
            self._project(s, tenant_id, project_id)
            img = s.scalar(select(Image).where(Image.project_id == project_id, Image.name == name))
            if img is None:
                raise NotFound(f"image {name!r} not found in project {project_id}")
            fmt = img.format
        path = self.storage.image_path(project_id, name)
        if not path.is_file():
            raise NotFound(f"image {name!r} not found in project {project_id}")
        return path, IMAGE_MEDIA.get(fmt, "application/octet-stream")

    def list_images(self, tenant_id: str, project_id: str) -> list[ImageView]:
        with self.store.session() as s:
            self._project(s, tenant_id, project_id)
            rows = s.scalars(select(Image).where(Image.project_id == project_id).order_by(Image.name)).all()
            return [_image_view(i) for i in rows]

    # -- jobs ------------------------------------------------------------------------------
    def start_match(
        self, tenant_id: str, project_id: str, req: MatchRequest
    ) -> tuple[JobView, JobView | None]:
        with self.store.session() as s:
            p = self._project(s, tenant_id, project_id)
            names = set(s.scalars(select(Image.name).where(Image.project_id == project_id)))
            if len(names) < 2:
                raise InvalidRequest(f"the project has {len(names)} image(s); matching needs at least 2")
            given = {k: getattr(req, k) for k in PROJECT_OPTIONS}
            opts = {**DEFAULTS, **check_config(dict(p.config)), **check_config(given)}
            if isinstance(opts["pairs"], list):
                opts["pairs"] = check_pair_list(opts["pairs"], names)
            mapper = opts.pop("mapper")
            job = Job(project_id=project_id, tenant_id=tenant_id, kind="match", options=opts)
            s.add(job)
            s.flush()
            follower = _reconstruct_job(s, project_id, tenant_id, mapper, job.id) if req.reconstruct else None
            views = _job_view(job), _job_view(follower) if follower else None
        self._enqueue(views[0])
        return views

    def start_reconstruct(self, tenant_id: str, project_id: str, mapper: str | None = None) -> JobView:
        with self.store.session() as s:
            p = self._project(s, tenant_id, project_id)
            mapper = check_option("mapper", mapper or p.config.get("mapper") or DEFAULTS["mapper"])
            matched = s.scalar(
                select(func.count())
                .select_from(Job)
                .where(Job.project_id == project_id, Job.kind == "match", Job.state == "succeeded")
            )
            if not matched:
                raise Conflict(
                    "nothing to reconstruct yet: no match job of this project has succeeded "
                    '(POST .../match first, or with "reconstruct": true to chain both)'
                )
            view = _job_view(_reconstruct_job(s, project_id, tenant_id, mapper))
        self._enqueue(view)
        return view

    def _enqueue(self, job: JobView) -> None:
        try:
            self.queue.enqueue(ENTRY_STEP[job.kind], job.id)
        except Exception as e:
            jobstate.fail(self.store, job.id, f"could not queue the job: {e}")
            raise Unavailable(f"the job queue is not reachable ({e}); the job was not started") from None

    def get_job(self, tenant_id: str, job_id: str) -> JobView:
        with self.store.session() as s:
            job = s.get(Job, job_id)
            if job is None or job.tenant_id != tenant_id:
                raise NotFound(f"job {job_id} not found")
            return _job_view(job)

    def cancel_job(self, tenant_id: str, job_id: str) -> JobView:
        """Idempotent: a finished job is returned as it is."""
        self.get_job(tenant_id, job_id)
        if jobstate.cancel(self.store, job_id, "cancelled by the client"):
            jobstate.release_followers(self.store, self.queue, job_id)
        return self.get_job(tenant_id, job_id)

    def watch_job(
        self, tenant_id: str, job_id: str, interval_s: float = 0.5, heartbeat_s: float = 15.0
    ) -> Iterator[JobView | None]:
        """The job each time its state or progress changes, until it ends; None as a keep-alive."""
        watch = JobWatch(self, tenant_id, job_id, heartbeat_s)
        while not watch.finished:
            emit, job = watch.poll()
            if emit:
                yield job
            if not watch.finished:
                time.sleep(interval_s)

    # -- outputs ---------------------------------------------------------------------------
    def model_file(self, tenant_id: str, project_id: str, fmt: str) -> Path:
        files = {m.name: m.file for m in model_files()}
        if fmt not in files and fmt not in {f.name for f in export_formats()}:
            raise InvalidRequest(f"format must be one of {', '.join(model_formats())}, not {fmt!r}")
        self.get_project(tenant_id, project_id)
        if fmt not in files:
            return self._model_export(project_id, fmt)
        path = self.storage.model_dir(project_id) / files[fmt]
        if not path.is_file():
            if not (self.storage.model_dir(project_id) / "summary.json").is_file():
                raise NotFound(f"project {project_id} has no model yet: POST .../reconstruct")
            raise NotFound(f"the model of project {project_id} has no {fmt} (no 3D points)")
        return path

    def _model_export(self, project_id: str, fmt: str) -> Path:
        """The model exported as ``fmt`` (geomatch.export), zipped, built once and kept.

        The zip lives inside the model folder, under a key of that model's summary.json: a
        reconstruction swaps the whole folder, so a new model never serves an old export, and an
        export still being built from the old model when the swap happens lands under the old
        key, which the new summary never asks for. The zip is written beside and renamed (in
        ``export_zip``), so a concurrent request sees it whole or not at all. A format that reads
        the database (hloc) reads a snapshot of the project's (keypoints and verified matches as
        of the first request for this model).
        """
        from geomatch.export import ExportError, export_zip, model_dir, open_run

        model = self.storage.model_dir(project_id)
        try:
            summary = (model / "summary.json").read_bytes()
        except FileNotFoundError:
            raise NotFound(f"project {project_id} has no model yet: POST .../reconstruct") from None
        if not (model_dir(model) / "images.bin").is_file():
            raise NotFound(f"the model of project {project_id} has no {fmt} export (no registered images)")
        path = model / "exports" / hashlib.sha256(summary).hexdigest()[:16] / f"{fmt}.zip"
        if path.is_file():
            return path
        snapshot = None
        try:
            if DATABASE in FORMATS[fmt].needs:
                fd, snapshot = self.storage.temp_file()
                os.close(fd)
                snapshot_sqlite(self.storage.database_path(project_id), snapshot)
            source = open_run(model, images=self.storage.images_dir(project_id), database=snapshot)
            return export_zip(source, fmt, path)
        except ExportError as e:  # the model folder lacks an input (the images were deleted ...)
            raise NotFound(f"project {project_id}: {e}") from None
        finally:
            if snapshot is not None:
                snapshot.unlink(missing_ok=True)

    def model_scene(self, tenant_id: str, project_id: str) -> dict[str, Any]:
        """Points with colours and posed cameras of the largest model, for a 3D viewer."""
        self.get_project(tenant_id, project_id)
        return read_scene(self.storage.model_dir(project_id))

    def list_pairs(self, tenant_id: str, project_id: str) -> list[PairView]:
        """The project's matched pairs and their counts (none before the first match job)."""
        self.get_project(tenant_id, project_id)
        return read_pairs(self.storage.database_path(project_id))

    def database_snapshot(self, tenant_id: str, project_id: str) -> Path:
        """A consistent copy of the project's COLMAP database (SQLite's online backup), which the
        caller deletes: the live file may be mid-transaction at any moment."""
        self.get_project(tenant_id, project_id)
        src = self.storage.database_path(project_id)
        if not src.is_file():
            raise NotFound(
                f"project {project_id} has no COLMAP database yet: it is created by its first match job"
            )
        fd, tmp = self.storage.temp_file()
        os.close(fd)
        try:
            snapshot_sqlite(src, tmp)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return tmp

    def matches_picture(self, tenant_id: str, project_id: str, name0: str, name1: str) -> Path:
        with self.store.session() as s:
            self._project(s, tenant_id, project_id)
            known = set(
                s.scalars(
                    select(Image.name).where(Image.project_id == project_id, Image.name.in_([name0, name1]))
                )
            )
        for n in (name0, name1):
            if n not in known:
                raise NotFound(f"image {n!r} not found in project {project_id}")
        if name0 == name1:
            raise InvalidRequest("a pair has two different images")
        path = self.storage.picture_path(project_id, name0, name1)
        if path.is_file():
            return path
        try:
            out = self.queue.call(
                RENDER_PAIR, project_id, name0, name1, timeout=self.settings.render_timeout_s
            )
        except TimeoutError:
            raise Unavailable(
                f"no worker drew the picture within {self.settings.render_timeout_s}s; retry later"
            ) from None
        if out.get("error") == "not_matched":
            raise NotFound(f"pair ({name0}, {name1}) has not been matched in project {project_id}")
        if out.get("error"):
            raise Unavailable(f"drawing the picture failed: {out['error']}")
        return path

    # -- pairwise matching -----------------------------------------------------------------
    def match_two(
        self,
        tenant_id: str,
        uploads: Iterable[Upload],
        options: dict[str, Any] | None = None,
        timeout_s: float = 600.0,
    ) -> PairMatches:
        """Two images in, matches out, nothing kept. The images pass the upload checks, then the
        queue's interactive path matches them where heavy work runs (a worker, or the embedded
        runner), so this process never loads a network. ``timeout_s`` also reaches the worker,
        which drops the pair once it has passed."""
        opts = check_config(options or {})
        extra = sorted(set(opts) - set(PAIR_OPTIONS))
        if extra:
            raise InvalidRequest(f"option(s) {', '.join(extra)} do not apply to a single pair")
        opts = {k: opts.get(k, DEFAULTS[k]) for k in PAIR_OPTIONS}
        work = self.storage.tmp_dir / f"pair-{uuid.uuid4().hex}"  # shared with the workers
        work.mkdir(parents=True)
        try:
            captures: list[str] = []
            for up in uploads:
                if len(captures) == 2:
                    raise InvalidRequest("a pair is two images; a third was sent")
                name = check_name(up.name)
                captures.append(_choice("capture", up.capture or "auto", CAPTURES))
                os.replace(self._stage(name, up.stream).path, work / str(len(captures) - 1))
            if len(captures) != 2:
                raise InvalidRequest(f"a pair is two images; {len(captures)} were sent")
            deadline = time.time() + timeout_s
            try:
                out = self.queue.call(MATCH_TWO, work.name, captures, opts, deadline, timeout=timeout_s)
            except TimeoutError:
                raise Unavailable(f"no worker matched the pair within {timeout_s:.0f}s") from None
            if out.get("error"):
                raise Unavailable(f"matching the pair failed: {out['error']}")
            with np.load(work / out["file"]) as z:
                return PairMatches(
                    keypoints0=z["keypoints0"],
                    keypoints1=z["keypoints1"],
                    scores=z["scores"],
                    F=z["F"],
                    sizes=(_size(z["size0"]), _size(z["size1"])),
                    method=str(z["method"]),
                    tiled=bool(z["tiled"]),
                    timings={k: float(v) for k, v in out.get("timings", {}).items()},
                )
        finally:
            shutil.rmtree(work, ignore_errors=True)

    # -- health ----------------------------------------------------------------------------
    def readiness(self) -> Readiness:
        r = Readiness(ok=True)
        for name, check in (
            ("database", self.store.ping),
            ("queue", self.queue.ping),
            ("storage", self.storage.check_writable),
        ):
            try:
                check()
                r.checks[name] = "ok"
            except Exception as e:
                r.ok = False
                r.checks[name] = f"error: {e}"
        r.checks["mode"] = "embedded" if self.settings.embedded else "redis"
        return r


class JobWatch:
    """Change detection over a job, one poll at a time, so that a caller may wait between polls
    however it likes (a thread sleeping in ``watch_job``, an event loop in the SSE route)."""

    def __init__(self, service: Service, tenant_id: str, job_id: str, heartbeat_s: float = 15.0) -> None:
        self.service, self.tenant_id, self.job_id, self.heartbeat_s = service, tenant_id, job_id, heartbeat_s
        self.finished = False
        self._last: tuple[Any, ...] | None = None
        self._quiet_since = time.monotonic()

    def poll(self) -> tuple[bool, JobView | None]:
        """(True, job) when it changed, (True, None) when a keep-alive is due, else (False, None)."""
        job = self.service.get_job(self.tenant_id, self.job_id)
        key = (job.state, job.done, job.total, job.error)
        now = time.monotonic()
        if key != self._last:
            self._last, self._quiet_since = key, now
            self.finished = job.terminal
            return True, job
        if now - self._quiet_since > self.heartbeat_s:
            self._quiet_since = now
            return True, None
        return False, None


def _size(a: np.ndarray) -> tuple[int, int]:
    return int(a[0]), int(a[1])


def _reconstruct_job(
    s: Session, project_id: str, tenant_id: str, mapper: str, after: str | None = None
) -> Job:
    job = Job(
        project_id=project_id,
        tenant_id=tenant_id,
        kind="reconstruct",
        options={"mapper": mapper},
        total=1,
        after_job_id=after,
    )
    s.add(job)
    s.flush()
    return job


def _image_view(i: Image, created: bool = False) -> ImageView:
    return ImageView(
        i.id, i.name, i.width, i.height, i.capture, i.sha256, i.size_bytes, i.format, i.aerial, created
    )


def _job_view(j: Job) -> JobView:
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


def remove_quietly(path: Path) -> None:
    with contextlib.suppress(OSError):
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink()
