"""File storage under the storage root (GEOMATCH_HOME): where each project's files live.

Layout, one folder per project::

    projects/<id>/images/<name>        the uploaded bytes, as uploaded
    projects/<id>/database.db          the COLMAP database (written by one writer at a time)
    projects/<id>/gcp_list.txt         the ground control points (OpenDroneMap's format), as accepted
    projects/<id>/model/               sparse/0 ..., points.ply, summary.json, model.zip
    projects/<id>/pictures/            match pictures, rendered on first request
    projects/<id>/localize/<job>/      photos of a localize job that are not added to the project,
                                       kept until the job ends
    features/                          the workers' feature cache (safe to delete)
    tmp/                               uploads being validated; renamed into place when accepted

Every file appears by rename from a temporary name on the same file system, so a reader never
sees half a file and a crash leaves only temporaries behind.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import os
import shutil
import tempfile
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path


class Storage:
    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)

    def ensure(self) -> None:
        for d in (self.root / "projects", self.tmp_dir, self.features_dir):
            d.mkdir(parents=True, exist_ok=True)

    @property
    def tmp_dir(self) -> Path:
        return self.root / "tmp"

    @property
    def features_dir(self) -> Path:
        return self.root / "features"

    def project_dir(self, project_id: str) -> Path:
        if not project_id.isalnum():  # ids are uuid hex; anything else never reaches the disk
            raise ValueError(f"bad project id {project_id!r}")
        return self.root / "projects" / project_id

    def images_dir(self, project_id: str) -> Path:
        return self.project_dir(project_id) / "images"

    def image_path(self, project_id: str, name: str) -> Path:
        return self.images_dir(project_id) / name

    def database_path(self, project_id: str) -> Path:
        return self.project_dir(project_id) / "database.db"

    def gcp_path(self, project_id: str) -> Path:
        """The project's ground control points, OpenDroneMap's ``gcp_list.txt`` as uploaded (UTF-8)."""
        return self.project_dir(project_id) / "gcp_list.txt"

    def plan_path(self, project_id: str) -> Path:
        """The plan of the project's last match job (geomatch.pipeline.plan.Plan), which its
        reconstruct jobs map by."""
        return self.project_dir(project_id) / "plan.json"

    def model_dir(self, project_id: str) -> Path:
        return self.project_dir(project_id) / "model"

    def pictures_dir(self, project_id: str) -> Path:
        return self.project_dir(project_id) / "pictures"

    def picture_path(self, project_id: str, name0: str, name1: str) -> Path:
        """Where the matches picture of a pair is kept (names hashed: any file name is safe)."""
        return self.pictures_dir(project_id) / picture_name(name0, name1)

    def localize_dir(self, project_id: str, job_id: str) -> Path:
        """The photos of a localize job that are not added to the project: inside the project, so
        a deletion of the project takes them too, and beside its images on the same file system
        (the upload staging renames them into place)."""
        if not job_id.isalnum():
            raise ValueError(f"bad job id {job_id!r}")
        return self.project_dir(project_id) / "localize" / job_id

    def writer_lock_path(self, project_id: str) -> Path:
        return self.project_dir(project_id) / ".writer.lock"

    def temp_file(self) -> tuple[int, Path]:
        self.tmp_dir.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(dir=self.tmp_dir, prefix="upload-")
        return fd, Path(name)

    def put_file(self, dest: Path, data: bytes) -> None:
        """``data`` at ``dest``, replacing what was there in one rename from a temporary file of
        ``tmp/`` (the same file system): a reader sees the old file or the new one, never a part.
        ``dest``'s folder must exist: a folder removed meanwhile (a project deleted under the
        write) is FileNotFoundError, and is not made again. ENOSPC leaves nothing behind."""
        fd, tmp = self.temp_file()
        try:
            with os.fdopen(fd, "wb") as f:
                self.check_space(len(data))
                f.write(data)
            os.replace(tmp, dest)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise

    @contextmanager
    def work(self, project_id: str, tag: str) -> Iterator[Path]:
        """A fresh folder inside the project, removed on exit; its owner holds an flock on its
        ``.owner.lock`` while it lives, which the kernel drops if the owner dies (SIGKILL), so
        ``remove_stale_work`` can tell a crashed attempt's folder from a live one."""
        d = self.project_dir(project_id) / f".work-{tag}-{uuid.uuid4().hex[:8]}"
        d.mkdir(parents=True)
        fd = os.open(d / ".owner.lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            yield d
        finally:
            shutil.rmtree(d, ignore_errors=True)
            os.close(fd)

    def remove_stale_work(self, project_id: str, grace_s: float = 60.0) -> list[str]:
        """Remove the project's work folders whose owner is gone (its lock is free); a folder
        without a lock file yet is left alone for ``grace_s`` (it is being created)."""
        d = self.project_dir(project_id)
        removed: list[str] = []
        for w in sorted(d.glob(".work-*")) if d.is_dir() else []:
            lock = w / ".owner.lock"
            try:
                if not lock.exists():
                    if time.time() - w.stat().st_mtime < grace_s:
                        continue
                else:
                    fd = os.open(lock, os.O_RDWR)
                    try:
                        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    except BlockingIOError:
                        continue  # a live attempt
                    finally:
                        os.close(fd)
            except FileNotFoundError:  # its owner finished meanwhile
                continue
            shutil.rmtree(w, ignore_errors=True)
            removed.append(w.name)
        return removed

    def replace_dir(self, src: Path, dst: Path) -> None:
        """Put ``src`` at ``dst``; the old ``dst`` (if any) goes away after the swap."""
        old = None
        if dst.exists():
            old = dst.with_name(f".old-{dst.name}-{uuid.uuid4().hex[:8]}")
            os.replace(dst, old)
        os.replace(src, dst)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)

    def delete_project(self, project_id: str) -> None:
        d = self.project_dir(project_id)
        if d.exists():
            trash = self.root / "tmp" / f"deleted-{project_id}-{uuid.uuid4().hex[:8]}"
            trash.parent.mkdir(parents=True, exist_ok=True)
            os.replace(d, trash)  # gone from its place at once; the slow part happens after
            shutil.rmtree(trash, ignore_errors=True)

    def check_space(self, nbytes: int) -> None:
        """Test hook, off unless GEOMATCH_TEST_FILL_LIMIT is set: pretend the storage root's file
        system holds only that many bytes, and raise ENOSPC for a write of ``nbytes`` that would
        not fit (the chaos tests' full disk without root or a small file system). Read at each
        call; costs one walk of the root when set, nothing otherwise."""
        limit = os.environ.get("GEOMATCH_TEST_FILL_LIMIT", "").strip()
        if limit and disk_usage(self.root) + nbytes > int(limit):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self.root))

    def check_writable(self) -> None:
        self.tmp_dir.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(dir=self.tmp_dir, prefix="ready-")
        try:
            os.write(fd, b"ok")
        finally:
            os.close(fd)
            os.unlink(name)


def disk_usage(root: Path) -> int:
    total = 0
    for dirpath, _dirs, files in os.walk(root):
        for f in files:
            with suppress(OSError):  # removed while walked
                total += os.lstat(os.path.join(dirpath, f)).st_size
    return total


def picture_name(name0: str, name1: str) -> str:
    return hashlib.sha256(f"{name0}\0{name1}".encode()).hexdigest()[:32] + ".png"
