"""How uvicorn serves the API over HTTP/1.1: its h11 protocol, answering a request head over the
limit with 431 that the client can read.

uvicorn's h11 protocol answers every request h11 refuses with 400 and closes the socket at once.
For a head over h11's limit (``h11_max_incomplete_event_size``, 16 KiB by default) that is two
faults: h11 says 431 (``error_status_hint``) and uvicorn drops it, and the close comes while the
client is still sending the rest of its head, so the kernel answers those bytes with a reset and
the client sees the connection reset, not the answer. This protocol sends
431, half-closes (no more from us) and reads and discards what the client still sends until it
closes its side, ``LINGER_S`` passes, or ``LINGER_BYTES`` arrived, and only then closes: the
"lingering close" of RFC 9112 section 9.6.

h11's verdict decides between 431 and 400: it raises 431 only while a head is still incomplete past
its limit. A complete head that does not parse (a bad header value) is 400 whatever follows it:
the body bytes buffered behind it (over 16 KiB) must not make it look like a head over the limit.

A request head must arrive within ``GEOMATCH_HEAD_TIMEOUT_S`` (10 s) of its first byte, or of the
connection's opening: a connection that dribbles its head is answered 408 and closed (one that sent
nothing at all is just closed), where uvicorn alone holds it for as long as the client likes, and
enough slow heads use up the file descriptors. Once the head is in, the timer stops: a
slow body and the app's answer have their own limits; an idle keep-alive connection is closed by
uvicorn's keep-alive timeout (5 s), and its next request's first byte starts a new head timer.

uvicorn takes a protocol class (``Config(http=...)``; ``--http service.http.server:H11Protocol``
on its command line). The class leans on uvicorn's H11Protocol beyond its documented surface
(``send_400_response``, ``conn``, made once in its ``__init__``, ``transport``, ``data_received``):
there is no setting for any of these; ``tests/service/test_http_surface.py`` and
``tests/service/test_held_and_capped.py`` fail if a uvicorn release changes them.

The same lingering close ends a request whose answer went out before its body was read
(``service/http/bodylimits.py``: a 401 or 413 against an upload still streaming). uvicorn would read and
discard the rest to keep the connection, a gigabyte if the client sends one; this protocol reads
at most ``LINGER_BYTES`` more and closes.
"""

from __future__ import annotations

import asyncio
import functools
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol as _UvicornH11

from geomatch_core.config import Settings

# h11's own default limit on a request head, which uvicorn uses unless h11_max_incomplete_event_size
# says otherwise: 16 KiB (h11 documents it; the constant itself is private to h11)
MAX_HEAD = 16 * 1024
LINGER_S = 5.0
LINGER_BYTES = 4 * 1024 * 1024
_TOO_LARGE = b"request header fields too large"
_TIMEOUT = b"request head not received in time"


@functools.cache
def head_timeout_s() -> float:
    return Settings.from_env().head_timeout_s


class _Connection(h11.Connection):
    """h11's connection, keeping the error it raised last: its ``error_status_hint`` (431 for a
    head still incomplete past the limit, 400 for the rest) is what the answer says."""

    last_error: h11.RemoteProtocolError | None = None

    def next_event(self) -> Any:
        try:
            return super().next_event()
        except h11.RemoteProtocolError as e:
            self.last_error = e
            raise


class H11Protocol(_UvicornH11):
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        # the same connection uvicorn made (its __init__ is the only place it makes one)
        self._conn = _Connection(h11.SERVER, self.config.h11_max_incomplete_event_size or MAX_HEAD)
        self.conn = self._conn
        self._discarded: int | None = None  # bytes read after the 431; None: not lingering
        self._linger: asyncio.TimerHandle | None = None
        self._head_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._start_head_timer()

    def send_400_response(self, msg: str) -> None:
        """uvicorn's answer to what h11 refused: 431 when it was a head still incomplete past the
        limit, 400 otherwise; then a lingering close, so that a client still sending reads it."""
        self._stop_head_timer()
        if self.conn.our_state is not h11.IDLE:
            super().send_400_response(msg)
            return
        error = self._conn.last_error
        if error is not None and error.error_status_hint == 431:
            limit = self.config.h11_max_incomplete_event_size or MAX_HEAD
            self.logger.warning("Request head over %d bytes: 431", limit)
            status, reason, body = 431, b"Request Header Fields Too Large", _TOO_LARGE
        else:
            self.logger.warning("%s", msg)
            status, reason, body = 400, b"Bad Request", msg.encode("ascii", "replace")
        head = h11.Response(
            status_code=status,
            reason=reason,
            headers=[
                (b"content-type", b"text/plain; charset=utf-8"),
                (b"content-length", str(len(body)).encode()),
                (b"connection", b"close"),
            ],
        )
        for event in (head, h11.Data(data=body), h11.EndOfMessage()):
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
            if self.conn.their_state is h11.IDLE:  # bytes of a head: its timer runs from the first
                self._start_head_timer()
            super().data_received(data)
            if self.conn.their_state is not h11.IDLE:  # the head is in (or refused)
                self._stop_head_timer()
            return
        self._discarded += len(data)
        if self._discarded > LINGER_BYTES:
            self.transport.close()

    def eof_received(self) -> None:
        if self._discarded is not None:  # the client has sent all it will: now the socket can go
            self.transport.close()

    def _start_head_timer(self) -> None:
        if self._head_timer is None:
            self._head_timer = self.loop.call_later(head_timeout_s(), self._head_timed_out)

    def _stop_head_timer(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_timed_out(self) -> None:
        self._head_timer = None
        waiting = self.conn.their_state is h11.IDLE and self._discarded is None
        if not waiting or self.transport.is_closing():
            return
        if not self.conn.trailing_data[0]:  # nothing of a head yet (a fresh or idle connection)
            self.transport.close()
            return
        self.logger.warning("Request head not received within %g s: 408", head_timeout_s())
        self.transport.write(
            b"HTTP/1.1 408 Request Timeout\r\ncontent-type: text/plain; charset=utf-8\r\n"
            b"content-length: %d\r\nconnection: close\r\n\r\n%s" % (len(_TIMEOUT), _TIMEOUT)
        )
        self._linger_then_close()

    def connection_lost(self, exc: Exception | None) -> None:
        if self._linger is not None:
            self._linger.cancel()
        self._stop_head_timer()
        super().connection_lost(exc)
