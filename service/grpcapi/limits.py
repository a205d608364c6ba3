"""What keeps one client from stalling the gRPC server.

The servicer's methods run on one pool of threads (``server.py``: calls waiting for their request,
and health checks, are held on the event loop, ``bridge.py``), and a request stream holds its thread
for as long as it is open: unchecked, one tenant's idle UploadImages streams can take them all and
leave GetProject waiting for a thread that never comes. Three rules keep the server answering:

- streaming calls (UploadImages, MatchPair, WatchJob, GetModel) hold at most ``STREAMS`` threads in
  all, so ``RESERVED`` threads are always left for unary calls and health checks;
- one tenant holds at most ``Settings.grpc_tenant_streams`` of those, and the last quarter of them
  only go to tenants holding fewer than a quarter of that cap, so tenants holding many cannot take
  the others' share either (a few tenants at the cap would otherwise hold every stream thread); a
  call past a limit is refused at once with RESOURCE_EXHAUSTED;
- a request stream that sends nothing for ``Settings.grpc_stream_idle_s`` is cancelled, which
  gives its thread (and its tenant's slot) back.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import grpc

from ..slots import FairSlots

log = logging.getLogger("geomatch.service.grpc")

THREADS = 64  # the server's handler threads
RESERVED = 16  # of those, never taken by streams: unary calls and health checks
STREAMS = THREADS - RESERVED


class StreamSlots(FairSlots):
    """Open streaming calls, in all and per tenant (``service/slots.py``: with a reserve that
    tenants holding many streams cannot take, so three of them cannot lock out a fourth)."""

    def __init__(self, total: int, per_tenant: int) -> None:
        super().__init__("streaming calls", total, per_tenant)


class IdleStreams:
    """Cancels request streams that went quiet. A thread blocked reading the next message of a
    stream cannot be woken otherwise; the cancellation ends the read, the call's handler unwinds
    (nothing is stored: uploads are all or nothing) and the client sees CANCELLED."""

    def __init__(self, idle_s: float) -> None:
        self.idle_s = idle_s
        self._lock = threading.Lock()
        self._last: dict[int, tuple[grpc.ServicerContext, float]] = {}
        self._thread: threading.Thread | None = None

    @contextmanager
    def watch(self, context: grpc.ServicerContext) -> Iterator[Callable[[bool], None]]:
        """Yields ``heard(ended)``, to call on every message received (``False``) and once the
        client has closed its side (``True``: from then on the call waits for the server only,
        MatchPair for its worker, and is not idle)."""
        key = id(context)

        def heard(ended: bool) -> None:
            with self._lock:
                if ended:
                    self._last.pop(key, None)
                else:
                    self._last[key] = (context, time.monotonic())

        heard(False)
        self._start()
        try:
            yield heard
        finally:
            heard(True)

    def _start(self) -> None:
        with self._lock:
            if self._thread is None:
                self._thread = threading.Thread(target=self._loop, name="geomatch-grpc-idle", daemon=True)
                self._thread.start()

    def _loop(self) -> None:
        while True:
            time.sleep(min(1.0, self.idle_s / 4))
            now = time.monotonic()
            with self._lock:
                quiet = [(k, c) for k, (c, t) in self._last.items() if now - t > self.idle_s]
                for k, _ in quiet:
                    del self._last[k]
            for _, context in quiet:
                log.warning("gRPC: a request stream sent nothing for %ss: cancelled", self.idle_s)
                context.cancel()
