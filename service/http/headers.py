"""Headers every response of the API carries, set in one place instead of by each route.

- ``X-Content-Type-Options: nosniff`` on everything: a browser must take each body as the type the
  server says (JSON stays JSON, an uploaded image stays that image), never guess one from bytes a
  client chose.
- ``Cache-Control: no-store`` on ``/v1``: what it answers is a tenant's data, read with the
  tenant's key; no browser or proxy cache may keep a copy for whoever asks next. (The SSE stream
  of a job is under it too: no-store keeps proxies from buffering it, as no-cache does.)

A plain ASGI middleware rather than ``@app.middleware("http")``: it only edits the headers of
``http.response.start`` and passes every body message through, so streamed responses (job events,
model downloads) stream unchanged. The ``server`` banner is uvicorn's to drop
(``server_header=False`` where the server is started, geomatch_app/cli.py).
"""

from __future__ import annotations

from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

ALWAYS = {"X-Content-Type-Options": "nosniff"}
TENANT_DATA = {"Cache-Control": "no-store"}
TENANT_PREFIX = "/v1/"


class SecurityHeaders:
    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        extra = ALWAYS | (TENANT_DATA if scope["path"].startswith(TENANT_PREFIX) else {})

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                for name, value in extra.items():
                    headers[name] = value
            await send(message)

        await self.app(scope, receive, send_with_headers)
