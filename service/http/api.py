"""The FastAPI application: routes, health, metrics, and the one place where domain errors
become HTTP statuses."""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, PlainTextResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from pydantic import BaseModel
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import compile_path

from geomatch_core import errors

from ..usecases import Service
from . import console
from .bodylimits import BodyLimits
from .errors import error_headers, status_of
from .headers import SecurityHeaders
from .metrics import Metrics
from .routes import build_router

log = logging.getLogger("geomatch.service")


def printable(text: str) -> str:
    """``text`` as UTF-8 can carry it: a lone surrogate a client sent (JSON allows ``\\ud800``)
    and a message echoes would otherwise fail the response's encoding, a 500 for a 4xx."""
    return text.encode("utf-8", "backslashreplace").decode("utf-8")


class Readiness(BaseModel):
    ready: bool
    checks: dict[str, str]


def create_app(service: Service) -> FastAPI:
    app = FastAPI(
        title="geomatch",
        version="0.1.0",
        description="Geometry-aware matching for Structure-from-Motion: projects, uploads, match and "
        "reconstruct jobs, COLMAP databases and models. Authenticate with `Authorization: Bearer KEY`.",
    )
    app.state.service = service
    metrics = Metrics(service.store)
    app.middleware("http")(metrics.middleware)
    app.add_middleware(BodyLimits, service=service)  # outside the app: before any body is read
    app.add_middleware(SecurityHeaders)

    def count_upload(n: int, size: int) -> None:
        metrics.uploaded_images.inc(n)
        metrics.uploaded_bytes.inc(size)

    service.ctx.on_upload = count_upload
    app.include_router(build_router())
    console.mount(app)

    @app.exception_handler(errors.DomainError)
    async def domain_error(request: Request, exc: errors.DomainError) -> JSONResponse:
        return JSONResponse(
            {"detail": printable(exc.message)}, status_code=status_of(exc), headers=error_headers(exc)
        )

    @app.exception_handler(RequestValidationError)
    async def invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        problems: list[Any] = list(exc.errors())
        if any(p.get("type") == "json_invalid" for p in problems):
            ctx = next(p for p in problems if p.get("type") == "json_invalid").get("ctx", {})
            return JSONResponse(
                {"detail": printable(f"malformed JSON body: {ctx.get('error', 'cannot be parsed')}")},
                status_code=400,
            )
        shown = [
            {
                "loc": [printable(x) if isinstance(x, str) else x for x in p.get("loc", ())],
                "msg": printable(str(p.get("msg"))),
                "type": p.get("type"),
            }
            for p in problems
        ]
        text = "; ".join(
            f"{'.'.join(str(x) for x in p['loc'] if x != 'body') or 'body'}: {p['msg']}" for p in shown
        )
        return JSONResponse({"detail": text, "errors": shown}, status_code=422)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> Response:
        """A 405's ``Allow`` names every method the schema documents for the path: Starlette's names
        those of the first route it found, and GET and DELETE of one path are two routes."""
        if exc.status_code == 405:
            path = request.scope["path"]
            allowed = {
                method.upper()
                for template, operations in app.openapi()["paths"].items()
                if compile_path(template)[0].fullmatch(path)
                for method in operations
            }
            if allowed:  # else a path outside the schema (/docs): Starlette's answer stands
                exc.headers = {**(exc.headers or {}), "Allow": ", ".join(sorted(allowed))}
        return await http_exception_handler(request, exc)

    @app.get("/healthz", tags=["health"])
    def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get(
        "/readyz",
        tags=["health"],
        response_model=Readiness,
        responses={
            503: {
                "model": Readiness,
                "description": "the store, the queue or the storage fails, or (queue mode) no worker "
                "was heard from within GEOMATCH_WORKER_LEASE",
            }
        },
    )
    def readyz() -> JSONResponse:
        r = service.readiness()
        return JSONResponse({"ready": r.ok, "checks": r.checks}, status_code=200 if r.ok else 503)

    @app.get(
        "/metrics",
        tags=["health"],
        response_class=PlainTextResponse,
        responses={200: {"description": "Prometheus text format", "content": {"text/plain": {}}}},
    )
    def prometheus() -> Response:
        return Response(generate_latest(metrics.registry), media_type=CONTENT_TYPE_LATEST)

    return app
