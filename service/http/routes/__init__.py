"""HTTP routes (prefix /v1), one module per concern as FastAPI's project template lays them out:
request shapes in, use case calls, response shapes out.

Handlers are plain ``def`` where they block (uploads, snapshots, waiting for a picture): FastAPI
runs those on its thread pool, so the event loop keeps serving other requests.
"""

from __future__ import annotations

from fastapi import APIRouter

from . import gcp, images, jobs, localize, outputs, projects
from .deps import ERRORS


def build_router() -> APIRouter:
    """Every route under /v1, made with each app: the model route's formats are read then."""
    v1 = APIRouter(prefix="/v1", responses=ERRORS)
    v1.include_router(projects.router)
    v1.include_router(images.router)
    v1.include_router(gcp.router)
    v1.include_router(jobs.router)
    v1.include_router(outputs.router())
    v1.include_router(localize.router)
    return v1
