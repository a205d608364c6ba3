"""``geomatch submit IMAGES --grpc``: the batch flow (``service.clients.submit``) over gRPC.

Uploads go as streams of a few images each: one stream per folder would make a late failure resend
it all, one per image would pay a round trip each. Re-sending is safe (same bytes, same image), so
a batch that meets UNAVAILABLE is sent again.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import grpc

from geomatch.options import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_UNREACHABLE

from ..grpcapi.pb import pb2
from .grpc_client import GrpcClient, ImageSource, to_dict
from .submit import JobStatus

BATCH_BYTES = 64 * 1024 * 1024
BATCH_IMAGES = 16
RETRIES = 4
CLIENT_ERRORS = {
    grpc.StatusCode.INVALID_ARGUMENT,
    grpc.StatusCode.NOT_FOUND,
    grpc.StatusCode.UNAUTHENTICATED,
    grpc.StatusCode.RESOURCE_EXHAUSTED,
    grpc.StatusCode.FAILED_PRECONDITION,
}
STATE = {v: k.removeprefix("JOB_STATE_").lower() for k, v in pb2.JobState.items()}


def batches(images: list[ImageSource]) -> Iterator[list[ImageSource]]:
    batch: list[ImageSource] = []
    size = 0
    for img in images:
        if batch and (len(batch) >= BATCH_IMAGES or size + img.size() > BATCH_BYTES):
            yield batch
            batch, size = [], 0
        batch.append(img)
        size += img.size()
    if batch:
        yield batch


class GrpcSubmitClient:
    """``service.clients.submit.SubmitClient`` over ``GrpcClient``."""

    def __init__(self, target: str, key: str, **options: Any) -> None:
        self.target = target
        self.where = f"{target} (gRPC)"
        self.client = GrpcClient(target, key, **options)

    def create_project(self, name: str) -> str:
        return str(self.client.create_project(name).id)

    def upload(
        self, project_id: str, images: list[tuple[Path, str]], on_bytes: Callable[[int], object]
    ) -> None:
        for batch in batches([ImageSource.of(path, capture) for path, capture in images]):
            self._upload(project_id, batch, on_bytes)

    def _upload(self, project_id: str, batch: list[ImageSource], on_bytes: Callable[[int], object]) -> None:
        sent = [0]

        def count(n: int) -> None:
            sent[0] += n
            on_bytes(n)

        for attempt in range(RETRIES + 1):
            sent[0] = 0
            try:
                self.client.upload(project_id, batch, on_bytes=count)
                return
            except grpc.RpcError as e:
                on_bytes(-sent[0])  # the batch starts over
                if e.code() != grpc.StatusCode.UNAVAILABLE or attempt == RETRIES:
                    raise
                time.sleep(min(30.0, 2.0**attempt))

    def match_and_reconstruct(
        self, project_id: str, pairs: str | None, method: str | None, resize: int | None, mapper: str | None
    ) -> tuple[str, str]:
        accepted = self.client.submit_matching(
            project_id, pair_spec=pairs, method=method, resize=resize, reconstruct=True, mapper=mapper
        )
        return accepted.job.id, accepted.reconstruct_job.id

    def follow_hint(self, job_id: str) -> str:
        return f"WatchJob {{job_id: {job_id}}} on {self.target}"

    def wait(self, job_id: str, on_update: Callable[[JobStatus], object]) -> JobStatus:
        def view(job: Any) -> JobStatus:
            result = to_dict(job.result) if job.state == pb2.JOB_STATE_SUCCEEDED else {}
            return JobStatus(STATE[job.state], job.progress.done, job.progress.total, job.error, result)

        return view(self.client.wait(job_id, lambda job: on_update(view(job))))

    def download(self, project_id: str, dest: Path) -> Path:
        return self.client.download_model(project_id, dest)[1]

    def failure(self, error: Exception) -> tuple[str, int] | None:
        if not isinstance(error, grpc.RpcError):
            return None
        code = error.code()
        if code == grpc.StatusCode.UNAVAILABLE:
            return f"{self.target} unreachable ({error.details()})", EXIT_UNREACHABLE
        return f"{code.name}: {error.details()}", EXIT_BAD_INPUT if code in CLIENT_ERRORS else EXIT_FAILED

    def close(self) -> None:
        self.client.close()
