"""The service's commands of ``geomatch``: serve, worker, keys, submit.

``register`` adds them to the library's argparse; everything heavy (FastAPI, Celery, httpx) is
imported inside the command that needs it, so ``geomatch match`` pays nothing for them.
"""

from __future__ import annotations

import argparse
import fnmatch
import os
import sys
import zipfile
from pathlib import Path
from typing import Any

from geomatch.options import IMAGE_SUFFIXES, add_arguments

EXIT_FAILED, EXIT_BAD_INPUT, EXIT_UNREACHABLE = 1, 2, 3
KEY_FILE = "api-key.txt"


def register(sub: Any) -> None:
    from .grpcapi import cli as grpc_cli  # light: grpc is imported by its commands only

    s = sub.add_parser(
        "serve",
        help="run the HTTP API (embedded default: SQLite, local files, jobs in-process; REDIS_URL: Celery)",
    )
    s.add_argument("--host", default="127.0.0.1")
    s.add_argument("--port", type=int, default=8000)
    grpc_cli.add_serve_options(s)
    s.set_defaults(func=cmd_serve)
    grpc_cli.register(sub)

    w = sub.add_parser("worker", help="run a Celery worker for the service's jobs (needs REDIS_URL)")
    w.add_argument("--concurrency", type=int, default=1, help="steps run at once (one process each)")
    w.add_argument("--pool", choices=("prefork", "solo", "threads"), default="prefork")
    w.add_argument("--loglevel", default="INFO")
    w.set_defaults(func=cmd_worker)

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


def _settings() -> Any:
    from .config import Settings

    return Settings.from_env()


# -- serve -----------------------------------------------------------------------------------------
def cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from . import logs
    from .api import create_app
    from .bootstrap import build_service, close_service

    logs.configure()
    settings = _settings()
    service = build_service(settings)
    from .grpcapi.cli import start_beside_http

    try:
        grpc_server = start_beside_http(service, args)  # same Service: one job runner, one config
    except SystemExit:
        close_service(service)
        raise
    base = f"http://{args.host}:{args.port}"
    if settings.embedded:
        key = embedded_key(service.store, settings.home)
        print(
            f"geomatch API on {base} (OpenAPI: {base}/docs), embedded mode: jobs run in this process, "
            f"state under {settings.home}",
            flush=True,
        )
        print(f"API key (tenant 'local'): {key}", flush=True)
        print(f"  curl -H 'Authorization: Bearer {key}' {base}/v1/projects", flush=True)
    else:
        print(
            f"geomatch API on {base} (OpenAPI: {base}/docs), jobs go to Celery queue '{settings.queue}' "
            "on REDIS_URL: start workers with `geomatch worker`; keys with `geomatch keys create TENANT`",
            flush=True,
        )
    server = uvicorn.Server(
        uvicorn.Config(create_app(service), host=args.host, port=args.port, log_level="warning")
    )
    try:
        server.run()
    finally:
        if grpc_server is not None:
            grpc_server.stop()
        close_service(service)
    return 0


def embedded_key(store: Any, home: Path) -> str:
    """The embedded server's ready-to-use key: made once, kept in GEOMATCH_HOME/api-key.txt (0600),
    shown again at every start (only the digest is in the database)."""
    from .auth import create_key, key_is_valid

    path = home / KEY_FILE
    if path.is_file():
        key = path.read_text().strip()
        if key_is_valid(store, key):
            return key
    key = create_key(store, "local")
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(key + "\n")
    return key


# -- worker ----------------------------------------------------------------------------------------
def cmd_worker(args: argparse.Namespace) -> int:
    import socket

    from . import logs
    from .storage import Storage
    from .store import MetadataStore

    settings = _settings()
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
    app = make_app(settings)
    register_tasks(app)
    from workers.pairmatch import register as register_match_two  # gRPC MatchPair's step

    register_match_two(app)
    app.worker_main(
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


# -- keys ------------------------------------------------------------------------------------------
def _store() -> Any:
    from .store import MetadataStore

    store = MetadataStore(_settings().database_url)
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
    from .errors import NotFound

    try:
        n = revoke(_store(), args.prefix)
    except NotFound as e:
        print(f"geomatch: error: {e.message}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(f"revoked {n} key(s)")
    return 0


# -- submit ----------------------------------------------------------------------------------------
def submit_inputs(args: argparse.Namespace) -> tuple[list[Path], dict[Path, str]] | int:
    """The images to send and their capture types, or the exit code of a bad request: shared by
    the HTTP and the gRPC batch clients so that both refuse the same input the same way."""
    if not args.key:
        print("geomatch: error: no API key: pass --key or set GEOMATCH_KEY", file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        files = _collect(args.images)
        return files, _captures(files, args.images, args)
    except (ValueError, OSError) as e:
        print(f"geomatch: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT


def _collect(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise ValueError(f"{folder}: not a directory")
    files = sorted(p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if len(files) < 2:
        raise ValueError(f"{folder}: found {len(files)} image(s); need at least 2")
    seen: dict[str, Path] = {}
    for p in files:
        if p.name in seen:
            raise ValueError(f"{p} and {seen[p.name]}: the service keeps flat names, and these two collide")
        seen[p.name] = p
    return files


def _captures(files: list[Path], folder: Path, args: argparse.Namespace) -> dict[Path, str]:
    if args.aerial is None and args.aerial_list is None:
        return {p: "auto" for p in files}
    if args.aerial_list is not None:
        listed = {ln.strip() for ln in args.aerial_list.read_text().splitlines() if ln.strip()}
        names = {p.name for p in files} | {p.relative_to(folder).as_posix() for p in files}
        unknown = sorted(listed - names)
        if unknown:
            raise ValueError(f"--aerial-list names images not in {folder}: {', '.join(unknown[:5])}")

        def is_aerial(p: Path) -> bool:
            return p.name in listed or p.relative_to(folder).as_posix() in listed
    else:

        def is_aerial(p: Path) -> bool:
            rel = p.relative_to(folder).as_posix()
            return fnmatch.fnmatch(rel, args.aerial) or fnmatch.fnmatch(p.name, args.aerial)

    return {p: "aerial" if is_aerial(p) else "ground" for p in files}


def cmd_submit(args: argparse.Namespace) -> int:
    if args.grpc:
        from .grpcapi.cli import cmd_submit as submit_grpc

        return submit_grpc(args)
    import httpx
    from tqdm import tqdm

    from .client import ApiError, Client

    inputs = submit_inputs(args)
    if isinstance(inputs, int):
        return inputs
    files, captures = inputs
    wait = args.wait or args.out is not None
    client = Client(args.server, args.key)
    quiet = args.no_progress
    try:
        project = client.create_project(args.name or args.images.resolve().name)
        pid = project["id"]
        print(f"project {pid}: uploading {len(files)} images to {args.server}", file=sys.stderr)
        total = sum(p.stat().st_size for p in files)
        with tqdm(total=total, unit="B", unit_scale=True, desc="upload", disable=quiet) as bar:
            for p in files:
                client.upload(pid, p, captures[p], on_bytes=bar.update)
        accepted = client.match(
            pid,
            pairs=args.pairs,
            method=args.method,
            resize=args.resize,
            reconstruct=True,
            mapper=args.mapper,
        )
        match_id, recon_id = accepted["job_id"], accepted["reconstruct_job_id"]
        print(f"match job {match_id}, then reconstruct job {recon_id}", file=sys.stderr)
        if not wait:
            print(
                f"follow with: curl -N -H 'Authorization: Bearer ...' {args.server}/v1/jobs/{recon_id}/events"
            )
            print(pid)
            return 0
        for job_id, desc in ((match_id, "match"), (recon_id, "reconstruct")):
            with tqdm(total=0, unit="pair" if desc == "match" else "step", desc=desc, disable=quiet) as bar:

                def show(job: dict[str, Any], bar: Any = bar) -> None:
                    bar.total = job["progress"]["total"]
                    bar.n = job["progress"]["done"]
                    bar.set_postfix_str(job["state"])
                    bar.refresh()

                job = client.wait(job_id, show)
            if job["state"] != "succeeded":
                print(f"geomatch: {desc} job {job_id} {job['state']}: {job.get('error')}", file=sys.stderr)
                return EXIT_FAILED
        summary = job.get("result") or {}
        print(
            f"registered {summary.get('registered')}/{summary.get('images')} images, "
            f"{summary.get('points3D')} 3D points, "
            f"mean track length {summary.get('mean_track_length', 0):.2f}, "
            f"mean reprojection error {summary.get('mean_reprojection_error', 0):.3f} px"
        )
        if args.out is not None:
            zpath = client.download(pid, args.out / "model.zip")
            with zipfile.ZipFile(zpath) as z:
                z.extractall(args.out)
            zpath.unlink()
            print(
                f"model: {args.out}/sparse/0 (binary + text), {args.out}/points.ply, {args.out}/summary.json"
            )
        print(pid)
        return 0
    except ApiError as e:
        print(f"geomatch: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT if 400 <= e.status < 500 else EXIT_FAILED
    except httpx.TransportError as e:
        print(f"geomatch: error: {args.server} unreachable ({e})", file=sys.stderr)
        return EXIT_UNREACHABLE
    finally:
        client.close()
