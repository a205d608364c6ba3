"""ASGI entry point for production servers: ``uvicorn geomatch_app.asgi:app``.

The HTTP API without the ``geomatch`` command around it; settings come from the environment,
as for every process.
"""

from __future__ import annotations

from geomatch_core.config import Settings
from service import logs
from service.http.api import create_app

from .bootstrap import build_service

logs.configure()
app = create_app(build_service(Settings.from_env()))
