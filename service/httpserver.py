"""How uvicorn serves the API over HTTP/1.1: its h11 protocol, answering a request head over the
limit with 431 that the client can read.

uvicorn's h11 protocol answers every request h11 refuses with 400 and closes the socket at once.
For a head over h11's limit (``h11_max_incomplete_event_size``, 16 KiB by default) that is two
faults: h11 says 431 (``error_status_hint``) and uvicorn drops it, and the close comes while the
client is still sending the rest of its head, so the kernel answers those bytes with a reset and
the client sees the connection reset, not the answer (a 200 KB header did). This protocol sends
431, half-closes (no more from us) and reads and discards what the client still sends until it
closes its side, ``LINGER_S`` passes, or ``LINGER_BYTES`` arrived, and only then closes: the
"lingering close" of RFC 9112 section 9.6.

uvicorn takes a protocol class (``Config(http=...)``; ``--http service.httpserver:H11Protocol``
on its command line). The class leans on uvicorn's H11Protocol beyond its documented surface
(``send_400_response``, ``conn``, ``transport``): there is no setting for either fault;
``tests/service/test_http_surface.py`` fails if a uvicorn release changes them.

The same lingering close ends a request whose answer went out before its body was read
(``service/bodylimits.py``: a 401 or 413 against an upload still streaming). uvicorn would read and
discard the rest to keep the connection, a gigabyte if the client sends one; this protocol reads
at most ``LINGER_BYTES`` more and closes.
"""

from __future__ import annotations

import asyncio
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol as _UvicornH11

# h11's own default limit on a request head, which uvicorn uses unless h11_max_incomplete_event_size
# says otherwise: 16 KiB (h11 documents it; the constant itself is private to h11)
MAX_HEAD = 16 * 1024
LINGER_S = 5.0
LINGER_BYTES = 4 * 1024 * 1024
_TOO_LARGE = b"request header fields too large"


class H11Protocol(_UvicornH11):
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._discarded: int | None = None  # bytes read after the 431; None: not lingering
        self._linger: asyncio.TimerHandle | None = None

    def send_400_response(self, msg: str) -> None:
        """uvicorn's answer to what h11 refused; 431 when it was a head over the limit."""
        limit = self.config.h11_max_incomplete_event_size or MAX_HEAD  # what h11 compared with
        if self.conn.our_state is not h11.IDLE or len(self.conn.trailing_data[0]) <= limit:
            super().send_400_response(msg)
            return
        self.logger.warning("Request head over %d bytes: 431", limit)
        head = h11.Response(
            status_code=431,
            reason=b"Request Header Fields Too Large",
            headers=[
                (b"content-type", b"text/plain; charset=utf-8"),
                (b"content-length", str(len(_TOO_LARGE)).encode()),
                (b"connection", b"close"),
            ],
        )
        for event in (head, h11.Data(data=_TOO_LARGE), h11.EndOfMessage()):
            self.transport.write(self.conn.send(event) or b"")
        self._linger_then_close()

    def on_response_complete(self) -> None:
        """An answer sent while the client is still sending its body (h11: SEND_BODY) ends the
        connection, after a lingering close, instead of reading the rest of the body."""
        if self.conn.their_state is not h11.SEND_BODY or self.transport.is_closing():
            super().on_response_complete()
            return
        self.server_state.total_requests += 1
        self.flow.resume_reading()  # paused while the app did not read: the rest is discarded
        self._linger_then_close()

    def _linger_then_close(self) -> None:
        self._discarded = 0
        if self.transport.can_write_eof():
            self.transport.write_eof()
        self._linger = self.loop.call_later(LINGER_S, self.transport.close)

    def data_received(self, data: bytes) -> None:
        if self._discarded is None:
            super().data_received(data)
            return
        self._discarded += len(data)
        if self._discarded > LINGER_BYTES:
            self.transport.close()

    def eof_received(self) -> None:
        if self._discarded is not None:  # the client has sent all it will: now the socket can go
            self.transport.close()

    def connection_lost(self, exc: Exception | None) -> None:
        if self._linger is not None:
            self._linger.cancel()
        super().connection_lost(exc)
