"""Images framed in a request stream: a header message, then chunk messages, image after image.

UploadImages and MatchPair share this framing. ``images`` turns the stream into the use cases'
``Upload`` objects whose ``stream`` reads the image's chunks lazily, so the use case (one upload
code path for REST and gRPC) stages each image as its bytes arrive and never holds a whole
request in memory. Every rule of the framing is checked here: headers before chunks, chunks of at
most 1 MiB, the declared size (when given) met exactly, and a stream that ends only by the client
closing it, never by a cancellation, a deadline or a broken message.
"""

from __future__ import annotations

import io
from collections.abc import Callable, Iterator
from typing import Any

from geomatch_core.errors import BadFile, InvalidRequest, TooLarge

from ..usecases.views import Upload
from .status import Malformed

MAX_CHUNK = 1 << 20  # 1 MiB: the most a chunk carries, uploaded or sent by GetModel
CAPTURES = {0: "auto", 1: "auto", 2: "aerial", 3: "ground"}  # Capture enum -> the use cases' words


class Messages:
    """A request iterator with one message of look-ahead, whose end is checked: gRPC's iterator
    also stops when the call is no longer active, which must not read as "the client is done"."""

    def __init__(
        self,
        requests: Iterator[Any],
        is_active: Callable[[], bool],
        heard: Callable[[bool], None] | None = None,
    ) -> None:
        self._it = requests
        self._is_active = is_active
        self._heard = heard  # limits.IdleStreams: a message came (False), the stream ended (True)
        self._pending: list[Any] = []

    def next(self) -> Any | None:
        if self._pending:
            return self._pending.pop()
        try:
            msg = next(self._it)
        except StopIteration:
            if not self._is_active():
                raise InvalidRequest("the request stream was cut off") from None
            if self._heard is not None:
                self._heard(True)
            return None
        if self._heard is not None:
            self._heard(False)
        if isinstance(msg, Malformed):
            raise InvalidRequest(msg.message)
        return msg

    def push_back(self, msg: Any) -> None:
        self._pending.append(msg)


class Budget:
    """What one upload stream may carry over all its images (``GEOMATCH_MAX_REQUEST_MB``, the
    limit a multipart request has over all its files): without it, a stream of files each under
    the per-file limit could fill the staging disk."""

    def __init__(self, limit: int | None) -> None:
        self.limit = limit
        self.used = 0

    def take(self, n: int, name: str) -> None:
        self.used += n
        if self.limit is not None and self.used > self.limit:
            raise TooLarge(
                f"{name}: the stream's images pass the limit of {self.limit // (1024 * 1024)} MiB "
                "for one upload together; send them in several calls"
            )


class ChunkReader(io.RawIOBase):
    """The bytes of one image: chunk messages up to the next header or the end of the stream."""

    def __init__(
        self, messages: Messages, name: str, declared: int | None, budget: Budget | None = None
    ) -> None:
        self._messages = messages
        self._name = name or "an image"
        self._declared = declared
        self._budget = budget or Budget(None)
        self._buf = memoryview(b"")
        self._received = 0
        self._done = False

    def readable(self) -> bool:
        return True

    def read(self, size: int = -1) -> bytes:
        while not self._buf:
            if self._done:
                return b""
            msg = self._messages.next()
            if msg is None or msg.WhichOneof("part") != "chunk":
                if msg is not None:
                    self._messages.push_back(msg)
                self._done = True
                if self._declared is not None and self._received != self._declared:
                    raise BadFile(
                        f"{self._name}: {self._received} bytes received of the {self._declared} declared"
                    )
                return b""
            if len(msg.chunk) > MAX_CHUNK:
                raise TooLarge(
                    f"{self._name}: a chunk of {len(msg.chunk)} bytes; chunks are at most {MAX_CHUNK} bytes"
                )
            self._received += len(msg.chunk)
            self._budget.take(len(msg.chunk), self._name)
            if self._declared is not None and self._received > self._declared:
                raise BadFile(f"{self._name}: more bytes than the {self._declared} declared")
            self._buf = memoryview(msg.chunk)
        n = len(self._buf) if size is None or size < 0 else min(size, len(self._buf))
        out, self._buf = self._buf[:n].tobytes(), self._buf[n:]
        return out

    def drain(self) -> None:
        while self.read(MAX_CHUNK):
            pass


def images(
    messages: Messages, max_bytes: int, project_id: str = "", max_total: int | None = None
) -> Iterator[Upload]:
    """The images of the stream, in order; each must be read to its end before the next.
    ``max_bytes`` bounds each image, ``max_total`` all of them together."""
    budget = Budget(max_total)
    while (msg := messages.next()) is not None:
        part = msg.WhichOneof("part")
        if part != "image":
            raise InvalidRequest(
                f"expected an image header (`image`), got `{part or 'nothing'}`: each image starts "
                "with a message naming it, then its chunks"
            )
        if project_id and getattr(msg, "project_id", "") not in ("", project_id):
            raise InvalidRequest("project_id changed within the stream")
        header = msg.image
        declared = header.size if header.HasField("size") else None
        if declared is not None and declared < 0:
            raise InvalidRequest(f"{header.name}: a negative size")
        if declared is not None and declared > max_bytes:
            raise TooLarge(
                f"{header.name}: {declared} bytes declared, over the upload limit of "
                f"{max_bytes // (1024 * 1024)} MiB"
            )
        if header.capture not in CAPTURES:
            raise InvalidRequest(f"{header.name}: unknown capture {header.capture}")
        reader = ChunkReader(messages, header.name, declared, budget)
        # a RawIOBase with the read() the use case calls: typing.BinaryIO is nominal, no io class is one
        yield Upload(header.name, reader, CAPTURES[header.capture])  # type: ignore[arg-type]
        reader.drain()  # the use case read it all, unless it stopped early (then it raised)
