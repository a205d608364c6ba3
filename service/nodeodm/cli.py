"""``geomatch serve``'s NodeODM node: its options, and the node started beside the REST API on the
same Service (one set of use cases, one job runner), on its own port (NodeODM's 3000 by default,
where WebODM and PyODM look for a node)."""

from __future__ import annotations

import argparse
import logging
import socket
import threading
import time
from typing import Any

DEFAULT_PORT = 3000
log = logging.getLogger("geomatch.nodeodm")


def add_serve_options(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("NodeODM node (WebODM, PyODM, ClusterODM; docs/webodm.md)")
    g.add_argument(
        "--node-port",
        type=int,
        default=None,
        help=f"NodeODM port (default {DEFAULT_PORT}, skipped with a warning when taken)",
    )
    g.add_argument("--node-host", default=None, help="NodeODM address to listen on (default: --host)")
    g.add_argument("--no-node", action="store_true", help="serve no NodeODM node")


def _free(host: str, port: int) -> bool:
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


class RunningNode:
    def __init__(self, server: Any, thread: threading.Thread, url: str) -> None:
        self.server, self.thread, self.url = server, thread, url

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=10)


def start_beside_http(service: Any, args: argparse.Namespace) -> RunningNode | None:
    """The node's server in a thread of this process, or None (``--no-node``, or the default port
    taken: a warning). An explicit port that cannot be bound is SystemExit(2)."""
    if args.no_node:
        return None
    import uvicorn

    from service.http.server import H11Protocol

    from .app import create_node_app

    host = args.node_host or args.host
    port = args.node_port if args.node_port is not None else DEFAULT_PORT
    if not _free(host, port):
        if args.node_port is None:
            print(
                f"geomatch: warning: port {port} is taken: no NodeODM node (--node-port to pick one)",
                flush=True,
            )
            return None
        print(f"geomatch: error: NodeODM port {host}:{port} is taken", flush=True)
        raise SystemExit(2)
    server = uvicorn.Server(
        uvicorn.Config(
            create_node_app(service),
            host=host,
            port=port,
            log_level="warning",
            access_log=False,  # the app logs each request with its token redacted
            server_header=False,
            http=H11Protocol,
        )
    )
    thread = threading.Thread(target=server.run, name="nodeodm", daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started and thread.is_alive() and time.monotonic() < deadline:
        time.sleep(0.05)
    url = f"http://{host}:{port}"
    print(
        f"NodeODM node on {url} (WebODM: add a processing node with this host, port and an API key as token)",
        flush=True,
    )
    return RunningNode(server, thread, url)
