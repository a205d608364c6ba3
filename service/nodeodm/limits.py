"""The REST API's body limits (service/http/bodylimits.py) on the node's paths: a request with a
body is authenticated by its ``?token=`` before a byte of the body is read, an upload
(``/task/new/upload/{uuid}``, ``/task/new``) may carry ``GEOMATCH_MAX_REQUEST_MB`` with each file
within ``GEOMATCH_MAX_UPLOAD_MB``, any other body ``GEOMATCH_MAX_JSON_MB``; and what is refused is
answered as NodeODM answers errors (200, ``{"error": ...}``), closing the connection."""

from __future__ import annotations

import json
import re
from urllib.parse import parse_qs

from starlette.datastructures import Headers
from starlette.types import Scope, Send

from ..http.bodylimits import PART_HEAD, BodyLimits, PartSizes, bearer, boundary_of

UPLOAD = re.compile(r"^/task/new(?:/upload/[^/]+)?/?$")
MiB = 1024 * 1024


class NodeBodyLimits(BodyLimits):
    def authenticates(self, path: str) -> bool:
        return True  # every path of the node needs the token

    def key(self, scope: Scope, headers: Headers) -> str | None:
        query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
        token = query.get("token", [""])[0]
        return token or bearer(headers)

    def limits(self, scope: Scope, headers: Headers) -> tuple[int, PartSizes | None, str]:
        s = self.service.settings
        if UPLOAD.match(scope["path"]):
            boundary = boundary_of(headers.get("content-type", ""))
            parts = PartSizes(boundary, s.max_upload_bytes + PART_HEAD) if boundary else None
            return s.max_request_bytes, parts, f"an upload request over {s.max_request_bytes // MiB} MiB"
        return s.max_json_bytes, None, f"a request body over {s.max_json_bytes // MiB} MiB"

    async def reply(
        self, send: Send, status: int, detail: str, headers: dict[str, str] | None = None
    ) -> None:
        body = json.dumps({"error": detail}).encode()
        raw = [
            (b"content-type", b"application/json"),
            (b"content-length", str(len(body)).encode()),
            (b"connection", b"close"),
        ]
        raw += [
            (k.lower().encode(), v.encode())
            for k, v in (headers or {}).items()
            if k.lower() != "www-authenticate"
        ]
        await send({"type": "http.response.start", "status": 200, "headers": raw})
        await send({"type": "http.response.body", "body": body})
