"""The FastAPI application: routes, health, metrics, and the one place where domain errors
become HTTP statuses."""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from core import errors

from .metrics import Metrics
from .routes import router
from .usecases import Service

log = logging.getLogger("geomatch.service")

STATUS: dict[type[errors.DomainError], int] = {
    errors.BadFile: 400,
    errors.Unauthenticated: 401,
    errors.NotFound: 404,
    errors.Conflict: 409,
    errors.TooLarge: 413,
    errors.UnsupportedFormat: 415,
    errors.InvalidRequest: 422,
    errors.Unavailable: 503,
}


def status_of(exc: errors.DomainError) -> int:
    for cls in type(exc).__mro__:
        if cls in STATUS:
            return STATUS[cls]
    return 400


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
    service.on_upload = lambda n, size: (metrics.uploaded_images.inc(n), metrics.uploaded_bytes.inc(size))
    app.include_router(router)

    @app.exception_handler(errors.DomainError)
    async def domain_error(request: Request, exc: errors.DomainError) -> JSONResponse:
        status = status_of(exc)
        headers = {"WWW-Authenticate": "Bearer"} if status == 401 else None
        return JSONResponse({"detail": exc.message}, status_code=status, headers=headers)

    @app.exception_handler(RequestValidationError)
    async def invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        problems: list[Any] = list(exc.errors())
        if any(p.get("type") == "json_invalid" for p in problems):
            ctx = next(p for p in problems if p.get("type") == "json_invalid").get("ctx", {})
            return JSONResponse(
                {"detail": f"malformed JSON body: {ctx.get('error', 'cannot be parsed')}"}, status_code=400
            )
        text = "; ".join(
            f"{'.'.join(str(x) for x in p.get('loc', ()) if x != 'body') or 'body'}: {p.get('msg')}"
            for p in problems
        )
        return JSONResponse(
            {"detail": text, "errors": [{k: p.get(k) for k in ("loc", "msg", "type")} for p in problems]},
            status_code=422,
        )

    @app.get("/healthz", tags=["health"])
    def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get("/readyz", tags=["health"])
    def readyz() -> JSONResponse:
        r = service.readiness()
        return JSONResponse({"ready": r.ok, "checks": r.checks}, status_code=200 if r.ok else 503)

    @app.get("/metrics", tags=["health"])
    def prometheus() -> Response:
        return Response(generate_latest(metrics.registry), media_type=CONTENT_TYPE_LATEST)

    return app
