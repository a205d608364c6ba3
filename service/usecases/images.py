"""Images: uploads (all files of a request or none), listing, the stored bytes."""

from __future__ import annotations

import errno
import os
from collections.abc import Iterable
from pathlib import Path

from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError, OperationalError
from sqlalchemy.orm import Session

from geomatch.options import CAPTURES
from geomatch_core.errors import (
    BadFile,
    Conflict,
    InsufficientStorage,
    InvalidRequest,
    NotFound,
    QuotaExceeded,
    Unavailable,
)
from geomatch_core.models import Image, Project

from ..ids import known_name
from ..paging import IMAGES, Page, page_of
from ..validation import check_name
from .base import Staged, UseCases, choice, staged_bytes
from .views import ImageView, Upload, image_view

# how a stored image is served back (the validated format, never the client's claim)
IMAGE_MEDIA = {
    "jpeg": "image/jpeg",
    "png": "image/png",
    "tiff": "image/tiff",
    "bmp": "image/bmp",
    "webp": "image/webp",
}
_FULL = (
    "the storage is full (no space left on device): nothing of this upload was kept; "
    "retry when space is freed"
)


class ImageUseCases(UseCases):
    def upload_images(
        self, tenant_id: str, project_id: str, uploads: Iterable[Upload], capture: str = "auto"
    ) -> list[ImageView]:
        """All files or none: every file is validated before the first one is stored. ``uploads``
        may be a stream (gRPC): each file is read to its end before the next is asked for."""
        capture = choice("capture", capture, CAPTURES)
        if not uploads:
            raise InvalidRequest("no files: send one or more multipart fields named 'files'")
        with self._unless_deleted(tenant_id, project_id):
            views = self._store(tenant_id, project_id, uploads, capture)
        new = [v for v in views if v.created]
        if self.ctx.on_upload is not None and new:
            self.ctx.on_upload(len(new), sum(v.size_bytes for v in new))
        return views

    def _store(
        self, tenant_id: str, project_id: str, uploads: Iterable[Upload], capture: str
    ) -> list[ImageView]:
        with self.ctx.store.session() as s:
            self._project(s, tenant_id, project_id)
        staged: list[Staged] = []
        moved: list[Path] = []
        committing = False
        try:
            seen: set[str] = set()
            for up in uploads:
                name = check_name(up.name)
                if name in seen:
                    raise BadFile(f"{name}: sent twice in one request")
                seen.add(name)
                file_capture = None if up.capture is None else choice("capture", up.capture, CAPTURES)
                staged.append(self._stage(name, up.stream))
                staged[-1].capture = file_capture
            if not staged:
                raise InvalidRequest("no images were sent")
            try:
                with self.ctx.store.session() as s:
                    self._project(s, tenant_id, project_id)
                    views = self._register(s, tenant_id, project_id, staged, capture, moved)
                    committing = True
            # a concurrent upload took a name or the bytes first (or a delete took the project:
            # upload_images answers NotFound for that)
            except IntegrityError:
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
        except Unavailable:
            # a connection lost during COMMIT leaves its outcome unknown: the rows may be in the
            # database, so their files stay (a file without a row is harmless and a retry
            # re-registers it; a listed image without its bytes would fail every job that reads it)
            if not committing:
                for path in moved:
                    path.unlink(missing_ok=True)
            raise
        except BaseException:
            for path in moved:
                path.unlink(missing_ok=True)
            raise
        finally:
            for st in staged:
                st.path.unlink(missing_ok=True)
        return views

    def _register(
        self,
        s: Session,
        tenant_id: str,
        project_id: str,
        staged: list[Staged],
        capture: str,
        moved: list[Path],
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
        new: list[tuple[Staged, Image]] = []
        for st in staged:
            same = by_sha.get(st.sha256)
            if same is not None:  # the same bytes again: idempotent, whatever the name
                self._restore_missing(project_id, same, st)
                views.append(image_view(same, created=False))
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
            views.append(image_view(img, created=True))
        self._within_image_quotas(s, tenant_id, [st for st, _ in new])
        s.add_all([img for _, img in new])
        s.flush()
        images_dir = self.ctx.storage.images_dir(project_id)
        images_dir.mkdir(parents=True, exist_ok=True)
        for st, img in new:
            dest = images_dir / img.name
            os.replace(st.path, dest)
            moved.append(dest)
        return [image_view(by_sha[v.sha256], created=v.created) for v in views]

    def _restore_missing(self, project_id: str, img: Image, st: Staged) -> None:
        """A retry heals a row whose file is gone: the bytes are the same (same sha256), so the
        staged copy takes the missing file's place. A row can outlive its file when an earlier
        request's commit reached the database but its acknowledgement was lost with the
        connection, and the request's cleanup removed the file it had moved into place."""
        dest = self.ctx.storage.images_dir(project_id) / img.name
        if dest.is_file() and dest.stat().st_size == img.size_bytes:
            return
        dest.parent.mkdir(parents=True, exist_ok=True)
        os.replace(st.path, dest)

    def _within_image_quotas(self, s: Session, tenant_id: str, new: list[Staged]) -> None:
        """QuotaExceeded when the new images would take the tenant past ``quota_images`` or
        ``quota_bytes`` (all its projects together); the request then stores nothing."""
        n_quota, bytes_quota = self.ctx.settings.quota_images, self.ctx.settings.quota_bytes
        if not new or not (n_quota or bytes_quota):
            return
        n, size = s.execute(
            select(func.count(Image.id), func.coalesce(func.sum(Image.size_bytes), 0))
            .join(Project, Project.id == Image.project_id)
            .where(Project.tenant_id == tenant_id)
        ).one()
        if n_quota and n + len(new) > n_quota:
            raise QuotaExceeded(
                f"this key's tenant has {n} images, its quota is {n_quota}: these {len(new)} would "
                "pass it (delete a project to make room)"
            )
        added = sum(st.size for st in new)
        size += staged_bytes(s, tenant_id) if bytes_quota else 0
        if bytes_quota and size + added > bytes_quota:
            raise QuotaExceeded(
                f"this key's tenant stores {size} bytes of images (photos staged for localizing "
                f"included), its quota is {bytes_quota}: these {added} would pass it (delete a project "
                "to make room)"
            )

    def image_file(self, tenant_id: str, project_id: str, name: str) -> tuple[Path, str]:
        """An uploaded image's bytes and media type, for a browser to show it (thumbnails)."""
        with self.ctx.store.session() as s:
            self._project(s, tenant_id, project_id)
            name = known_name(project_id, name)
            img = s.scalar(select(Image).where(Image.project_id == project_id, Image.name == name))
            if img is None:
                raise NotFound(f"image {name!r} not found in project {project_id}")
            fmt = img.format
        path = self.ctx.storage.image_path(project_id, name)
        if not path.is_file():
            raise NotFound(f"image {name!r} not found in project {project_id}")
        return path, IMAGE_MEDIA.get(fmt, "application/octet-stream")

    def list_images(
        self, tenant_id: str, project_id: str, offset: int = 0, limit: int | None = None
    ) -> Page[ImageView]:
        """One page of the project's images by name (``paging.IMAGES``: its sizes)."""
        limit = IMAGES.clamp(limit)
        with self.ctx.store.session() as s:
            self._project(s, tenant_id, project_id)
            rows = s.scalars(
                select(Image)
                .where(Image.project_id == project_id)
                .order_by(Image.name)
                .offset(offset)
                .limit(limit + 1)
            ).all()
            return page_of([image_view(i) for i in rows], offset, limit)
