"""``python -m service.grpcapi [--host H] [--port P]``: the gRPC server without the ``geomatch``
command, whose module imports the library and torch at start (as ``service.asgi`` is to
``geomatch serve``). In Redis mode this process then never loads torch: MatchPair goes to workers."""

from __future__ import annotations

import argparse
import sys

from .cli import DEFAULT_PORT, cmd_grpc_serve


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m service.grpcapi", description=__doc__)
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help="0: any free port (printed)")
    return cmd_grpc_serve(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
