"""Ground control points: a project's OpenDroneMap ``gcp_list.txt``, put, read and removed.

A file is checked against the project's images when it is put (``geomatch.geo.gcpfile``): one the
project cannot use at all (no coordinate system PROJ knows, fewer than 3 usable points) is refused
with the reason and nothing is stored; a usable one replaces the project's earlier one in one rename
(``Storage.put_file``). What is wrong with single lines or points (an image not in the project yet,
a pixel outside its image, a point seen in one photo only) is reported, not refused: the answer is
the file's summary. A reconstruct job reads the file again when it runs, against the images of that
moment (``workers.jobs.reconstruct``), and georeferences the model by it.

An image's size is its row's: the width and height the upload check read from the stored file
(Pillow's size, before any EXIF orientation: the pixels of a GCP file, and what
``geomatch.metadata.read_metadata`` reads for ``geomatch run --gcp``).

The library's GCP reader (numpy, pyproj) is imported inside the calls: importing the API loads
none of it. It runs on a thread of its own with a deadline (``read_gcps``): the coordinate system is
held to an allow-list before PROJ sees it (``geomatch.geo.gcpfile.parse_crs``), so nothing a file
says opens a file or reaches the network, and the deadline is the bound behind that: a call that
still blocked would cost one thread of a few, never the caller's thread or the health checks.
"""

from __future__ import annotations

import errno
import queue
import threading
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from geomatch_core.errors import (
    BadFile,
    InsufficientStorage,
    InvalidRequest,
    NotFound,
    Overloaded,
    TooLarge,
)
from geomatch_core.models import Image
from geomatch_core.storage import Storage

from .base import UseCases
from .views import GcpView

MiB = 1024 * 1024
MAX_GCP_BYTES = MiB  # a survey's file is a few kB: thousands of observations fit in 1 MiB
MAX_CHECKPOINTS = 10_000  # names in a reconstruct request, or their count
MAX_CHECKPOINT_NAME = 1000  # characters of one name
GCP_READ_TIMEOUT_S = 10.0  # a 1 MiB file of 20,000 observations reads in well under a second
GCP_READERS = 8  # files read at once in one API process; a reader past its deadline keeps its place
_readers = threading.BoundedSemaphore(GCP_READERS)
NO_FILE = "send OpenDroneMap's gcp_list.txt as the request body (text/plain) or as the multipart field 'file'"


def image_sizes(s: Session, project_id: str) -> dict[str, tuple[int, int]]:
    """Every image of the project: name -> (width, height)."""
    rows = s.execute(select(Image.name, Image.width, Image.height).where(Image.project_id == project_id))
    return {name: (int(w), int(h)) for name, w, h in rows}


def gcp_text(data: bytes) -> str:
    """The uploaded bytes as text: UTF-8 (a byte order mark is dropped), no NUL, within the limit."""
    if len(data) > MAX_GCP_BYTES:
        raise TooLarge(f"the GCP file is {len(data)} bytes, over the limit of {MAX_GCP_BYTES // MiB} MiB")
    if not data:
        raise InvalidRequest(f"no GCP file: {NO_FILE}")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = data[: e.start].count(b"\n") + 1
        raise BadFile(f"the GCP file is not UTF-8 text (line {line}, byte {e.start})") from None
    if "\x00" in text:
        line = text[: text.index("\x00")].count("\n") + 1
        raise BadFile(f"the GCP file holds a NUL byte on line {line}: it is not a text file")
    return text


def read_gcps(text: str, sizes: dict[str, tuple[int, int]], timeout_s: float = GCP_READ_TIMEOUT_S) -> Any:
    """``geomatch.geo.gcpfile.read_gcp_file`` on a daemon thread of its own, within ``timeout_s``;
    a file the project cannot use, a PROJ error, or a read past the deadline is InvalidRequest.
    With GCP_READERS reads running (past their deadline ones included) it is 429: no read waits."""
    from pyproj.exceptions import ProjError

    from geomatch.geo.gcpfile import GcpError, read_gcp_file

    if not _readers.acquire(blocking=False):
        raise Overloaded(f"{GCP_READERS} GCP files are being read: retry in a second")
    answer: queue.Queue[tuple[Any, BaseException | None]] = queue.Queue(maxsize=1)

    def read() -> None:
        try:
            answer.put((read_gcp_file(text, sizes), None))
        except BaseException as e:  # handed to the caller, which raises it
            answer.put((None, e))
        finally:
            _readers.release()

    threading.Thread(target=read, name="gcp-read", daemon=True).start()
    try:
        gcps, error = answer.get(timeout=timeout_s)
    except queue.Empty:
        raise InvalidRequest(
            f"line 1: the GCP file could not be read within {timeout_s:g} s: give its coordinate "
            "system as an EPSG code, WGS84, a PROJ string or WKT"
        ) from None
    if isinstance(error, GcpError):
        raise InvalidRequest(str(error)) from None
    if isinstance(error, ProjError):  # CRSError too: every PROJ error is about line 1
        raise InvalidRequest(f"line 1: PROJ cannot use the coordinate system ({str(error)[:200]})") from None
    if error is not None:
        raise error
    return gcps


def _view(summary: dict[str, Any], size: int, error: str | None = None) -> GcpView:
    return GcpView(
        crs=str(summary.get("crs", "")),
        frame=None if summary.get("frame") is None else str(summary["frame"]),
        points=[str(p) for p in summary.get("points", [])],
        unusable={str(k): str(v) for k, v in dict(summary.get("unusable", {})).items()},
        problems=[str(p) for p in summary.get("problems", [])],
        size_bytes=size,
        error=error,
    )


def stored_text(storage: Storage, project_id: str) -> str | None:
    """The project's stored GCP file, None when it has none."""
    try:
        return storage.gcp_path(project_id).read_bytes().decode("utf-8")
    except FileNotFoundError:
        return None


def check_checkpoints(
    s: Session, storage: Storage, project_id: str, value: list[str] | int | None
) -> list[str] | int:
    """A reconstruct request's check points (names, or how many to hold out), checked against the
    project's GCP file as it reads now: 0 for none. The job may still find fewer points placed in
    the model than asked for; its summary's ``gcp`` then says so, and the model keeps its frame."""
    if value is None:
        return 0
    if isinstance(value, bool) or not isinstance(value, int | list):
        raise InvalidRequest("checkpoints must be a number of check points or a list of point names")
    if isinstance(value, int):
        if not 0 <= value <= MAX_CHECKPOINTS:
            raise InvalidRequest(f"checkpoints must be between 0 and {MAX_CHECKPOINTS}, not {value}")
        if value == 0:
            return 0
    else:
        if len(value) > MAX_CHECKPOINTS:
            raise InvalidRequest(f"{len(value)} check points: at most {MAX_CHECKPOINTS}")
        bad = [v for v in value if not isinstance(v, str) or not v or len(v) > MAX_CHECKPOINT_NAME]
        if bad:
            raise InvalidRequest(
                f"check point names must be text of 1 to {MAX_CHECKPOINT_NAME} characters, not {bad[0]!r}"
            )
        if len(set(value)) != len(value):
            raise InvalidRequest("a check point is named twice")
        if not value:
            return 0
    text = stored_text(storage, project_id)
    if text is None:
        raise InvalidRequest(
            f"check points need ground control points: project {project_id} has none "
            f"(PUT /v1/projects/{project_id}/gcp first)"
        )
    from geomatch.geo.gcp import choose_checkpoints
    from geomatch.geo.gcpfile import GcpError

    gcps = read_gcps(text, image_sizes(s, project_id))
    try:
        choose_checkpoints(sorted(gcps.points), value)
    except GcpError as e:
        raise InvalidRequest(str(e)) from None
    return value


class GcpUseCases(UseCases):
    def put_gcp(self, tenant_id: str, project_id: str, data: bytes) -> GcpView:
        """Check ``data`` against the project's images and store it in place of the earlier file;
        a file that cannot be used is refused with the reason, and the earlier one stays."""
        with self._unless_deleted(tenant_id, project_id):
            with self.ctx.store.session() as s:
                self._project(s, tenant_id, project_id)  # an unknown project first, whatever the body
                sizes = image_sizes(s, project_id)
            text = gcp_text(data)
            gcps = read_gcps(text, sizes)
            stored = text.encode("utf-8")
            try:
                self.ctx.storage.put_file(self.ctx.storage.gcp_path(project_id), stored)
            except OSError as e:
                if e.errno in (errno.ENOSPC, errno.EDQUOT):
                    raise InsufficientStorage(
                        "the storage is full (no space left on device): the GCP file was not stored; "
                        "retry when space is freed"
                    ) from None
                raise
        return _view(gcps.summary(), len(stored))

    def get_gcp(self, tenant_id: str, project_id: str) -> GcpView:
        """The stored file's summary, read again against the project's images now (images added
        since may see points that had none). A file that no longer fits them is answered with
        ``error``; a reconstruct job then leaves the model in its frame."""
        with self.ctx.store.session() as s:
            self._project(s, tenant_id, project_id)
            sizes = image_sizes(s, project_id)
        text = stored_text(self.ctx.storage, project_id)
        if text is None:
            raise NotFound(f"project {project_id} has no ground control points")
        size = len(text.encode("utf-8"))
        try:
            return _view(read_gcps(text, sizes).summary(), size)
        except InvalidRequest as e:
            lines = (ln.strip() for ln in text.splitlines())
            header = next((ln for ln in lines if ln and not ln.startswith("#")), "")
            return _view({"crs": header}, size, e.message)

    def delete_gcp(self, tenant_id: str, project_id: str) -> None:
        with self.ctx.store.session() as s:
            self._project(s, tenant_id, project_id)
        try:
            self.ctx.storage.gcp_path(project_id).unlink()
        except FileNotFoundError:
            raise NotFound(f"project {project_id} has no ground control points") from None
