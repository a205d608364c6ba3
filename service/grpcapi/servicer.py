"""``geomatch.v1.Matching``: each method translates its request, calls the use case the REST route
for the same operation calls, and translates the answer. Nothing here decides anything the REST API
would decide differently; what is gRPC's own is framing (``framing.py``), streaming responses and
deadlines.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import grpc

from geomatch_core.errors import InvalidRequest, Unavailable

from ..paging import offset_of
from ..usecases import Service
from ..usecases.localize import localizations
from ..usecases.views import Upload
from . import convert
from .framing import MAX_CHUNK, Messages, images
from .limits import STREAMS, IdleStreams, StreamSlots
from .pb import pb2, pb2_grpc
from .status import rpc, rpc_stream

WATCH_POLL_S = 0.5  # how often WatchJob reads the job (the SSE stream's interval)
LIVENESS_S = 1.0  # how often a quiet WatchJob checks that its client is still there
MATCH_PAIR_TIMEOUT_S = 600.0  # MatchPair without a deadline waits this long for a worker
DEADLINE_MARGIN_S = 0.25  # left for the answer to travel back before the client's deadline


class MatchingServicer(pb2_grpc.MatchingServicer):
    """Streaming methods take one of ``streams`` while they last, and request streams are watched
    for silence (``limits``): open streams cannot starve health checks and unary calls."""

    def __init__(self, service: Service) -> None:
        self.service = service
        self.streams = StreamSlots(STREAMS, service.settings.grpc_tenant_streams)
        self.idle = IdleStreams(service.settings.grpc_stream_idle_s)

    # -- projects ----------------------------------------------------------------------------
    @rpc
    def CreateProject(
        self, request: pb2.CreateProjectRequest, context: grpc.ServicerContext, tenant_id: str
    ) -> pb2.Project:
        config = convert.optional_fields(request.config, convert.CONFIG_FIELDS)
        return convert.project(self.service.projects.create_project(tenant_id, request.name, config))

    @rpc
    def GetProject(
        self, request: pb2.GetProjectRequest, context: grpc.ServicerContext, tenant_id: str
    ) -> pb2.Project:
        return convert.project(self.service.projects.get_project(tenant_id, request.project_id))

    @rpc
    def ListProjects(
        self, request: pb2.ListProjectsRequest, context: grpc.ServicerContext, tenant_id: str
    ) -> pb2.ListProjectsResponse:
        page = self.service.projects.list_projects(
            tenant_id, offset_of(request.page_token), request.page_size
        )
        return pb2.ListProjectsResponse(
            projects=[convert.project(p) for p in page.items], next_page_token=token_of(page.next_offset)
        )

    @rpc
    def DeleteProject(
        self, request: pb2.DeleteProjectRequest, context: grpc.ServicerContext, tenant_id: str
    ) -> pb2.DeleteProjectResponse:
        self.service.projects.delete_project(tenant_id, request.project_id)
        return pb2.DeleteProjectResponse()

    # -- images ------------------------------------------------------------------------------
    @rpc
    def UploadImages(
        self,
        request_iterator: Iterator[pb2.UploadImagesRequest],
        context: grpc.ServicerContext,
        tenant_id: str,
    ) -> pb2.UploadImagesResponse:
        with self.streams.open(tenant_id), self.idle.watch(context) as heard:
            messages = Messages(request_iterator, context.is_active, heard)
            first = _first_message(messages, "UploadImages")
            settings = self.service.settings
            uploads = images(
                messages, settings.max_upload_bytes, first.project_id, settings.max_request_bytes
            )
            views = self.service.images.upload_images(tenant_id, first.project_id, uploads)
        return pb2.UploadImagesResponse(images=[convert.image(v) for v in views])

    @rpc
    def ListImages(
        self, request: pb2.ListImagesRequest, context: grpc.ServicerContext, tenant_id: str
    ) -> pb2.ListImagesResponse:
        page = self.service.images.list_images(
            tenant_id, request.project_id, offset_of(request.page_token), request.page_size
        )
        return pb2.ListImagesResponse(
            images=[convert.image(v) for v in page.items], next_page_token=token_of(page.next_offset)
        )

    # -- ground control points ----------------------------------------------------------------
    @rpc
    def PutGcp(
        self, request: pb2.PutGcpRequest, context: grpc.ServicerContext, tenant_id: str
    ) -> pb2.GcpSummary:
        data = request.text.encode("utf-8")
        return convert.gcp(self.service.gcp.put_gcp(tenant_id, request.project_id, data))

    @rpc
    def GetGcp(
        self, request: pb2.GetGcpRequest, context: grpc.ServicerContext, tenant_id: str
    ) -> pb2.GcpSummary:
        return convert.gcp(self.service.gcp.get_gcp(tenant_id, request.project_id))

    @rpc
    def DeleteGcp(
        self, request: pb2.DeleteGcpRequest, context: grpc.ServicerContext, tenant_id: str
    ) -> pb2.DeleteGcpResponse:
        self.service.gcp.delete_gcp(tenant_id, request.project_id)
        return pb2.DeleteGcpResponse()

    # -- jobs --------------------------------------------------------------------------------
    @rpc
    def SubmitMatching(
        self, request: pb2.SubmitMatchingRequest, context: grpc.ServicerContext, tenant_id: str
    ) -> pb2.SubmitMatchingResponse:
        job, follower = self.service.jobs.start_match(
            tenant_id, request.project_id, convert.match_request(request)
        )
        out = pb2.SubmitMatchingResponse(job=convert.job(job))
        if follower is not None:
            out.reconstruct_job.CopyFrom(convert.job(follower))
        return out

    @rpc
    def SubmitReconstruction(
        self, request: pb2.SubmitReconstructionRequest, context: grpc.ServicerContext, tenant_id: str
    ) -> pb2.Job:
        mapper = request.mapper if request.HasField("mapper") else None
        checkpoints = convert.checkpoints(request)
        mapping = convert.optional_fields(request, convert.MAPPING_FIELDS)
        return convert.job(
            self.service.jobs.start_reconstruct(tenant_id, request.project_id, mapper, checkpoints, mapping)
        )

    @rpc
    def ListJobs(
        self, request: pb2.ListJobsRequest, context: grpc.ServicerContext, tenant_id: str
    ) -> pb2.ListJobsResponse:
        state = convert.JOB_STATE_NAMES.get(request.state) if request.state else None
        if request.state and state is None:
            raise InvalidRequest(f"unknown job state {request.state}")
        page = self.service.jobs.list_jobs(
            tenant_id, request.project_id, offset_of(request.page_token), request.page_size, state
        )
        return pb2.ListJobsResponse(
            jobs=[convert.job(j) for j in page.items], next_page_token=token_of(page.next_offset)
        )

    @rpc
    def GetJob(self, request: pb2.GetJobRequest, context: grpc.ServicerContext, tenant_id: str) -> pb2.Job:
        return convert.job(self.service.jobs.get_job(tenant_id, request.job_id))

    @rpc_stream
    def WatchJob(
        self, request: pb2.WatchJobRequest, context: grpc.ServicerContext, tenant_id: str
    ) -> Iterator[pb2.JobEvent]:
        # watch_job yields None when nothing changed for LIVENESS_S: the moment to notice a client
        # that went away (or whose deadline passed) and stop polling the store for it
        with self.streams.open(tenant_id):
            for job in self.service.jobs.watch_job(
                tenant_id, request.job_id, interval_s=WATCH_POLL_S, heartbeat_s=LIVENESS_S
            ):
                if not context.is_active():
                    return
                if job is not None:
                    yield pb2.JobEvent(job=convert.job(job))

    @rpc
    def CancelJob(
        self, request: pb2.CancelJobRequest, context: grpc.ServicerContext, tenant_id: str
    ) -> pb2.Job:
        return convert.job(self.service.jobs.cancel_job(tenant_id, request.job_id))

    # -- models ------------------------------------------------------------------------------
    @rpc_stream
    def GetModel(
        self, request: pb2.GetModelRequest, context: grpc.ServicerContext, tenant_id: str
    ) -> Iterator[pb2.GetModelResponse]:
        fmt = convert.MODEL_FORMATS.get(request.format)
        if fmt is None:
            raise InvalidRequest(f"unknown model format {request.format}")
        path = self.service.outputs.model_file(tenant_id, request.project_id, fmt)
        # open first: a reconstruction that swaps the model folder meanwhile does not tear what
        # this stream sends (the open file outlives the swap)
        with self.streams.open(tenant_id), path.open("rb") as f:
            summary = _summary(f, fmt, path)
            digest, size = _digest(f)
            yield pb2.GetModelResponse(
                info=pb2.ModelInfo(
                    summary=convert.model_summary(summary),
                    format=request.format or pb2.MODEL_FORMAT_ZIP,
                    file_name=f"{request.project_id}-{path.name}",
                    size=size,
                    sha256=digest,
                )
            )
            while chunk := f.read(MAX_CHUNK):
                if not context.is_active():
                    return
                yield pb2.GetModelResponse(chunk=chunk)

    # -- pairwise matching -------------------------------------------------------------------
    @rpc
    def MatchPair(
        self, request_iterator: Iterator[pb2.MatchPairRequest], context: grpc.ServicerContext, tenant_id: str
    ) -> pb2.MatchPairResponse:
        with self.streams.open(tenant_id), self.idle.watch(context) as heard:
            return self._match_pair(Messages(request_iterator, context.is_active, heard), context, tenant_id)

    def _match_pair(
        self, messages: Messages, context: grpc.ServicerContext, tenant_id: str
    ) -> pb2.MatchPairResponse:
        options: dict[str, Any] = {}
        first = messages.next()
        if first is not None and first.WhichOneof("part") == "options":
            options = convert.optional_fields(first.options, convert.PAIR_FIELDS)
        elif first is not None:
            messages.push_back(first)
        uploads = (
            up if up.name else Upload(f"image{i}", up.stream, up.capture)
            for i, up in enumerate(images(messages, self.service.settings.max_upload_bytes))
        )
        remaining = context.time_remaining()
        timeout = MATCH_PAIR_TIMEOUT_S if remaining is None else max(0.1, remaining - DEADLINE_MARGIN_S)
        try:
            matches = self.service.pairtools.match_two(tenant_id, uploads, options, timeout_s=timeout)
        except Unavailable:
            left = context.time_remaining()
            if left is not None and left <= 2 * DEADLINE_MARGIN_S:  # we stopped waiting for the deadline
                context.abort(
                    grpc.StatusCode.DEADLINE_EXCEEDED, "the pair was not matched within the deadline"
                )
            raise
        return convert.pair_matches(matches)

    # -- localization ------------------------------------------------------------------------
    @rpc
    def Localize(
        self, request_iterator: Iterator[pb2.LocalizeRequest], context: grpc.ServicerContext, tenant_id: str
    ) -> pb2.LocalizeResponse:
        with self.streams.open(tenant_id), self.idle.watch(context) as heard:
            messages = Messages(request_iterator, context.is_active, heard)
            first = _first_message(messages, "Localize", options="options")
            add, wait = False, None
            if first.WhichOneof("part") == "options":
                add = first.options.add
                wait = first.options.wait_s if first.options.HasField("wait_s") else None
            settings = self.service.settings
            photos = images(messages, settings.max_upload_bytes, first.project_id, settings.max_request_bytes)
            # the answer must reach the client before its deadline: the job goes on regardless
            remaining = context.time_remaining()
            if remaining is not None:
                left = max(0.0, remaining - 2 * DEADLINE_MARGIN_S)
                wait = left if wait is None else min(wait, left)
            job = self.service.localize.localize(tenant_id, first.project_id, photos, add=add, wait_s=wait)
        answers = localizations(job) or []
        return pb2.LocalizeResponse(
            job=convert.job(job), localizations=[convert.localization(a) for a in answers]
        )


def _first_message(messages: Messages, method: str, options: str | None = None) -> Any:
    """The first message of an upload stream, which names the project. A file part it carries
    is put back for the file reader; a message that only names the project, or carries the
    call's ``options`` part, is the caller's."""
    first = messages.next()
    if first is None or not first.project_id:
        raise InvalidRequest(f"the first message of {method} must carry project_id")
    part = first.WhichOneof("part")
    if part is not None and part != options:
        messages.push_back(first)
    return first


def token_of(next_offset: int | None) -> str:
    return "" if next_offset is None else str(next_offset)


def _summary(f: IO[bytes], fmt: str, path: Path) -> dict[str, Any]:
    """The summary that belongs to the bytes sent: from inside the zip, or the file beside."""
    try:
        if path.suffix == ".zip":  # the model's zip, or an export's (geomatch.export.export_zip)
            with zipfile.ZipFile(f) as z:
                return dict(json.loads(z.read("summary.json")))
        if fmt == "json":
            return dict(json.loads(f.read()))
        return dict(json.loads((path.parent / "summary.json").read_text()))
    except (OSError, KeyError, ValueError, zipfile.BadZipFile):
        return {}
    finally:
        f.seek(0)


def _digest(f: IO[bytes]) -> tuple[str, int]:
    h, size = hashlib.sha256(), 0
    while chunk := f.read(MAX_CHUNK):
        h.update(chunk)
        size += len(chunk)
    f.seek(0)
    return h.hexdigest(), size
