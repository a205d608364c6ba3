"""ASGI entry point for production servers: ``uvicorn service.asgi:app``.

Unlike ``geomatch serve`` (whose command module imports the library, and with it torch), this
imports the service only. Settings come from the environment, as for every process.
"""

from __future__ import annotations

from . import logs
from .api import create_app
from .bootstrap import build_service
from .config import Settings

logs.configure()
app = create_app(build_service(Settings.from_env()))
