"""The gRPC server: the Matching servicer, health checking, reflection, on one port.

``start`` is shared by ``geomatch serve`` (beside uvicorn, over the same ``Service`` object, so the
embedded job runner exists once) and ``geomatch grpc-serve`` (alone).

Handlers are built from the service descriptor rather than with the generated
``add_MatchingServicer_to_server`` only to put ``safe_deserializer`` in front of every method: a
request that does not parse is INVALID_ARGUMENT, and a broken message inside an upload stream
cannot end the stream early (see ``status.Malformed``).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from concurrent import futures
from dataclasses import dataclass
from typing import Any

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from ..usecases import Service
from .limits import THREADS
from .pb import SERVICE, SERVICE_NAME, pb2
from .servicer import MatchingServicer
from .status import Malformed

log = logging.getLogger("geomatch.service.grpc")

DEFAULT_PORT = 50051
READINESS_INTERVAL_S = 5.0  # how often health follows the store / queue / storage checks
MAX_MESSAGE = 4 * 1024 * 1024  # gRPC's default receive limit, explicit: chunks are at most 1 MiB
OPTIONS = [
    # a second server on a taken port must fail, not share it: with SO_REUSEPORT (gRPC's default
    # on Linux) the kernel would split connections between two unrelated servers
    ("grpc.so_reuseport", 0),
    ("grpc.max_receive_message_length", MAX_MESSAGE),
    ("grpc.max_send_message_length", 64 * 1024 * 1024),  # MatchPair answers with many matches
    # pings keep long WatchJob streams open through idle-timeout proxies and find dead clients
    ("grpc.keepalive_time_ms", 30_000),
    ("grpc.keepalive_timeout_ms", 10_000),
    ("grpc.http2.max_pings_without_data", 0),
    ("grpc.keepalive_permit_without_calls", 1),
    # accept the clients' 30 s pings while a stream carries no data: by default the server wants
    # 5 min between them and, after two earlier ones, ends the connection with "too_many_pings",
    # which killed WatchJob streams whenever one pair took over a minute (a loaded CPU, full size)
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


def matching_handler(servicer: MatchingServicer) -> tuple[grpc.GenericRpcHandler, dict[str, Any]]:
    kinds = {
        (False, False): grpc.unary_unary_rpc_method_handler,
        (True, False): grpc.stream_unary_rpc_method_handler,
        (False, True): grpc.unary_stream_rpc_method_handler,
        (True, True): grpc.stream_stream_rpc_method_handler,
    }
    handlers = {}
    for m in SERVICE.methods:
        make = kinds[(m.client_streaming, m.server_streaming)]
        handlers[m.name] = make(
            getattr(servicer, m.name),
            request_deserializer=safe_deserializer(getattr(pb2, m.input_type.name)),
            response_serializer=getattr(pb2, m.output_type.name).SerializeToString,
        )
    return grpc.method_handlers_generic_handler(SERVICE_NAME, handlers), handlers


@dataclass
class GrpcServer:
    server: grpc.Server
    port: int
    health: health.HealthServicer
    _stop: threading.Event

    def stop(self, grace_s: float = 5.0) -> None:
        """Health says NOT_SERVING first, so balancers stop sending; open calls get ``grace_s``."""
        self._stop.set()
        self.health.enter_graceful_shutdown()
        self.server.stop(grace_s).wait(grace_s + 1)

    def wait(self) -> None:
        self.server.wait_for_termination()


def address(host: str, port: int) -> str:
    return f"[{host}]:{port}" if ":" in host and not host.startswith("[") else f"{host}:{port}"


def start(service: Service, host: str = "127.0.0.1", port: int = DEFAULT_PORT) -> GrpcServer:
    """Serve on ``host:port`` (port 0: a free port, see ``GrpcServer.port``); raises PortInUse."""
    server = grpc.server(
        futures.ThreadPoolExecutor(THREADS, thread_name_prefix="geomatch-grpc"), options=OPTIONS
    )
    generic, handlers = matching_handler(MatchingServicer(service))
    server.add_generic_rpc_handlers((generic,))
    if hasattr(server, "add_registered_method_handlers"):  # grpcio >= 1.62: faster dispatch
        server.add_registered_method_handlers(SERVICE_NAME, handlers)
    health_servicer = health.HealthServicer(experimental_non_blocking=True)
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
    stop = threading.Event()
    _follow_readiness(service, health_servicer, stop)
    server.start()
    return GrpcServer(server, bound, health_servicer, stop)


def _follow_readiness(service: Service, h: health.HealthServicer, stop: threading.Event) -> None:
    """Health follows /readyz. ``geomatch.v1.Matching`` is SERVING while the service can get work
    done: the store, the queue and the storage answer and, in queue mode, a worker is alive. The
    server's own name ``""`` leaves the workers out (the store, the queue and the storage only): it
    says whether this process serves, which the image's health check asks and which must not wait
    for workers that themselves start after the API. The first check is made before the server
    starts, so no client ever sees an unknown status."""
    serving, not_serving = health_pb2.HealthCheckResponse.SERVING, health_pb2.HealthCheckResponse.NOT_SERVING

    def update(last: tuple[bool, bool] | None) -> tuple[bool, bool]:
        try:
            r = service.readiness()
            now, checks = (r.serving, r.ok), r.checks
        except Exception as e:
            now, checks = (False, False), {"readiness": str(e)}
        if now != last:
            for name, ok in (("", now[0]), (SERVICE_NAME, now[1])):
                h.set(name, serving if ok else not_serving)
            if not now[1]:
                log.warning("gRPC health: %s NOT_SERVING %s", SERVICE_NAME, checks)
        return now

    def loop(last: tuple[bool, bool]) -> None:
        while not stop.wait(READINESS_INTERVAL_S):
            last = update(last)

    threading.Thread(target=loop, args=(update(None),), name="geomatch-grpc-health", daemon=True).start()
