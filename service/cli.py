"""The service's client-side commands of ``geomatch``: keys, submit.

``register`` adds them to the command's parser (``geomatch_app.cli``); everything heavy (httpx, grpc) is
imported inside the command that needs it. The commands that run servers or workers (serve,
grpc-serve, worker) put a service together with a job runner: they live in the composition root.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

from geomatch.options import EXIT_BAD_INPUT, add_arguments
from geomatch_core.errors import NotFound

from .grpcapi import cli as grpc_cli  # light: grpc is imported by its commands only


def register(sub: Any) -> None:
    k = sub.add_parser("keys", help="API keys")
    ks = k.add_subparsers(dest="keys_command", required=True)
    kc = ks.add_parser("create", help="print a new key for TENANT (created on first use)")
    kc.add_argument("tenant")
    kc.set_defaults(func=cmd_keys_create)
    ks.add_parser("list", help="keys by tenant (prefixes only)").set_defaults(func=cmd_keys_list)
    kr = ks.add_parser("revoke", help="revoke the key(s) starting with PREFIX")
    kr.add_argument("prefix")
    kr.set_defaults(func=cmd_keys_revoke)

    b = sub.add_parser("submit", help="batch client: upload a folder, match, reconstruct, download the model")
    b.add_argument("images", type=Path, help="folder of images (searched recursively; names must be unique)")
    b.add_argument(
        "--server",
        default=os.environ.get("GEOMATCH_SERVER", "http://127.0.0.1:8000"),
        help="API base URL (or $GEOMATCH_SERVER)",
    )
    b.add_argument("--key", default=os.environ.get("GEOMATCH_KEY"), help="API key (or $GEOMATCH_KEY)")
    air = b.add_mutually_exclusive_group()
    air.add_argument("--aerial", metavar="GLOB", help="aerial images by name pattern (others: ground)")
    air.add_argument("--aerial-list", type=Path, metavar="FILE", help="aerial names, one per line")
    b.add_argument("--name", help="project name (default: the folder's name)")
    add_arguments(b, ("pairs", "method", "resize", "mapper"), server=True)
    b.add_argument("--wait", action="store_true", help="wait for the model (implied by --out)")
    b.add_argument("--out", type=Path, help="unpack the model here: sparse/0/, points.ply, summary.json")
    b.add_argument("--no-progress", action="store_true")
    grpc_cli.add_submit_options(b)
    b.set_defaults(func=cmd_submit)


# -- keys ------------------------------------------------------------------------------------------
def _store() -> Any:
    from geomatch_core.config import Settings
    from geomatch_core.store import MetadataStore

    store = MetadataStore(Settings.from_env().database_url)
    store.create_all()
    return store


def cmd_keys_create(args: argparse.Namespace) -> int:
    from .auth import create_key

    try:
        key = create_key(_store(), args.tenant)
    except ValueError as e:
        print(f"geomatch: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(key)
    print(f"(tenant {args.tenant!r}; shown once, store it now)", file=sys.stderr)
    return 0


def cmd_keys_list(args: argparse.Namespace) -> int:
    from .auth import list_keys

    for k in list_keys(_store()):
        state = f"revoked {k['revoked_at']}" if k["revoked_at"] else "active"
        print(f"{k['tenant']}\t{k['prefix']}...\t{k['created_at']}\t{state}")
    return 0


def cmd_keys_revoke(args: argparse.Namespace) -> int:
    from .auth import revoke

    try:
        n = revoke(_store(), args.prefix)
    except NotFound as e:
        print(f"geomatch: error: {e.message}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(f"revoked {n} key(s)")
    return 0


# -- submit ----------------------------------------------------------------------------------------
def cmd_submit(args: argparse.Namespace) -> int:
    from .clients.submit import HttpSubmitClient, SubmitClient, submit

    def connect() -> SubmitClient:
        if args.grpc:
            from .clients.grpc_submit import GrpcSubmitClient

            return GrpcSubmitClient(args.grpc_server, args.key)
        return HttpSubmitClient(args.server, args.key)

    return submit(args, connect)
