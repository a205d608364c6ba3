"""The gRPC server: the Matching servicer, health checking, reflection, on one port.

``start`` is shared by ``geomatch serve`` (beside uvicorn, over the same ``Service`` object, so the
embedded job runner exists once) and ``geomatch grpc-serve`` (alone).

The server is grpc.aio's, on an event loop of its own thread: a call waiting for its request message
holds no thread (``bridge.py``: grpcio's synchronous server holds one per such call, so calls
without a key or a message can stop health checks and every tenant's calls). Health checks and
reflection are answered on the loop itself, so no number of busy or held threads stops them; the
servicer's methods, synchronous, run on ``THREADS`` pool threads once their request is there.
``gate.Gate`` refuses a Matching call without a key before it is read and gives every unary call
``Settings.grpc_first_message_s`` to send its message.

Handlers are built from the service descriptor rather than with the generated
``add_MatchingServicer_to_server`` to put ``safe_deserializer`` in front of every method (a
request that does not parse is INVALID_ARGUMENT, and a broken message inside an upload stream
cannot end the stream early, see ``status.Malformed``) and the bridge around every method.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Callable
from concurrent import futures
from dataclasses import dataclass, field
from typing import Any

import grpc
from grpc import aio
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_health.v1.health import aio as health_aio
from grpc_reflection.v1alpha import reflection

from ..auth import MISSING_KEY
from ..usecases import Service
from . import bridge
from .gate import Gate
from .limits import THREADS
from .pb import SERVICE, SERVICE_NAME, pb2
from .servicer import MatchingServicer
from .status import Malformed

log = logging.getLogger("geomatch.service.grpc")

DEFAULT_PORT = 50051
READINESS_INTERVAL_S = 5.0  # how often health follows the store / queue / storage checks
MAX_MESSAGE = 4 * 1024 * 1024  # gRPC's default receive limit, explicit: chunks are at most 1 MiB
MAX_CALLS_PER_CONNECTION = 256  # HTTP/2 streams one connection may hold open at once
OPTIONS = [
    # a second server on a taken port must fail, not share it: with SO_REUSEPORT (gRPC's default
    # on Linux) the kernel would split connections between two unrelated servers
    ("grpc.so_reuseport", 0),
    ("grpc.max_receive_message_length", MAX_MESSAGE),
    ("grpc.max_send_message_length", 64 * 1024 * 1024),  # MatchPair answers with many matches
    ("grpc.max_concurrent_streams", MAX_CALLS_PER_CONNECTION),
    # pings keep long WatchJob streams open through idle-timeout proxies and find dead clients
    ("grpc.keepalive_time_ms", 30_000),
    ("grpc.keepalive_timeout_ms", 10_000),
    ("grpc.http2.max_pings_without_data", 0),
    ("grpc.keepalive_permit_without_calls", 1),
    # accept the clients' 30 s pings while a stream carries no data: by default the server wants
    # 5 min between them and, after two earlier ones, ends the connection with "too_many_pings",
    # which would end WatchJob streams whenever one pair takes over a minute (a loaded CPU, full size)
    ("grpc.http2.min_recv_ping_interval_without_data_ms", 20_000),
]


class PortInUse(RuntimeError):
    pass


def safe_deserializer(cls: Any) -> Callable[[bytes], Any]:
    def parse(data: bytes) -> Any:
        try:
            return cls.FromString(data)
        except Exception as e:  # protobuf's DecodeError, and whatever a hostile message triggers
            return Malformed(e)

    return parse


def matching_handler(servicer: MatchingServicer, pool: futures.ThreadPoolExecutor) -> grpc.GenericRpcHandler:
    kinds: dict[tuple[bool, bool], tuple[Any, Any]] = {
        (False, False): (grpc.unary_unary_rpc_method_handler, bridge.unary_unary),
        (True, False): (grpc.stream_unary_rpc_method_handler, bridge.stream_unary),
        (False, True): (grpc.unary_stream_rpc_method_handler, bridge.unary_stream),
    }
    handlers = {}
    for m in SERVICE.methods:
        make, bridged = kinds[(m.client_streaming, m.server_streaming)]
        handlers[m.name] = make(
            bridged(getattr(servicer, m.name), pool),
            request_deserializer=safe_deserializer(getattr(pb2, m.input_type.name)),
            response_serializer=getattr(pb2, m.output_type.name).SerializeToString,
        )
    return grpc.method_handlers_generic_handler(SERVICE_NAME, handlers)


@dataclass
class GrpcServer:
    server: aio.Server
    port: int
    health: health_aio.HealthServicer
    loop: asyncio.AbstractEventLoop
    pool: futures.ThreadPoolExecutor
    _thread: threading.Thread
    _stop: threading.Event = field(default_factory=threading.Event)

    def stop(self, grace_s: float = 5.0) -> None:
        """Health says NOT_SERVING first, so balancers stop sending; open calls get ``grace_s``."""
        if self._stop.is_set():
            return
        self._stop.set()

        async def shutdown() -> None:
            await self.health.enter_graceful_shutdown()
            await self.server.stop(grace_s)

        try:
            asyncio.run_coroutine_threadsafe(shutdown(), self.loop).result(grace_s + 5)
        except Exception as e:  # a stop must not fail the process's exit
            log.warning("gRPC server stop: %s", e)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(5)
        self.pool.shutdown(wait=False, cancel_futures=True)

    def wait(self) -> None:
        self._thread.join()


def address(host: str, port: int) -> str:
    return f"[{host}]:{port}" if ":" in host and not host.startswith("[") else f"{host}:{port}"


def start(service: Service, host: str = "127.0.0.1", port: int = DEFAULT_PORT) -> GrpcServer:
    """Serve on ``host:port`` (port 0: a free port, see ``GrpcServer.port``); raises PortInUse."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=_run_loop, args=(loop,), name="geomatch-grpc-loop", daemon=True)
    thread.start()
    pool = futures.ThreadPoolExecutor(THREADS, thread_name_prefix="geomatch-grpc")
    try:
        server, bound, health_servicer = asyncio.run_coroutine_threadsafe(
            _build(service, pool, host, port), loop
        ).result()
    except BaseException:
        loop.call_soon_threadsafe(loop.stop)
        thread.join(5)
        pool.shutdown(wait=False)
        raise
    grpc_server = GrpcServer(server, bound, health_servicer, loop, pool, thread)
    # the first check is made before the server starts, so no client ever sees an unknown status
    _follow_readiness(service, grpc_server, grpc_server._stop)
    asyncio.run_coroutine_threadsafe(server.start(), loop).result()
    return grpc_server


def _run_loop(loop: asyncio.AbstractEventLoop) -> None:
    asyncio.set_event_loop(loop)
    try:
        loop.run_forever()
    finally:
        loop.close()


async def _build(
    service: Service, pool: futures.ThreadPoolExecutor, host: str, port: int
) -> tuple[aio.Server, int, health_aio.HealthServicer]:
    gate = Gate(SERVICE_NAME, MISSING_KEY, service.settings.grpc_first_message_s)
    server = aio.server(interceptors=[gate], options=OPTIONS)
    server.add_generic_rpc_handlers((matching_handler(MatchingServicer(service), pool),))
    health_servicer = health_aio.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    reflection.enable_server_reflection(
        (SERVICE_NAME, health_pb2.DESCRIPTOR.services_by_name["Health"].full_name, reflection.SERVICE_NAME),
        server,
    )
    try:
        bound = server.add_insecure_port(address(host, port))
    except RuntimeError as e:
        raise PortInUse(f"cannot listen on {address(host, port)} ({e})") from None
    if not bound:  # older grpcio answers 0 instead of raising
        raise PortInUse(f"cannot listen on {address(host, port)}")
    return server, bound, health_servicer


def _follow_readiness(service: Service, g: GrpcServer, stop: threading.Event) -> None:
    """Health follows /readyz. ``geomatch.v1.Matching`` is SERVING while the service can get work
    done: the store, the queue and the storage answer and, in queue mode, a worker is alive. The
    server's own name ``""`` leaves the workers out (the store, the queue and the storage only): it
    says whether this process serves, which the image's health check asks and which must not wait
    for workers that themselves start after the API. The checks run on this thread (they block);
    the statuses are set on the server's loop. The first check is made before this returns."""
    serving, not_serving = health_pb2.HealthCheckResponse.SERVING, health_pb2.HealthCheckResponse.NOT_SERVING

    async def publish(now: tuple[bool, bool]) -> None:
        for name, ok in (("", now[0]), (SERVICE_NAME, now[1])):
            await g.health.set(name, serving if ok else not_serving)

    def update(last: tuple[bool, bool] | None) -> tuple[bool, bool]:
        try:
            r = service.readiness()
            now, checks = (r.serving, r.ok), r.checks
        except Exception as e:
            now, checks = (False, False), {"readiness": str(e)}
        if now != last:
            asyncio.run_coroutine_threadsafe(publish(now), g.loop).result()
            if not now[1]:
                log.warning("gRPC health: %s NOT_SERVING %s", SERVICE_NAME, checks)
        return now

    def loop(last: tuple[bool, bool]) -> None:
        while not stop.wait(READINESS_INTERVAL_S):
            try:
                last = update(last)
            except Exception as e:  # the server's loop stopped under us: the process is ending
                log.debug("gRPC health: %s", e)
                return

    threading.Thread(target=loop, args=(update(None),), name="geomatch-grpc-health", daemon=True).start()
