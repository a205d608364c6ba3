"""NodeODM tasks over the service's use cases: a task is a project of the token's tenant, its
images, its ground control points, and the match job (with its chained reconstruct job) that each
commit or restart starts. Nothing here runs work or stores rows of its own: projects, uploads,
GCP checks, quotas, jobs, cancellation and exports are the use cases' (service.usecases), so a
task obeys every limit a REST client does. The node keeps one small file per project
(``node-task.json``: the task's name, creation time, options as sent, whether it was committed)
and the files it is sent before the commit (``node/``: the GCP file, ``geo.txt``).

A task's uuid is its project's id written as a UUID (8-4-4-4-12), and either spelling finds it.
Its status and console output are read from its jobs each time they are asked for: the lines
are made only from facts that never change once true (a job queued, started, ended), so a client
reading from line N (WebODM's ``with_output``) never sees a line change under it.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import time
import uuid
import zipfile
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from geomatch_core.errors import BadFile, Conflict, NotFound, TooLarge, UnsupportedFormat

from ..usecases import Service
from ..usecases.views import JobView, MatchRequest, Upload
from .options import TaskOptions, parse_options

QUEUED, RUNNING, FAILED, COMPLETED, CANCELED = 10, 20, 30, 40, 50
TASK_FILE, STAGED, REFUSED = "node-task.json", "node", "refused.txt"
GEO_TXT, GROUPS_TXT = "geo.txt", "image_groups.txt"
MAX_TEXT_BYTES = 1024 * 1024  # a GCP file or geo.txt: a survey's is a few kB


def task_uuid(project_id: str) -> str:
    return str(uuid.UUID(hex=project_id))


def project_of(task: str) -> str:
    """The project id a task uuid names; NotFound for anything that is not a UUID."""
    try:
        return uuid.UUID(task.strip()).hex
    except (ValueError, AttributeError):
        raise NotFound(f"task {task[:80]!r} not found") from None


def _ms(when: datetime | None) -> int:
    if when is None:
        return 0
    return int((when if when.tzinfo else when.replace(tzinfo=UTC)).timestamp() * 1000)


@dataclass(frozen=True)
class Cycle:
    """One commit's or restart's work: its match job and the reconstruct job chained to it."""

    match: JobView
    reconstruct: JobView | None


class NodeTasks:
    def __init__(self, service: Service) -> None:
        self.svc = service

    # -- the node's own file per task ----------------------------------------------------------
    def _task_file(self, project_id: str) -> Path:
        return self.svc.storage.project_dir(project_id) / TASK_FILE

    def _read(self, tenant_id: str, task: str) -> tuple[str, dict[str, Any]]:
        pid = project_of(task)
        self.svc.projects.get_project(tenant_id, pid)  # the tenant's, or NotFound
        try:
            return pid, json.loads(self._task_file(pid).read_text())
        except FileNotFoundError:
            raise NotFound(f"task {task_uuid(pid)} not found") from None

    def _write(self, project_id: str, record: dict[str, Any]) -> None:
        self.svc.storage.put_file(self._task_file(project_id), json.dumps(record).encode())

    # -- creating a task ----------------------------------------------------------------------
    def init(
        self, tenant_id: str, name: str | None, options: str | None, created_ms: int | None = None
    ) -> str:
        """POST /task/new/init: the project, with the options checked first (nothing is created
        for options a known name refuses)."""
        opts = parse_options(options)
        label = (name or "").strip() or f"Task of {datetime.now(UTC):%Y-%m-%d %H:%M:%S}"
        project = self.svc.projects.create_project(tenant_id, label, opts.project)
        record = {
            "name": project.name,
            "created_ms": created_ms or _ms(project.created_at),
            "options": opts.given,
            "committed": False,
        }
        try:
            (self.svc.storage.project_dir(project.id) / STAGED).mkdir(parents=True, exist_ok=True)
            self._write(project.id, record)
        except BaseException:
            with contextlib.suppress(Exception):
                self.svc.projects.delete_project(tenant_id, project.id)
            raise
        return task_uuid(project.id)

    def upload(self, tenant_id: str, task: str, files: list[Upload]) -> None:
        """POST /task/new/upload/{uuid}: images go to the project (every check of an upload);
        a ``.txt`` is kept for the commit: ``geo.txt``, ``image_groups.txt`` (not used), else the
        GCP file."""
        pid, record = self._read(tenant_id, task)
        if record.get("committed"):
            raise Conflict(f"task {task_uuid(pid)} is committed: its files can no longer change")
        images = []
        for f in files:
            fname = (f.name or "").strip()
            if fname.lower().endswith(".txt"):
                data = f.stream.read(MAX_TEXT_BYTES + 1)
                if len(data) > MAX_TEXT_BYTES:
                    raise BadFile(f"{fname}: over {MAX_TEXT_BYTES // 1024} KiB")
                kind = fname.lower() if fname.lower() in (GEO_TXT, GROUPS_TXT) else "gcp_list.txt"
                staged = self.svc.storage.project_dir(pid) / STAGED
                self.svc.storage.put_file(staged / kind, data)
            else:
                images.append(f)
        if images:
            try:
                self.svc.images.upload_images(tenant_id, pid, images)
            except (BadFile, UnsupportedFormat, TooLarge) as e:
                # the file's own fault: answered by the commit, which removes the task. PyODM
                # sends a file its upload answer refused five times more, over 75 s, whatever the
                # answer says (its noRetry check reads a result the error never assigns)
                refused = self.svc.storage.project_dir(pid) / STAGED / REFUSED
                before = refused.read_text() if refused.is_file() else ""
                self.svc.storage.put_file(refused, (before + e.message + "\n").encode())

    def commit(self, tenant_id: str, task: str) -> str:
        """POST /task/new/commit/{uuid}: the GCP file checked against the images and stored, and
        the match job started with a reconstruct after it. A task whose files cannot be used
        (a GCP file that does not parse, fewer than 2 images) is removed whole and the error
        answered: nothing of it stays half made."""
        pid, record = self._read(tenant_id, task)
        if record.get("committed"):
            return task_uuid(pid)
        try:
            refused = self.svc.storage.project_dir(pid) / STAGED / REFUSED
            if refused.is_file():
                raise BadFile("; ".join(refused.read_text().splitlines()))
            staged = self.svc.storage.project_dir(pid) / STAGED / "gcp_list.txt"
            if staged.is_file():
                self.svc.gcp.put_gcp(tenant_id, pid, staged.read_bytes())
            self._start(tenant_id, pid, record, parse_options(json.dumps(record["options"])))
        except Exception:
            with contextlib.suppress(Exception):
                self.svc.projects.delete_project(tenant_id, pid)
            raise
        return task_uuid(pid)

    def _start(self, tenant_id: str, pid: str, record: dict[str, Any], opts: TaskOptions) -> None:
        given = dict(opts.project)
        pairs = given.pop("pairs", None)
        req = MatchRequest(pairs=pairs, reconstruct=True, checkpoints=opts.checkpoints, **given)
        self.svc.jobs.start_match(tenant_id, pid, req)
        self._write(pid, {**record, "options": opts.given, "committed": True})

    # -- reading a task ------------------------------------------------------------------------
    def _cycles(self, tenant_id: str, pid: str) -> list[Cycle]:
        jobs: list[JobView] = []
        offset: int | None = 0
        while offset is not None:
            page = self.svc.jobs.list_jobs(tenant_id, pid, offset=offset)
            jobs += page.items
            offset = page.next_offset
        jobs.sort(key=lambda j: (j.created_at, j.id))
        after = {j.after_job_id: j for j in jobs if j.kind == "reconstruct" and j.after_job_id}
        return [Cycle(j, after.get(j.id)) for j in jobs if j.kind == "match"]

    def info(self, tenant_id: str, task: str, with_output: int | None = None) -> dict[str, Any]:
        pid, record = self._read(tenant_id, task)
        project = self.svc.projects.get_project(tenant_id, pid)
        cycles = self._cycles(tenant_id, pid)
        status, error, progress, processing = task_status(cycles[-1] if cycles else None)
        out: dict[str, Any] = {
            "uuid": task_uuid(pid),
            "name": record.get("name", project.name),
            "dateCreated": int(record.get("created_ms", 0)),
            "processingTime": processing,
            "status": {"code": status, **({"errorMessage": error} if error else {})},
            "options": record.get("options", []),
            "imagesCount": project.images,
            "progress": progress,
        }
        if with_output is not None:
            out["output"] = self.output(tenant_id, task, with_output)
        return out

    def output(self, tenant_id: str, task: str, line: int = 0) -> list[str]:
        pid, record = self._read(tenant_id, task)
        lines = self._console(tenant_id, pid, record)
        return lines[max(0, line) :] if line >= 0 else lines[line:]

    def _console(self, tenant_id: str, pid: str, record: dict[str, Any]) -> list[str]:
        lines = [f"geomatch task {record.get('name', '')} ({task_uuid(pid)})"]
        cycles = self._cycles(tenant_id, pid)
        for n, c in enumerate(cycles):
            lines += _cycle_lines(n, c)
        # the model's survey report closes the console of a completed run (a restart's lines
        # take its place until that run completes: WebODM starts a restarted task's console anew)
        done = bool(cycles) and task_status(cycles[-1])[0] == COMPLETED
        if done and self._model_summary(pid) is not None:
            with contextlib.suppress(NotFound):
                from geomatch.report import to_markdown

                report = self.svc.outputs.survey_report(tenant_id, pid).report
                lines += to_markdown(report, f"Survey report: {record.get('name', '')}").splitlines()
        return lines

    def _model_summary(self, pid: str) -> Path | None:
        path = self.svc.storage.model_dir(pid) / "summary.json"
        return path if path.is_file() else None

    def list(self, tenant_id: str) -> list[dict[str, str]]:
        out = []
        offset: int | None = 0
        while offset is not None:
            page = self.svc.projects.list_projects(tenant_id, offset=offset)
            out += [{"uuid": task_uuid(p.id)} for p in page.items if self._task_file(p.id).is_file()]
            offset = page.next_offset
        return out

    # -- commands ------------------------------------------------------------------------------
    def cancel(self, tenant_id: str, task: str) -> None:
        pid, _ = self._read(tenant_id, task)
        for c in self._cycles(tenant_id, pid):
            for job in (c.match, c.reconstruct):
                if job is not None and not job.terminal:
                    self.svc.jobs.cancel_job(tenant_id, job.id)

    def remove(self, tenant_id: str, task: str) -> None:
        pid, _ = self._read(tenant_id, task)
        self.svc.projects.delete_project(tenant_id, pid)

    def restart(self, tenant_id: str, task: str, options: str | None) -> None:
        """Runs the task's jobs again (the database keeps the pairs matched, so only what the
        new options add is matched), with ``options`` in place of the earlier ones when given."""
        pid, record = self._read(tenant_id, task)
        if not record.get("committed"):
            raise Conflict(f"task {task_uuid(pid)} was never committed: commit it first")
        cycles = self._cycles(tenant_id, pid)
        if cycles and task_status(cycles[-1])[0] in (QUEUED, RUNNING):
            raise Conflict(f"task {task_uuid(pid)} is still running: cancel it first")
        opts = parse_options(options if options is not None else json.dumps(record.get("options", [])))
        self._start(tenant_id, pid, record, opts)

    # -- results -------------------------------------------------------------------------------
    def all_zip(self, tenant_id: str, task: str) -> Path:
        """The task's results: the model's ``odm`` export (built once per model by the outputs
        use case) plus ``task_output.txt``, as one zip kept per model and console, so the parallel
        Range requests of one download all read the same bytes."""
        pid, record = self._read(tenant_id, task)
        cycles = self._cycles(tenant_id, pid)
        if not cycles or task_status(cycles[-1])[0] != COMPLETED:
            raise Conflict(f"task {task_uuid(pid)} has not completed: nothing to download yet")
        odm = self.svc.outputs.model_file(tenant_id, pid, "odm")
        console = ("\n".join(self._console(tenant_id, pid, record)) + "\n").encode()
        # the export's folder is named by the model's summary: a new model is a new key
        key = hashlib.sha256(odm.parent.name.encode() + b"\0" + console).hexdigest()
        dest = self.svc.storage.project_dir(pid) / STAGED / f"all-{key[:16]}.zip"
        if dest.is_file():
            return dest
        for old in dest.parent.glob("all-*.zip"):
            old.unlink(missing_ok=True)  # an earlier model's or console's: never asked for again
        fd, tmp = self.svc.storage.temp_file()
        try:
            with open(fd, "wb") as f, zipfile.ZipFile(f, "w", zipfile.ZIP_DEFLATED) as out:
                with zipfile.ZipFile(odm) as src:
                    for info in src.infolist():
                        with src.open(info) as part:
                            out.writestr(info, part.read())
                stamp = zipfile.ZipInfo("task_output.txt", date_time=(1980, 1, 1, 0, 0, 0))
                out.writestr(stamp, console, compress_type=zipfile.ZIP_DEFLATED)
            os.replace(tmp, dest)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return dest

    def queue_count(self) -> int:
        """Tasks queued or running on this node (every tenant's jobs; a task counts its match
        and reconstruct jobs as one when they wait together)."""
        from sqlalchemy import func, select

        from geomatch_core.models import Job

        with self.svc.store.session() as s:
            n = s.scalar(
                select(func.count())
                .select_from(Job)
                .where(Job.kind == "match", Job.state.in_(("queued", "running")))
            )
            m = s.scalar(
                select(func.count()).select_from(Job).where(Job.kind == "reconstruct", Job.state == "running")
            )
        return int(n or 0) + int(m or 0)


def task_status(c: Cycle | None) -> tuple[int, str | None, int, int]:
    """(status code, error, progress 0-100, processing ms) of a task's latest cycle."""
    if c is None:
        return QUEUED, None, 0, 0
    m, r = c.match, c.reconstruct
    start = m.started_at or m.created_at
    end = (r.finished_at if r is not None else None) or m.finished_at
    processing = max(0, (_ms(end) if end else int(time.time() * 1000)) - _ms(start)) if m.started_at else 0
    if m.state == "cancelled" or (r is not None and r.state == "cancelled" and m.state == "succeeded"):
        return CANCELED, None, _progress(m, r), processing
    if m.state == "failed":
        return FAILED, f"matching failed: {m.error}", _progress(m, r), processing
    if r is not None and r.state == "failed":
        return FAILED, f"reconstruction failed: {r.error}", _progress(m, r), processing
    if r is not None and r.state == "succeeded":
        return COMPLETED, None, 100, processing
    if m.state == "queued":
        return QUEUED, None, 0, 0
    return RUNNING, None, _progress(m, r), processing


def _progress(m: JobView, r: JobView | None) -> int:
    """Matching is 5-80 (by pairs), mapping 80-99: never back while one cycle runs."""
    if r is not None and r.state == "succeeded":
        return 100
    if m.state == "succeeded":
        return 90 if r is not None and r.state == "running" else 80
    if m.state == "queued":
        return 0
    return 5 + int(75 * m.done / m.total) if m.total else 5


def _cycle_lines(n: int, c: Cycle) -> list[str]:
    m, r = c.match, c.reconstruct
    head = "commit" if n == 0 else f"restart {n}"
    opts = ", ".join(f"{k}={v}" for k, v in sorted(m.options.items()))
    lines = [f"[{head}] match job {m.id} queued ({opts})"]
    if m.started_at:
        lines.append(f"[{head}] matching started")
    if m.terminal:
        lines.append(
            f"[{head}] matching {m.state}: {m.done} of {m.total} pairs" + (f": {m.error}" if m.error else "")
        )
    if r is not None and m.state == "succeeded":
        if r.started_at:
            lines.append(f"[{head}] reconstruction started (mapper {r.options.get('mapper')})")
        if r.terminal:
            lines.append(f"[{head}] reconstruction {r.state}" + (f": {r.error}" if r.error else ""))
        if r.state == "succeeded" and r.result:
            s = r.result
            lines.append(
                f"[{head}] registered {s.get('registered')} of {s.get('images')} images, {s.get('points3D')} "
                f"points, georeferenced: {bool(s.get('georeferenced'))}"
            )
    return lines
