"""Outputs: the model in its formats (the export table's included), the scene for a viewer, the
survey report, the matched pairs, a snapshot of the COLMAP database, the picture of a pair's
matches."""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy import select

from geomatch.export.formats import DATABASE, FORMATS, ExportFormat
from geomatch.report import survey_report
from geomatch.sfm.sqlitecopy import snapshot_sqlite
from geomatch_core.errors import InvalidRequest, NotFound, Unavailable
from geomatch_core.models import Image
from geomatch_core.queue import RENDER_PAIR

from ..ids import known_name
from ..modelscene import read_scene
from ..pairlist import PairView, read_pairs
from .base import UseCases
from .views import ReportView


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


class OutputUseCases(UseCases):
    def model_file(self, tenant_id: str, project_id: str, fmt: str) -> Path:
        files = {m.name: m.file for m in model_files()}
        if fmt not in files and fmt not in {f.name for f in export_formats()}:
            raise InvalidRequest(f"format must be one of {', '.join(model_formats())}, not {fmt!r}")
        self._owned(tenant_id, project_id)
        if fmt not in files:
            return self._model_export(tenant_id, project_id, fmt)
        path = self.ctx.storage.model_dir(project_id) / files[fmt]
        if not path.is_file():
            if not (self.ctx.storage.model_dir(project_id) / "summary.json").is_file():
                raise NotFound(f"project {project_id} has no model yet: POST .../reconstruct")
            why = FORMATS[fmt].missing if fmt in FORMATS else "no 3D points"
            raise NotFound(f"the model of project {project_id} has no {fmt} ({why})")
        return path

    def _model_export(self, tenant_id: str, project_id: str, fmt: str) -> Path:
        """The model exported as ``fmt`` (geomatch.export), zipped, built once and kept.

        The zip lives inside the model folder, under a key of that model's summary.json: a
        reconstruction swaps the whole folder, so a new model never serves an old export, and an
        export still being built from the old model when the swap happens lands under the old
        key, which the new summary never asks for. The zip is written beside and renamed (in
        ``export_zip``), so a concurrent request sees it whole or not at all. A format that reads
        the database (hloc) reads a snapshot of the project's (keypoints and verified matches as
        of the first request for this model). Building one is heavy work: it takes one of the
        tenant's ``heavy`` slots.
        """
        from geomatch.export import ExportError, export_zip, model_dir, open_run

        model = self.ctx.storage.model_dir(project_id)
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
            with self.ctx.heavy.open(tenant_id):
                if DATABASE in FORMATS[fmt].needs:
                    fd, snapshot = self.ctx.storage.temp_file()
                    os.close(fd)
                    snapshot_sqlite(self.ctx.storage.database_path(project_id), snapshot)
                source = open_run(model, images=self.ctx.storage.images_dir(project_id), database=snapshot)
                return export_zip(source, fmt, path)
        except ExportError as e:  # the model folder lacks an input (the images were deleted ...)
            raise NotFound(f"project {project_id}: {e}") from None
        finally:
            if snapshot is not None:
                snapshot.unlink(missing_ok=True)

    def model_scene(self, tenant_id: str, project_id: str) -> dict[str, Any]:
        """Points with colours and posed cameras of the largest model, for a 3D viewer."""
        self._owned(tenant_id, project_id)
        with self.ctx.heavy.open(tenant_id):  # parses every point of the model's text files
            return read_scene(self.ctx.storage.model_dir(project_id))

    def survey_report(self, tenant_id: str, project_id: str) -> ReportView:
        """The survey report of the project's model (geomatch.report): the one its reconstruct
        job wrote into summary.json, or, for a model made before reports existed, built now from
        that summary (the same function builds both)."""
        with self.ctx.store.session() as s:
            name = self._project(s, tenant_id, project_id).name
        try:
            summary = json.loads((self.ctx.storage.model_dir(project_id) / "summary.json").read_bytes())
        except FileNotFoundError:
            raise NotFound(f"project {project_id} has no model yet: POST .../reconstruct") from None
        report = summary.get("report") or survey_report(summary)
        return ReportView(project_name=name, report=_finite(report))

    def list_pairs(self, tenant_id: str, project_id: str) -> list[PairView]:
        """The project's matched pairs and their counts (none before the first match job)."""
        self._owned(tenant_id, project_id)
        return read_pairs(self.ctx.storage.database_path(project_id))

    def database_snapshot(self, tenant_id: str, project_id: str) -> Path:
        """A consistent copy of the project's COLMAP database (SQLite's online backup), which the
        caller deletes: the live file may be mid-transaction at any moment."""
        self._owned(tenant_id, project_id)
        src = self.ctx.storage.database_path(project_id)
        if not src.is_file():
            raise NotFound(
                f"project {project_id} has no COLMAP database yet: it is created by its first match job"
            )
        fd, tmp = self.ctx.storage.temp_file()
        os.close(fd)
        try:
            with self.ctx.heavy.open(tenant_id):
                snapshot_sqlite(src, tmp)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return tmp

    def matches_picture(self, tenant_id: str, project_id: str, name0: str, name1: str) -> Path:
        with self.ctx.store.session() as s:
            self._project(s, tenant_id, project_id)
            name0, name1 = known_name(project_id, name0), known_name(project_id, name1)
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
        path = self.ctx.storage.picture_path(project_id, name0, name1)
        if path.is_file():
            return path
        # waiting for a worker holds a thread of the API for up to render_timeout_s: a heavy slot.
        # without one, a tenant's waiting pictures could take every thread, /healthz included
        try:
            with self.ctx.heavy.open(tenant_id):
                out = self.ctx.queue.call(
                    RENDER_PAIR, project_id, name0, name1, timeout=self.ctx.settings.render_timeout_s
                )
        except TimeoutError:
            raise Unavailable(
                f"no worker drew the picture within {self.ctx.settings.render_timeout_s}s; retry later"
            ) from None
        if out.get("error") == "not_matched":
            raise NotFound(f"pair ({name0}, {name1}) has not been matched in project {project_id}")
        if out.get("error"):
            raise Unavailable(f"drawing the picture failed: {out['error']}")
        return path


def _finite(value: Any) -> Any:
    """``value`` with NaN and infinities as None: summary.json is Python's JSON, which writes them,
    and a JSON answer may not hold them."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value


def remove_quietly(path: Path) -> None:
    with contextlib.suppress(OSError):
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink()
