"""Request bodies: who may send one, and how much, decided before the body is read.

FastAPI reads and parses a request's body (a multipart upload spooled to temporary files, a JSON
document into memory) before it runs the route's dependencies, the API key check among them: a
wrong key against a large upload would cost its size in temporary files before its 401, and a valid
one would get its 413 for a file over the per-file limit only once every byte is spooled. This ASGI
middleware runs first, on the request head:

- a ``/v1`` request that carries a body is authenticated here (``Service.authenticate``, in a
  thread: it reads the store), 401 before a byte of the body is read; the tenant goes to the
  request's state, where ``routes.deps.tenant`` takes it instead of checking the key again;
- ``Content-Length`` over the route's limit is 413 at once: ``max_request_bytes`` for an upload
  (every file of it together), 1 MiB (and a multipart part's headers) for a GCP file,
  ``max_json_bytes`` for any other body;
- while the app reads the body, what arrives is counted (a chunked body has no length to check
  up front), and in a multipart upload so is each part: a part over the per-file limit, or a body
  over the route's limit, ends the request with 413 there and then.

Answering without reading the body is only half of it: a server that closes a socket with unread
bytes makes the kernel reset the connection, and the client, still sending, loses the answer.
``service/http/server.py`` keeps reading and discarding for a short while after such an answer.
"""

from __future__ import annotations

import json
import re

from starlette.concurrency import run_in_threadpool
from starlette.datastructures import Headers
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from geomatch_core.config import Settings
from geomatch_core.errors import DomainError, Unauthenticated

from ..usecases import Service
from ..usecases.gcp import MAX_GCP_BYTES
from .errors import error_headers, status_of

UPLOAD = re.compile(r"^/v1/projects/[^/]+/(?:images|localize)/?$")  # multipart uploads of images
GCP = re.compile(r"^/v1/projects/[^/]+/gcp/?$")  # a gcp_list.txt, as the body or one multipart part
PART_HEAD = 64 * 1024  # a multipart part's own headers, allowed on top of the file's bytes
BODY_METHODS = {"POST", "PUT", "PATCH", "DELETE"}
MiB = 1024 * 1024


class BodyTooLarge(Exception):
    """Raised from ``receive`` into the app reading the body; the middleware answers 413."""


class PartSizes:
    """Counts the bytes of each part of a multipart body as it streams by, finding the parts'
    delimiters across chunk borders (it keeps the last ``len(delimiter) - 1`` bytes)."""

    def __init__(self, boundary: bytes, limit: int) -> None:
        self.delimiter = b"\r\n--" + boundary
        self.limit = limit
        self.since = 0  # bytes since the last delimiter: the current part so far
        self.tail = b""

    def feed(self, data: bytes) -> bool:
        """True when the current part went over the limit."""
        buf = self.tail + data
        at = buf.rfind(self.delimiter)
        if at >= 0:
            self.since = len(buf) - at - len(self.delimiter)
        else:
            self.since += len(data)
        self.tail = buf[-(len(self.delimiter) - 1) :]
        return self.since > self.limit


def bearer(headers: Headers) -> str | None:
    scheme, _, token = headers.get("authorization", "").strip().partition(" ")
    return token.strip() or None if scheme.lower() == "bearer" else None


def boundary_of(content_type: str) -> bytes | None:
    m = re.search(r'boundary="?([^";]+)"?', content_type, re.I)
    return m.group(1).encode("latin-1") if m else None


async def answer(send: Send, status: int, detail: str, headers: dict[str, str] | None = None) -> None:
    """An answer given before the body was read: it says the connection closes, so that a client
    does not send its next request on a connection the server is about to drop."""
    body = json.dumps({"detail": detail}).encode()
    raw = [
        (b"content-type", b"application/json"),
        (b"content-length", str(len(body)).encode()),
        (b"connection", b"close"),
    ]
    raw += [(k.lower().encode(), v.encode()) for k, v in (headers or {}).items()]
    await send({"type": "http.response.start", "status": status, "headers": raw})
    await send({"type": "http.response.body", "body": body})


class BodyLimits:
    """The REST API's limits; the NodeODM node (service/nodeodm/limits.py) is this class with its
    own paths, its key in the query and its errors in NodeODM's shape."""

    def __init__(self, app: ASGIApp, service: Service) -> None:
        self.app = app
        self.service = service

    def authenticates(self, path: str) -> bool:
        """Whether a request with a body to ``path`` is authenticated before its body is read."""
        return path.startswith("/v1/")

    def key(self, scope: Scope, headers: Headers) -> str | None:
        return bearer(headers)

    async def reply(
        self, send: Send, status: int, detail: str, headers: dict[str, str] | None = None
    ) -> None:
        await answer(send, status, detail, headers)

    def limits(self, scope: Scope, headers: Headers) -> tuple[int, PartSizes | None, str]:
        """The body's limit, the per-part counter of an upload, and what the 413 says."""
        s: Settings = self.service.settings
        if UPLOAD.match(scope["path"]):
            boundary = boundary_of(headers.get("content-type", ""))
            parts = PartSizes(boundary, s.max_upload_bytes + PART_HEAD) if boundary else None
            return s.max_request_bytes, parts, f"an upload request over {s.max_request_bytes // MiB} MiB"
        if GCP.match(scope["path"]):
            return MAX_GCP_BYTES + PART_HEAD, None, f"a GCP file over {MAX_GCP_BYTES // MiB} MiB"
        return s.max_json_bytes, None, f"a request body over {s.max_json_bytes // MiB} MiB"

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] not in BODY_METHODS:
            await self.app(scope, receive, send)
            return
        headers = Headers(scope=scope)
        length_text = headers.get("content-length")
        chunked = "transfer-encoding" in headers
        if not chunked and (length_text is None or length_text.strip() == "0"):
            await self.app(scope, receive, send)  # no body: nothing to protect
            return
        if self.authenticates(scope["path"]):
            try:
                tenant = await run_in_threadpool(self.service.authenticate, self.key(scope, headers))
            except Unauthenticated as e:
                await self.reply(send, 401, e.message, {"WWW-Authenticate": "Bearer"})
                return
            except DomainError as e:  # the tenant's rate (429): the route would say the same
                await self.refuse(send, e)
                return
            scope.setdefault("state", {})["tenant_id"] = tenant
        limit, parts, what = self.limits(scope, headers)
        if length_text is not None and length_text.strip().isdigit() and int(length_text) > limit:
            await self.reply(send, 413, f"{what}: send fewer or smaller files")
            return
        await self.counted(scope, receive, send, limit, parts, what)

    async def refuse(self, send: Send, e: DomainError) -> None:
        await self.reply(send, status_of(e), e.message, error_headers(e))

    async def counted(
        self, scope: Scope, receive: Receive, send: Send, limit: int, parts: PartSizes | None, what: str
    ) -> None:
        seen = 0
        over: str | None = None
        started = False

        async def limited_receive() -> Message:
            nonlocal seen, over
            message = await receive()
            if message["type"] == "http.request" and over is None:
                chunk = message.get("body", b"")
                seen += len(chunk)
                if seen > limit:
                    over = f"{what}: send fewer or smaller files"
                elif parts is not None and parts.feed(chunk):
                    over = (
                        "a file of this request is larger than the upload limit of "
                        f"{self.service.settings.max_upload_bytes // MiB} MiB"
                    )
            if over is not None:
                raise BodyTooLarge(over)
            return message

        async def guarded_send(message: Message) -> None:
            nonlocal started
            if over is not None:  # the app's answer to the broken-off body: ours instead
                if not started:
                    started = True
                    await self.reply(send, 413, over)
                return
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, limited_receive, guarded_send)
        except BodyTooLarge:
            pass
        except Exception:
            if over is None:
                raise
        if over is not None and not started:
            await self.reply(send, 413, over)
