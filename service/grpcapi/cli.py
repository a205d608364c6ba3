"""The gRPC options and commands of ``geomatch``: ``serve --grpc-port``, ``grpc-serve``, ``submit --grpc``.

Kept apart from ``service/cli.py`` so that module only gains a few calls; grpc is imported inside
the commands, as the other commands import their frameworks.

Ports: ``serve`` starts gRPC on 50051 unless told otherwise. An explicit ``--grpc-port N`` that
cannot be bound is an error (exit 2); the default port already taken (another deployment on the
same host) prints a warning and serves HTTP only. Port 0 is the operating system's "any free
port": the port chosen is printed. ``--no-grpc`` turns gRPC off.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from typing import Any

DEFAULT_PORT = 50051  # server.DEFAULT_PORT, repeated so that parsing arguments imports no grpc
EXIT_BAD_INPUT = 2


def add_serve_options(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("gRPC (geomatch.v1.Matching, health, reflection; docs/grpc.md)")
    g.add_argument(
        "--grpc-port",
        type=int,
        default=None,
        help=f"gRPC port (default {DEFAULT_PORT}, skipped with a warning when taken; 0: any free port)",
    )
    g.add_argument("--grpc-host", default=None, help="gRPC address to listen on (default: --host)")
    g.add_argument("--no-grpc", action="store_true", help="serve HTTP only")


def add_submit_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--grpc", action="store_true", help="talk gRPC to --grpc-server instead of HTTP")
    parser.add_argument(
        "--grpc-server",
        default=os.environ.get("GEOMATCH_GRPC_SERVER", f"127.0.0.1:{DEFAULT_PORT}"),
        metavar="HOST:PORT",
        help="gRPC address for --grpc (or $GEOMATCH_GRPC_SERVER)",
    )


def register(sub: Any) -> None:
    s = sub.add_parser(
        "grpc-serve",
        help="run the gRPC API alone (same configuration as `serve`: GEOMATCH_HOME, REDIS_URL ...)",
    )
    s.add_argument("--host", default="127.0.0.1")
    s.add_argument("--port", type=int, default=DEFAULT_PORT, help="0: any free port (printed)")
    s.set_defaults(func=cmd_grpc_serve)


def start_beside_http(service: Any, args: argparse.Namespace) -> Any:
    """The gRPC server of ``geomatch serve``, or None (``--no-grpc``, or the default port taken).
    Raises SystemExit(2) when an explicit port cannot be bound or the generated code is missing."""
    if args.no_grpc:
        return None
    from .pb import GeneratedCodeMissing

    host = args.grpc_host or args.host
    port = DEFAULT_PORT if args.grpc_port is None else args.grpc_port
    try:
        from .server import PortInUse, address, start

        server = start(service, host, port)
    except GeneratedCodeMissing as e:
        print(f"geomatch: error: {e}; or serve HTTP only with --no-grpc", file=sys.stderr)
        raise SystemExit(EXIT_BAD_INPUT) from None
    except PortInUse as e:
        if args.grpc_port is not None:
            print(f"geomatch: error: gRPC: {e}", file=sys.stderr)
            raise SystemExit(EXIT_BAD_INPUT) from None
        print(
            f"geomatch: warning: gRPC not started: {e}; pass --grpc-port N (0: any free port)",
            file=sys.stderr,
            flush=True,
        )
        return None
    print(f"gRPC (geomatch.v1.Matching) on {address(host, server.port)}", flush=True)
    return server


def cmd_grpc_serve(args: argparse.Namespace) -> int:
    from .. import logs
    from ..bootstrap import build_service, close_service
    from ..cli import embedded_key
    from ..config import Settings
    from .pb import GeneratedCodeMissing

    try:
        from .server import PortInUse, address, start
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
        where = address(args.host, server.port)
        if settings.embedded:
            key = embedded_key(service.store, settings.home)
            print(
                f"gRPC (geomatch.v1.Matching) on {where}, embedded mode: jobs run in this process, "
                f"state under {settings.home}",
                flush=True,
            )
            print(f"API key (tenant 'local'): {key}", flush=True)
        else:
            print(
                f"gRPC (geomatch.v1.Matching) on {where}, jobs go to Celery queue '{settings.queue}' on "
                "REDIS_URL: start workers with `geomatch worker`",
                flush=True,
            )
        done = threading.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: done.set())
        done.wait()
        server.stop()
    finally:
        close_service(service)
    return 0


def cmd_submit(args: argparse.Namespace) -> int:
    from .submit import submit

    return submit(args)
