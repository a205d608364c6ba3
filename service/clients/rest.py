"""A small HTTP client of the API (httpx), used by ``geomatch submit``.

Uploads are idempotent on the server (same bytes, same image), so every request here is safe to
repeat: connection errors and 502/503/504 are retried with backoff, which is what a batch job
on a flaky network needs.
"""

from __future__ import annotations

import io
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

import httpx

TERMINAL = ("succeeded", "failed", "cancelled")


class ApiError(Exception):
    def __init__(self, status: int, detail: str) -> None:
        super().__init__(f"HTTP {status}: {detail}")
        self.status = status
        self.detail = detail


class _Counting(io.RawIOBase):
    """A file whose reads report progress (httpx streams multipart files by reading them)."""

    def __init__(self, f: BinaryIO, on_bytes: Callable[[int], object]) -> None:
        self._f = f
        self._on_bytes = on_bytes

    def readable(self) -> bool:
        return True

    def fileno(self) -> int:  # lets httpx size the body
        return self._f.fileno()

    def read(self, size: int = -1) -> bytes:
        data = self._f.read(size)
        if data:
            self._on_bytes(len(data))
        return data


class Client:
    def __init__(self, server: str, key: str, timeout: float = 120.0, retries: int = 4) -> None:
        self.http = httpx.Client(
            base_url=server.rstrip("/"), headers={"Authorization": f"Bearer {key}"}, timeout=timeout
        )
        self.retries = retries

    def close(self) -> None:
        self.http.close()

    def request(
        self, method: str, path: str, rewind: Callable[[], object] | None = None, **kwargs: Any
    ) -> httpx.Response:
        """``rewind`` puts a streamed body back to its start before a retry."""
        for attempt in range(self.retries + 1):
            if attempt:
                time.sleep(min(30.0, 2.0 ** (attempt - 1)))
                if rewind is not None:
                    rewind()
            try:
                r = self.http.request(method, path, **kwargs)
            except httpx.TransportError:
                if attempt == self.retries:
                    raise
                continue
            if r.status_code in (502, 503, 504) and attempt < self.retries:
                continue
            break
        if r.status_code >= 400:
            try:
                detail = r.json().get("detail", r.text)
            except ValueError:
                detail = r.text
            raise ApiError(r.status_code, str(detail))
        return r

    def create_project(self, name: str, config: dict[str, Any] | None = None) -> dict[str, Any]:
        body: dict[str, Any] = {"name": name}
        if config:
            body["config"] = config
        project: dict[str, Any] = self.request("POST", "/v1/projects", json=body).json()
        return project

    def upload(
        self,
        project_id: str,
        path: Path,
        capture: str = "auto",
        on_bytes: Callable[[int], object] = lambda n: None,
    ) -> dict[str, Any]:
        with path.open("rb") as f:
            sent = [0]

            def count(n: int) -> None:
                sent[0] += n
                on_bytes(n)

            def rewind() -> None:  # a retried upload starts over: undo the progress it made
                f.seek(0)
                on_bytes(-sent[0])
                sent[0] = 0

            body = _Counting(f, count)
            r = self.request(
                "POST",
                f"/v1/projects/{project_id}/images",
                files=[("files", (path.name, body, "application/octet-stream"))],
                data={"capture": capture},
                rewind=rewind,
            )
        image: dict[str, Any] = r.json()["images"][0]
        return image

    def match(self, project_id: str, **options: Any) -> dict[str, Any]:
        body = {k: v for k, v in options.items() if v is not None}
        accepted: dict[str, Any] = self.request("POST", f"/v1/projects/{project_id}/match", json=body).json()
        return accepted

    def job(self, job_id: str) -> dict[str, Any]:
        job: dict[str, Any] = self.request("GET", f"/v1/jobs/{job_id}").json()
        return job

    def wait(
        self, job_id: str, on_update: Callable[[dict[str, Any]], object] = lambda j: None, poll_s: float = 1.0
    ) -> dict[str, Any]:
        while True:
            job = self.job(job_id)
            on_update(job)
            if job["state"] in TERMINAL:
                return job
            time.sleep(poll_s)

    def download(self, project_id: str, dest: Path, fmt: str = "zip") -> Path:
        dest.parent.mkdir(parents=True, exist_ok=True)
        tmp = dest.with_name(dest.name + ".part")
        with self.http.stream("GET", f"/v1/projects/{project_id}/model", params={"format": fmt}) as r:
            if r.status_code >= 400:
                r.read()
                raise ApiError(r.status_code, r.text)
            with tmp.open("wb") as f:
                for chunk in r.iter_bytes():
                    f.write(chunk)
        tmp.replace(dest)
        return dest
