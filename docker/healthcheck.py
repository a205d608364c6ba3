"""The image's HEALTHCHECK: one image runs the API, the gRPC server or a worker, so the check
finds the ``geomatch`` process in /proc and checks what that process serves.

- ``serve``: GET /healthz on its ``--port`` (liveness of the HTTP server), and the standard gRPC
  health check on its gRPC port when it serves gRPC. Not /readyz: a Redis or PostgreSQL outage
  would mark every API container unhealthy at once, and /readyz already reports it to whoever
  routes traffic.
- ``grpc-serve``: the gRPC health check on its port.
- ``worker``: a Celery ping to this worker, by its node name. The worker's main process answers it
  through Redis while its pool processes run tasks, so it fails when the broker is unreachable or
  the worker's consumer is stuck, not while a long match runs (with the default prefork pool).

The process's options are read with the CLI's own parser, so ports and hosts follow the command
the container was started with. ``--pid N`` checks that process instead of searching (tests).
Exit 0 healthy, 1 unhealthy (the reason on stderr, which ``docker inspect`` shows).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import urllib.request
from pathlib import Path

SERVERS = ("serve", "grpc-serve", "worker")
TIMEOUT_S = 5.0


def cmdline(pid: int) -> list[str]:
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return []
    return [a.decode(errors="replace") for a in raw.split(b"\0") if a]


def ppid(pid: int) -> int:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return 0
    return int(stat.rsplit(")", 1)[1].split()[1])


def geomatch_args(argv: list[str]) -> list[str] | None:
    """The arguments after the ``geomatch`` console script, when it runs a server command."""
    for i, a in enumerate(argv):
        if os.path.basename(a) == "geomatch" and i + 1 < len(argv) and argv[i + 1] in SERVERS:
            return argv[i + 1 :]
    return None


def find_process() -> tuple[int, list[str]]:
    """The server's main process: the one whose parent is not itself one (prefork children are)."""
    found = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            args = geomatch_args(cmdline(int(entry.name)))
            if args is not None:
                found[int(entry.name)] = args
    mains = sorted(pid for pid in found if ppid(pid) not in found)
    if not mains:
        raise RuntimeError(f"no `geomatch {'|'.join(SERVERS)}` process is running")
    return mains[0], found[mains[0]]


def parse(args: list[str]) -> argparse.Namespace:
    """The server's options as the CLI parsed them (defaults included); parsing imports neither
    the library's networks (torch) nor the servers' frameworks."""
    from geomatch_app.cli import build_parser

    return build_parser().parse_args(args)


def _connect_host(host: str | None) -> str:
    return "127.0.0.1" if host in (None, "", "0.0.0.0", "::", "[::]") else str(host)


def check_http(host: str, port: int) -> str:
    url = f"http://{host}:{port}/healthz"
    with urllib.request.urlopen(url, timeout=TIMEOUT_S) as r:
        body = json.loads(r.read() or b"{}")
        if r.status != 200 or body.get("status") != "ok":
            raise RuntimeError(f"{url}: HTTP {r.status} {body}")
    return f"{url} ok"


def check_grpc(host: str, port: int) -> str:
    import grpc
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    target = f"{host}:{port}"
    with grpc.insecure_channel(target) as channel:
        reply = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=TIMEOUT_S)
    if reply.status != health_pb2.HealthCheckResponse.SERVING:
        status = health_pb2.HealthCheckResponse.ServingStatus.Name(reply.status)
        raise RuntimeError(f"gRPC {target}: {status}")
    return f"gRPC {target} serving"


def check_worker(pid: int) -> str:
    from geomatch_core.config import Settings
    from workers.celery_app import make_app

    node = f"geomatch-{pid}@{socket.gethostname()}"  # the name `geomatch worker` gives itself
    celery = make_app(Settings.from_env())
    try:
        replies = celery.control.ping(destination=[node], timeout=TIMEOUT_S)
    finally:
        celery.close()
    if not any(node in r for r in replies):
        raise RuntimeError(f"worker {node} did not answer a ping within {TIMEOUT_S:.0f} s")
    return f"worker {node} answered"


def grpc_port(opts: argparse.Namespace) -> int | None:
    """The port the process serves gRPC on; None when it serves none (``serve --no-grpc``). Port 0
    (any free port, which only the process's output tells) is not checkable and reads as none."""
    if opts.command == "grpc-serve":
        port = opts.port
    elif getattr(opts, "no_grpc", False) or not hasattr(opts, "grpc_port"):
        return None
    elif opts.grpc_port is None:
        from service.grpcapi.cli import DEFAULT_PORT  # what `serve` binds when not told

        port = DEFAULT_PORT
    else:
        port = opts.grpc_port
    return int(port) or None


def check(pid: int, args: list[str]) -> list[str]:
    opts = parse(args)
    if opts.command == "worker":
        return [check_worker(pid)]
    host = _connect_host(getattr(opts, "host", None))
    done = []
    if opts.command == "serve":
        done.append(check_http(host, opts.port))
    port = grpc_port(opts)
    if port is not None:
        done.append(check_grpc(_connect_host(getattr(opts, "grpc_host", None) or host), port))
    elif opts.command == "grpc-serve":
        raise RuntimeError(f"`geomatch {' '.join(args)}`: port 0 (any free port) cannot be checked")
    return done


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pid", type=int, help="check this process instead of searching /proc")
    a = ap.parse_args(argv)
    try:
        if a.pid is None:
            pid, args = find_process()
        else:
            found = geomatch_args(cmdline(a.pid))
            if found is None:
                raise RuntimeError(f"process {a.pid} is not a `geomatch {'|'.join(SERVERS)}` process")
            pid, args = a.pid, found
        for line in check(pid, args):
            print(line)
    except Exception as e:
        print(f"unhealthy: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
