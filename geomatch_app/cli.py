"""The ``geomatch`` command: the composition root, the one module that names every layer.

The library's commands (match, run, eval, demo, synth, export) come from ``geomatch.cli``, the
client-side ones (keys, submit) from ``service.cli``; the commands that put a service together with a job
runner (serve, grpc-serve, worker) live here, with ``geomatch_app.bootstrap``. Everything heavy (FastAPI,
Celery, grpc, torch) is imported inside the command that needs it, so parsing is cheap.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import sys
import threading
from typing import Any

from geomatch import cli as library
from geomatch.options import EXIT_BAD_INPUT
from service import cli as client
from service.grpcapi import cli as grpc_options
from service.nodeodm import cli as node_options


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="geomatch", description="Geometry-aware matching for SfM")
    sub = parser.add_subparsers(dest="command", required=True)
    library.register(sub)
    register(sub)
    client.register(sub)
    return parser


def register(sub: Any) -> None:
    s = sub.add_parser(
        "serve",
        help="run the HTTP API (embedded default: SQLite, local files, jobs in-process; REDIS_URL: Celery)",
    )
    s.add_argument("--host", default="127.0.0.1")
    s.add_argument("--port", type=int, default=8000)
    grpc_options.add_serve_options(s)
    node_options.add_serve_options(s)
    s.set_defaults(func=cmd_serve)

    g = sub.add_parser(
        "grpc-serve",
        help="run the gRPC API alone (same configuration as `serve`: GEOMATCH_HOME, REDIS_URL ...)",
    )
    g.add_argument("--host", default="127.0.0.1")
    g.add_argument("--port", type=int, default=grpc_options.DEFAULT_PORT, help="0: any free port (printed)")
    g.set_defaults(func=cmd_grpc_serve)

    w = sub.add_parser("worker", help="run a Celery worker for the service's jobs (needs REDIS_URL)")
    w.add_argument("--concurrency", type=int, default=1, help="steps run at once (one process each)")
    w.add_argument("--pool", choices=("prefork", "solo", "threads"), default="prefork")
    w.add_argument("--loglevel", default="INFO")
    w.set_defaults(func=cmd_worker)


def main(argv: list[str] | None = None) -> int:
    return library.run(build_parser().parse_args(argv))


# -- serve ---------------------------------------------------------------------------------------
def announce(service: Any, what: str, keys_hint: str = "", curl_base: str | None = None) -> None:
    """What a server prints once it listens: ``what`` (where), the mode, and in embedded mode the
    key of the tenant 'local' (with a curl line against ``curl_base``)."""
    from service.auth import embedded_key

    settings = service.settings
    if not settings.embedded:
        print(
            f"{what}, jobs go to Celery queue '{settings.queue}' on REDIS_URL: start workers with "
            f"`geomatch worker`{keys_hint}",
            flush=True,
        )
        return
    key = embedded_key(service.store, settings.home)
    print(f"{what}, embedded mode: jobs run in this process, state under {settings.home}", flush=True)
    print(f"API key (tenant 'local'): {key}", flush=True)
    if curl_base is not None:
        print(f"  curl -H 'Authorization: Bearer {key}' {curl_base}/v1/projects", flush=True)


def cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from geomatch_core.config import Settings
    from service import logs
    from service.http.api import create_app
    from service.http.server import H11Protocol

    from .bootstrap import build_service, close_service

    logs.configure()
    settings = Settings.from_env()
    service = build_service(settings)
    try:
        grpc_server = grpc_options.start_beside_http(service, args)  # same Service: one runner, one config
    except SystemExit:
        close_service(service)
        raise
    try:
        node = node_options.start_beside_http(service, args)  # the NodeODM node: same Service again
    except SystemExit:
        if grpc_server is not None:
            grpc_server.stop()
        close_service(service)
        raise
    base = f"http://{args.host}:{args.port}"
    announce(
        service,
        f"geomatch API on {base} (OpenAPI: {base}/docs)",
        keys_hint="; keys with `geomatch keys create TENANT`",
        curl_base=base,
    )
    # no `server: uvicorn` banner: it tells a scanner which parser's bugs to try, and no client needs
    # it; the protocol answers a head over h11's limit with a 431 the client can read (service/http/server.py)
    server = uvicorn.Server(
        uvicorn.Config(
            create_app(service),
            host=args.host,
            port=args.port,
            log_level="warning",
            server_header=False,
            http=H11Protocol,
        )
    )
    try:
        server.run()
    finally:
        if node is not None:
            node.stop()
        if grpc_server is not None:
            grpc_server.stop()
        close_service(service)
    return 0


def cmd_grpc_serve(args: argparse.Namespace) -> int:
    from geomatch_core.config import Settings
    from service import logs
    from service.grpcapi.pb import GeneratedCodeMissing

    from .bootstrap import build_service, close_service

    try:
        from service.grpcapi.server import PortInUse, address, start
    except GeneratedCodeMissing as e:
        print(f"geomatch: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    logs.configure()
    settings = Settings.from_env()
    service = build_service(settings)
    try:
        try:
            server = start(service, args.host, args.port)
        except PortInUse as e:
            print(f"geomatch: error: {e}", file=sys.stderr)
            return EXIT_BAD_INPUT
        announce(service, f"gRPC (geomatch.v1.Matching) on {address(args.host, server.port)}")
        done = threading.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: done.set())
        done.wait()
        server.stop()
    finally:
        close_service(service)
    return 0


# -- worker --------------------------------------------------------------------------------------
def cmd_worker(args: argparse.Namespace) -> int:
    from geomatch_core.config import Settings
    from geomatch_core.storage import Storage
    from geomatch_core.store import MetadataStore
    from service import logs

    settings = Settings.from_env()
    if settings.embedded:
        print(
            "geomatch: error: `geomatch worker` needs REDIS_URL (the queue); without it "
            "`geomatch serve` runs the jobs itself",
            file=sys.stderr,
        )
        return EXIT_BAD_INPUT
    from workers.celery_app import interactive_queue, make_app
    from workers.tasks import register as register_tasks

    logs.configure()
    store = MetadataStore(settings.database_url)
    store.create_all()  # a worker may start before the first API process
    store.dispose()
    Storage(settings.home).ensure()
    celery = make_app(settings)
    register_tasks(celery)
    celery.worker_main(
        [
            "worker",
            f"--loglevel={args.loglevel}",
            f"--concurrency={args.concurrency}",
            f"--pool={args.pool}",
            f"--queues={settings.queue},{interactive_queue(settings)}",
            f"--hostname=geomatch-{os.getpid()}@{socket.gethostname()}",
            "--without-gossip",
            "--without-mingle",
        ]
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
