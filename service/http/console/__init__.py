"""The web console: static files served by the API itself at ``/`` (``static/``, plain ES modules,
no build step), talking only to the public ``/v1`` API with the user's key.

Its pages get a strict Content-Security-Policy (no inline script, nothing from another origin,
not framable): the console shows names and messages that clients chose, and the policy is the
second line of defence behind rendering all of them as text.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from pathlib import Path

from fastapi import FastAPI, Request, Response
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

STATIC = Path(__file__).resolve().parent / "static"
PREFIX = "/console"
# blob: for images fetched with the key (an <img src> cannot send an Authorization header)
CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; "
    "connect-src 'self'; frame-ancestors 'none'; object-src 'none'; base-uri 'none'; form-action 'self'"
)
HEADERS = {
    "Content-Security-Policy": CSP,
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
}


def is_console(path: str) -> bool:
    return path == "/" or path == PREFIX or path.startswith(PREFIX + "/")


def mount(app: FastAPI) -> None:
    """``/`` (the page) and ``/console/...`` (its modules, style, vendored files), outside the
    OpenAPI schema: they are not part of the API's contract."""

    @app.api_route("/", methods=["GET", "HEAD"], include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(
            STATIC / "index.html", media_type="text/html", headers={"Cache-Control": "no-cache"}
        )

    app.mount(PREFIX, StaticFiles(directory=STATIC), name="console")

    @app.middleware("http")
    async def security_headers(
        request: Request, call_next: Callable[[Request], Awaitable[Response]]
    ) -> Response:
        response = await call_next(request)
        if is_console(request.url.path):
            response.headers.update(HEADERS)
        return response
