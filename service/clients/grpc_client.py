"""A small Python client of ``geomatch.v1.Matching``, used by ``geomatch submit --grpc`` and the tests.

Methods return the protobuf messages (``pb2``) as they come, so every field of the proto is there;
errors are ``grpc.RpcError`` with ``code()`` and ``details()``. What the client adds is the
framing of uploads (header, then chunks of at most 1 MiB), reassembly and verification of model
downloads, and numpy arrays for MatchPair.

    with GrpcClient("127.0.0.1:50051", key) as c:
        p = c.create_project("campus", resize=640)
        c.upload(p.id, [ImageSource.of(a, "aerial") for a in drone] + [ImageSource.of(g) for g in ground])
        r = c.submit_matching(p.id, pair_spec="exhaustive", reconstruct=True)
        for job in c.watch_job(r.reconstruct_job.id): ...
        info, path = c.download_model(p.id, Path("model.zip"))
        answer = c.localize(p.id, [ImageSource.of("new.jpg", "ground")])  # .localizations, .job
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import grpc
import numpy as np
from google.protobuf.json_format import MessageToDict

from geomatch.export.formats import FORMATS

from ..grpcapi.pb import pb2, pb2_grpc

CHUNK = 1 << 20  # the server's limit on a chunk
CAPTURE = {"auto": pb2.CAPTURE_AUTO, "aerial": pb2.CAPTURE_AERIAL, "ground": pb2.CAPTURE_GROUND}
# the model's formats by the names REST takes: the service's own files and the export table's rows
FORMAT = {"zip": pb2.MODEL_FORMAT_ZIP, "json": pb2.MODEL_FORMAT_JSON} | {
    f.name: f.proto for f in FORMATS.values()
}
TERMINAL = (pb2.JOB_STATE_SUCCEEDED, pb2.JOB_STATE_FAILED, pb2.JOB_STATE_CANCELLED)
CHANNEL_OPTIONS = [
    ("grpc.max_receive_message_length", 64 * 1024 * 1024),  # MatchPair answers can be large
    ("grpc.keepalive_time_ms", 30_000),
    ("grpc.keepalive_permit_without_calls", 1),
]


@dataclass(frozen=True)
class ImageSource:
    """An image to send: a file, or bytes in memory, with its name and capture."""

    name: str
    path: Path | None = None
    data: bytes | None = None
    capture: str = "auto"

    @classmethod
    def of(cls, path: str | Path, capture: str = "auto", name: str | None = None) -> ImageSource:
        p = Path(path)
        return cls(name or p.name, path=p, capture=capture)

    def size(self) -> int:
        return len(self.data) if self.data is not None else Path(self.path or "").stat().st_size

    def chunks(self, chunk_size: int = CHUNK) -> Iterator[bytes]:
        if self.data is not None:
            for i in range(0, len(self.data), chunk_size):
                yield self.data[i : i + chunk_size]
            return
        assert self.path is not None
        with self.path.open("rb") as f:
            yield from _read_chunks(f, chunk_size)


def _read_chunks(f: BinaryIO, chunk_size: int) -> Iterator[bytes]:
    while chunk := f.read(chunk_size):
        yield chunk


def image_messages(
    make: Callable[..., Any],
    images: Iterable[ImageSource],
    on_bytes: Callable[[int], object] | None = None,
    chunk_size: int = CHUNK,
    **first: Any,
) -> Iterator[Any]:
    """The framing of UploadImages and MatchPair: ``make(image=header)``, then ``make(chunk=...)``
    per chunk; ``first`` (e.g. ``project_id``) goes into the first message only."""
    for img in images:
        header = pb2.ImageHeader(name=img.name, capture=CAPTURE[img.capture], size=img.size())
        yield make(image=header, **first)
        first = {}
        for chunk in img.chunks(chunk_size):
            yield make(chunk=chunk)
            if on_bytes is not None:
                on_bytes(len(chunk))


@dataclass(frozen=True)
class PairResult:
    """MatchPair's answer as arrays: (N, 2) keypoints in original pixels, (N,) scores, F (3, 3)."""

    keypoints0: np.ndarray
    keypoints1: np.ndarray
    scores: np.ndarray
    F: np.ndarray
    sizes: tuple[tuple[int, int], tuple[int, int]]
    method: str
    tiled: bool
    timings: dict[str, float] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.scores.shape[0])

    @classmethod
    def from_message(cls, m: Any) -> PairResult:
        return cls(
            keypoints0=np.asarray(m.keypoints0, np.float32).reshape(-1, 2),
            keypoints1=np.asarray(m.keypoints1, np.float32).reshape(-1, 2),
            scores=np.asarray(m.scores, np.float32),
            F=np.asarray(m.fundamental, np.float64).reshape(3, 3),
            sizes=((m.size0.width, m.size0.height), (m.size1.width, m.size1.height)),
            method=m.method,
            tiled=m.tiled,
            timings=dict(m.timings),
        )


class DownloadError(Exception):
    pass


class GrpcClient:
    """``timeout`` is the deadline of each unary call; streams take their own (None: no deadline)."""

    def __init__(self, target: str, key: str | None, timeout: float = 120.0) -> None:
        self.channel = grpc.insecure_channel(target, options=CHANNEL_OPTIONS)
        self.stub = pb2_grpc.MatchingStub(self.channel)
        self.metadata = (("authorization", f"Bearer {key}"),) if key else ()
        self.timeout = timeout

    def close(self) -> None:
        self.channel.close()

    def __enter__(self) -> GrpcClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _call(self, name: str, request: Any, timeout: float | None = None) -> Any:
        method = getattr(self.stub, name)
        return method(request, timeout=timeout or self.timeout, metadata=self.metadata)

    # -- projects ----------------------------------------------------------------------------
    def create_project(self, name: str, **config: Any) -> Any:
        return self._call(
            "CreateProject", pb2.CreateProjectRequest(name=name, config=pb2.ProjectConfig(**config))
        )

    def get_project(self, project_id: str) -> Any:
        return self._call("GetProject", pb2.GetProjectRequest(project_id=project_id))

    def list_projects(self) -> list[Any]:
        """Every project of the key's tenant, page after page."""
        out: list[Any] = []
        token = ""
        while True:
            r = self._call("ListProjects", pb2.ListProjectsRequest(page_token=token))
            out += r.projects
            if not (token := r.next_page_token):
                return out

    def delete_project(self, project_id: str) -> None:
        self._call("DeleteProject", pb2.DeleteProjectRequest(project_id=project_id))

    # -- images ------------------------------------------------------------------------------
    def upload(
        self,
        project_id: str,
        images: Iterable[ImageSource],
        on_bytes: Callable[[int], object] | None = None,
        timeout: float | None = None,
        chunk_size: int = CHUNK,
    ) -> list[Any]:
        """One UploadImages stream: all the images are stored, or none."""
        requests = image_messages(
            pb2.UploadImagesRequest, images, on_bytes, chunk_size, project_id=project_id
        )
        reply = self.stub.UploadImages(requests, timeout=timeout, metadata=self.metadata)
        return list(reply.images)

    def list_images(self, project_id: str) -> list[Any]:
        """Every image of the project, page after page."""
        out: list[Any] = []
        token = ""
        while True:
            r = self._call("ListImages", pb2.ListImagesRequest(project_id=project_id, page_token=token))
            out += r.images
            if not (token := r.next_page_token):
                return out

    # -- ground control points ----------------------------------------------------------------
    def put_gcp(self, project_id: str, text: str) -> Any:
        """Store the project's gcp_list.txt; the GcpSummary of it."""
        return self._call("PutGcp", pb2.PutGcpRequest(project_id=project_id, text=text))

    def get_gcp(self, project_id: str) -> Any:
        return self._call("GetGcp", pb2.GetGcpRequest(project_id=project_id))

    def delete_gcp(self, project_id: str) -> None:
        self._call("DeleteGcp", pb2.DeleteGcpRequest(project_id=project_id))

    # -- jobs --------------------------------------------------------------------------------
    def submit_matching(
        self,
        project_id: str,
        pair_spec: str | None = None,
        pair_list: Iterable[tuple[str, str]] | None = None,
        reconstruct: bool = False,
        **options: Any,
    ) -> Any:
        """Options: method, resize, tiling, snap_radius, camera, and for the reconstruct job mapper,
        min_pose_inliers, ortho, ortho_gsd (None: the default)."""
        req = pb2.SubmitMatchingRequest(
            project_id=project_id,
            reconstruct=reconstruct,
            **{k: v for k, v in options.items() if v is not None},
        )
        if pair_spec is not None:
            req.pair_spec = pair_spec
        if pair_list is not None:
            req.pair_list.CopyFrom(
                pb2.PairList(pairs=[pb2.ImagePair(name0=a, name1=b) for a, b in pair_list])
            )
        return self._call("SubmitMatching", req)

    def submit_reconstruction(
        self,
        project_id: str,
        mapper: str | None = None,
        checkpoints: Iterable[str] | int | None = None,
        **options: Any,
    ) -> Any:
        """``checkpoints``: GCP names held out of the fit, or how many (None: none). Options:
        min_pose_inliers, ortho, ortho_gsd (None: the project's)."""
        req = pb2.SubmitReconstructionRequest(
            project_id=project_id, **{k: v for k, v in options.items() if v is not None}
        )
        if mapper is not None:
            req.mapper = mapper
        if isinstance(checkpoints, int):
            req.checkpoint_count = checkpoints
        elif checkpoints is not None:
            req.checkpoint_names.CopyFrom(pb2.CheckpointNames(names=list(checkpoints)))
        return self._call("SubmitReconstruction", req)

    def list_jobs(self, project_id: str, state: str | None = None) -> list[Any]:
        """Every job of the project, newest first, page after page (of one state when given)."""
        out: list[Any] = []
        token = ""
        req_state = f"JOB_STATE_{state.upper()}" if state else "JOB_STATE_UNSPECIFIED"  # the enum by name
        while True:
            r = self._call(
                "ListJobs", pb2.ListJobsRequest(project_id=project_id, page_token=token, state=req_state)
            )
            out += r.jobs
            if not (token := r.next_page_token):
                return out

    def get_job(self, job_id: str) -> Any:
        return self._call("GetJob", pb2.GetJobRequest(job_id=job_id))

    def cancel_job(self, job_id: str) -> Any:
        return self._call("CancelJob", pb2.CancelJobRequest(job_id=job_id))

    def watch_job(self, job_id: str, timeout: float | None = None) -> Iterator[Any]:
        """The job at each change, ending with its final state."""
        events = self.stub.WatchJob(
            pb2.WatchJobRequest(job_id=job_id), timeout=timeout, metadata=self.metadata
        )
        for event in events:
            yield event.job

    def wait(self, job_id: str, on_update: Callable[[Any], object] = lambda j: None) -> Any:
        """Follow a job to its end; a dropped stream (server restart) is opened again."""
        while True:
            job = None
            try:
                for job in self.watch_job(job_id):
                    on_update(job)
            except grpc.RpcError as e:
                if e.code() != grpc.StatusCode.UNAVAILABLE:
                    raise
            if job is not None and job.state in TERMINAL:
                return job

    # -- models ------------------------------------------------------------------------------
    def download_model(
        self, project_id: str, dest: Path, fmt: str = "zip", timeout: float | None = None
    ) -> tuple[Any, Path]:
        """The model file at ``dest`` (written whole or not at all, size and sha256 checked) and
        its ModelInfo (``info.summary`` has the statistics)."""
        stream = self.stub.GetModel(
            pb2.GetModelRequest(project_id=project_id, format=pb2.ModelFormat.Name(FORMAT[fmt])),
            timeout=timeout,
            metadata=self.metadata,
        )
        dest.parent.mkdir(parents=True, exist_ok=True)
        tmp = dest.with_name(dest.name + ".part")
        info, h, size = None, hashlib.sha256(), 0
        try:
            with tmp.open("wb") as f:
                for msg in stream:
                    if msg.WhichOneof("part") == "info":
                        info = msg.info
                    else:
                        h.update(msg.chunk)
                        size += len(msg.chunk)
                        f.write(msg.chunk)
            if info is None or size != info.size or h.hexdigest() != info.sha256:
                raise DownloadError(
                    f"model download incomplete or corrupt: {size} bytes"
                    + (
                        f" of {info.size}, sha256 {'ok' if h.hexdigest() == info.sha256 else 'differs'}"
                        if info
                        else ""
                    )
                )
            tmp.replace(dest)
        finally:
            tmp.unlink(missing_ok=True)
        return info, dest

    # -- pairwise matching -------------------------------------------------------------------
    def match_pair(
        self,
        image0: ImageSource,
        image1: ImageSource,
        method: str | None = None,
        resize: int | None = None,
        tiling: str | None = None,
        timeout: float | None = 600.0,
    ) -> PairResult:
        opts: dict[str, Any] = {
            k: v for k, v in (("method", method), ("resize", resize), ("tiling", tiling)) if v is not None
        }

        def requests() -> Iterator[Any]:
            yield pb2.MatchPairRequest(options=pb2.MatchPairOptions(**opts))
            yield from image_messages(pb2.MatchPairRequest, (image0, image1))

        reply = self.stub.MatchPair(requests(), timeout=timeout, metadata=self.metadata)
        return PairResult.from_message(reply)

    # -- localization ------------------------------------------------------------------------
    def localize(
        self,
        project_id: str,
        photos: Iterable[ImageSource],
        add: bool = False,
        wait_s: float | None = None,
        timeout: float | None = 600.0,
    ) -> Any:
        """One Localize stream: the LocalizeResponse (its ``job``, and one ``localizations`` entry
        per photo when the job ended within the wait). A job still running is followed with
        :meth:`wait`; its ``result`` then holds the answers (:func:`to_dict`)."""
        options = pb2.LocalizeOptions(add=add)
        if wait_s is not None:
            options.wait_s = wait_s

        def requests() -> Iterator[Any]:
            yield pb2.LocalizeRequest(project_id=project_id, options=options)
            yield from image_messages(pb2.LocalizeRequest, photos)

        return self.stub.Localize(requests(), timeout=timeout, metadata=self.metadata)


def to_dict(message: Any) -> dict[str, Any]:
    """A message (a Job's ``result``, a summary's ``full``) as plain JSON values."""
    return MessageToDict(message, preserving_proto_field_name=True)
