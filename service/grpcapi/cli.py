"""The gRPC options of ``geomatch``: ``serve --grpc-port``, ``submit --grpc``, and the gRPC server
started beside the HTTP one. grpc is imported inside the functions, so parsing imports none.

Ports: ``serve`` starts gRPC on 50051 unless told otherwise. An explicit ``--grpc-port N`` that
cannot be bound is an error (exit 2); the default port already taken (another deployment on the
same host) prints a warning and serves HTTP only. Port 0 is the operating system's "any free
port": the port chosen is printed. ``--no-grpc`` turns gRPC off.
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any

from geomatch.options import EXIT_BAD_INPUT

DEFAULT_PORT = 50051  # server.DEFAULT_PORT, repeated so that parsing arguments imports no grpc


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
