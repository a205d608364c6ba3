"""The NodeODM node's HTTP surface: NodeODM's paths at the root of its own port, the API key as
``?token=``, and every error as HTTP 200 with ``{"error": "..."}``.

That last rule is NodeODM's and its clients depend on it: PyODM raises NodeResponseError for an
``error`` in a JSON answer (which WebODM shows the user) and NodeServerError for any other status,
which WebODM treats as the node failing. So a domain error of the use cases (unknown task, bad
option value, over a quota, a corrupt image, a GCP file that does not parse) is 200 + error, and so
is an unexpected failure (logged here with its traceback, answered without it). Only a path the
node does not have is a 404.

The token is an API key of the service (``geomatch keys create``): each request is authenticated
by ``Service.authenticate`` (its tenant's rate included), a request with a body before the body is
read (``limits.NodeBodyLimits``). The access log this module writes shows the query with the token
replaced by ``***``; uvicorn's own access log is off.
"""

from __future__ import annotations

import logging
import os
import re
import time
from collections.abc import Awaitable, Callable
from typing import Any

from fastapi import FastAPI, Request
from fastapi.responses import FileResponse, JSONResponse, Response
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile

from geomatch_core import errors

from ..http.errors import error_headers
from ..usecases import Service
from ..usecases.views import Upload
from .limits import NodeBodyLimits
from .options import node_options
from .tasks import NodeTasks

log = logging.getLogger("geomatch.nodeodm")
API_VERSION = "2.2.1"  # the NodeODM API version whose calls this node answers (NodeODM's docs/index.adoc)
ENGINE = "geomatch"
TOKEN = re.compile(r"(?i)(token=)[^&]*")


def redacted(query: str) -> str:
    """A query string as the node logs it: the token's value replaced."""
    return TOKEN.sub(r"\1***", query)


def error(message: str, headers: dict[str, str] | None = None) -> JSONResponse:
    text = message.encode("utf-8", "backslashreplace").decode("utf-8")
    return JSONResponse({"error": text}, status_code=200, headers=headers)


def token_of(request: Request) -> str | None:
    token = request.query_params.get("token")
    if token:
        return token
    scheme, _, value = request.headers.get("authorization", "").partition(" ")
    return value.strip() or None if scheme.lower() == "bearer" else None


async def tenant(request: Request, service: Service) -> str:
    checked = request.scope.get("state", {}).get("tenant_id")  # NodeBodyLimits, before the body
    if checked is not None:
        return str(checked)
    return await run_in_threadpool(service.authenticate, token_of(request))


async def form_fields(request: Request) -> dict[str, Any]:
    """A POST's fields, sent as a form (PyODM) or as JSON (NodeODM accepts both)."""
    if request.headers.get("content-type", "").startswith("application/json"):
        body = await request.json()
        if not isinstance(body, dict):
            raise errors.InvalidRequest("the body must be a JSON object")
        return body
    form = await request.form()
    return {k: v for k, v in form.items() if not isinstance(v, UploadFile)}


async def uploads(request: Request) -> tuple[list[Upload], dict[str, str]]:
    """The multipart field ``images`` (repeated) and the text fields beside it."""
    form = await request.form(max_files=100_000)
    files = [Upload(v.filename, v.file) for v in form.getlist("images") if isinstance(v, UploadFile)]
    fields = {k: v for k, v in form.items() if isinstance(v, str)}
    return files, fields


def _memory() -> tuple[int | None, int | None]:
    try:
        page = os.sysconf("SC_PAGE_SIZE")
        return page * os.sysconf("SC_PHYS_PAGES"), page * os.sysconf("SC_AVPHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None, None


def create_node_app(service: Service) -> FastAPI:
    app = FastAPI(title="geomatch NodeODM node", version=API_VERSION, docs_url=None, redoc_url=None)
    app.add_middleware(NodeBodyLimits, service=service)
    tasks = NodeTasks(service)

    @app.middleware("http")
    async def access_log(request: Request, call_next: Callable[[Request], Awaitable[Response]]) -> Response:
        t0 = time.perf_counter()
        response = await call_next(request)
        log.info(
            "%s %s%s %s %.0f ms",
            request.method,
            request.url.path,
            "?" + redacted(request.url.query) if request.url.query else "",
            response.status_code,
            1000 * (time.perf_counter() - t0),
        )
        return response

    @app.exception_handler(errors.DomainError)
    async def domain_error(request: Request, exc: errors.DomainError) -> JSONResponse:
        return error(exc.message, error_headers(exc))

    @app.exception_handler(Exception)
    async def unexpected(request: Request, exc: Exception) -> JSONResponse:
        log.exception("the node failed on %s %s", request.method, request.url.path)
        return error(f"the node could not answer this request ({type(exc).__name__}); see the server's log")

    @app.get("/info")
    async def info(request: Request) -> dict[str, Any]:
        await tenant(request, service)
        total, available = _memory()
        return {
            "version": API_VERSION,
            "taskQueueCount": await run_in_threadpool(tasks.queue_count),
            "maxImages": None,
            "maxParallelTasks": max(1, service.settings.embedded_threads if service.settings.embedded else 1),
            "engine": ENGINE,
            "engineVersion": _engine_version(),
            "totalMemory": total,
            "availableMemory": available,
            "cpuCores": os.cpu_count() or 1,
        }

    @app.get("/options")
    async def options(request: Request) -> list[dict[str, Any]]:
        await tenant(request, service)
        return node_options()

    @app.post("/task/new/init")
    async def new_init(request: Request) -> dict[str, str]:
        tenant_id = await tenant(request, service)
        f = await form_fields(request)
        created = _int(f.get("dateCreated"))
        return {
            "uuid": await run_in_threadpool(
                tasks.init, tenant_id, _text(f.get("name")), f.get("options"), created
            )
        }

    @app.post("/task/new/upload/{task}", response_model=None)
    async def new_upload(task: str, request: Request) -> dict[str, bool] | JSONResponse:
        tenant_id = await tenant(request, service)
        files, _ = await uploads(request)
        if not files:
            raise errors.InvalidRequest("no files: send them as the multipart field 'images'")
        try:
            await run_in_threadpool(tasks.upload, tenant_id, task, files)
        except errors.DomainError as e:
            # PyODM sends a refused file again (five times, waiting longer each time) unless told
            # that only a busy node is worth retrying
            busy = isinstance(e, errors.Overloaded | errors.Unavailable)
            return JSONResponse({"error": e.message, "noRetry": not busy}, headers=error_headers(e))
        return {"success": True}

    @app.post("/task/new/commit/{task}")
    async def new_commit(task: str, request: Request) -> dict[str, str]:
        tenant_id = await tenant(request, service)
        return {"uuid": await run_in_threadpool(tasks.commit, tenant_id, task)}

    @app.post("/task/new")
    async def new_task(request: Request) -> dict[str, str]:
        """The one-request form: init, upload and commit; what fails removes the task."""
        tenant_id = await tenant(request, service)
        files, f = await uploads(request)
        created = _int(f.get("dateCreated"))
        uuid = await run_in_threadpool(tasks.init, tenant_id, _text(f.get("name")), f.get("options"), created)
        try:
            await run_in_threadpool(tasks.upload, tenant_id, uuid, files)
        except BaseException:
            await run_in_threadpool(tasks.remove, tenant_id, uuid)
            raise
        return {"uuid": await run_in_threadpool(tasks.commit, tenant_id, uuid)}

    @app.get("/task/list")
    async def task_list(request: Request) -> list[dict[str, str]]:
        tenant_id = await tenant(request, service)
        return await run_in_threadpool(tasks.list, tenant_id)

    @app.get("/task/{task}/info")
    async def task_info(task: str, request: Request) -> dict[str, Any]:
        tenant_id = await tenant(request, service)
        with_output = _int(request.query_params.get("with_output"))
        return await run_in_threadpool(tasks.info, tenant_id, task, with_output)

    @app.get("/task/{task}/output")
    async def task_output(task: str, request: Request) -> list[str]:
        tenant_id = await tenant(request, service)
        return await run_in_threadpool(
            tasks.output, tenant_id, task, _int(request.query_params.get("line")) or 0
        )

    @app.get("/task/{task}/download/{asset}")
    async def download(task: str, asset: str, request: Request) -> FileResponse:
        tenant_id = await tenant(request, service)
        if asset != "all.zip":
            raise errors.NotFound(f"asset {asset[:80]!r} not found: this node offers all.zip")
        path = await run_in_threadpool(tasks.all_zip, tenant_id, task)
        # Starlette answers Range requests (206, Accept-Ranges: bytes): PyODM downloads in chunks
        return FileResponse(path, media_type="application/zip", filename=f"{task}-all.zip")

    @app.post("/task/cancel")
    async def cancel(request: Request) -> dict[str, bool]:
        tenant_id = await tenant(request, service)
        await run_in_threadpool(tasks.cancel, tenant_id, _uuid(await form_fields(request)))
        return {"success": True}

    @app.post("/task/remove")
    async def remove(request: Request) -> dict[str, bool]:
        tenant_id = await tenant(request, service)
        await run_in_threadpool(tasks.remove, tenant_id, _uuid(await form_fields(request)))
        return {"success": True}

    @app.post("/task/restart")
    async def restart(request: Request) -> dict[str, bool]:
        tenant_id = await tenant(request, service)
        f = await form_fields(request)
        opts = f.get("options")
        if opts is not None and not isinstance(opts, str):  # a JSON body may hold the list itself
            import json

            opts = json.dumps(opts)
        await run_in_threadpool(tasks.restart, tenant_id, _uuid(f), opts)
        return {"success": True}

    return app


def _uuid(fields: dict[str, Any]) -> str:
    value = fields.get("uuid")
    if not isinstance(value, str) or not value:
        raise errors.InvalidRequest("uuid missing: send the task's uuid as the field 'uuid'")
    return value


def _text(value: Any) -> str | None:
    return value if isinstance(value, str) and value.strip() and value != "None" else None


def _int(value: Any) -> int | None:
    if value is None or value == "":
        return None
    try:
        return int(str(value).strip())
    except ValueError:
        raise errors.InvalidRequest(f"{str(value)[:40]!r} is not an integer") from None


def _engine_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("geomatch")[:32]
    except PackageNotFoundError:
        return "0"
