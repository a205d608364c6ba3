"""``geomatch submit``: the batch client. One flow (:func:`submit`: check the inputs, create a
project, upload, match with a reconstruction queued behind it, follow both jobs, download and
unpack the model) over a small client interface, :class:`SubmitClient`, with two implementations:
:class:`HttpSubmitClient` here (over ``service.clients.rest``) and ``GrpcSubmitClient`` in
``service.clients.grpc_submit``. So both transports refuse the same input, print the same lines and
exit with the same codes.
"""

from __future__ import annotations

import argparse
import fnmatch
import sys
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from geomatch.options import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_UNREACHABLE, IMAGE_SUFFIXES


# -- the inputs ------------------------------------------------------------------------------------
def submit_inputs(args: argparse.Namespace) -> tuple[list[Path], dict[Path, str]] | int:
    """The images to send and their capture types, or the exit code of a bad request (said on
    stderr), whatever the transport."""
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


# -- the client interface --------------------------------------------------------------------------
@dataclass(frozen=True)
class JobStatus:
    """A job as the flow reads it, whatever the transport: state is the API's word (``running``,
    ``succeeded``, ``failed`` ...), result the job's result as plain JSON values."""

    state: str
    done: int
    total: int
    error: str | None = None
    result: dict[str, Any] = field(default_factory=dict)


class SubmitClient(Protocol):
    """What the batch flow needs of a transport. Errors are the transport's own exceptions:
    :meth:`failure` turns those it knows into a message and an exit code."""

    where: str  # the server, as the upload line names it

    def create_project(self, name: str) -> str: ...

    def upload(
        self, project_id: str, images: list[tuple[Path, str]], on_bytes: Callable[[int], object]
    ) -> None:
        """Every (path, capture); ``on_bytes`` follows the bytes sent (negative: sent again)."""

    def match_and_reconstruct(
        self, project_id: str, pairs: str | None, method: str | None, resize: int | None, mapper: str | None
    ) -> tuple[str, str]:
        """Queue a match job with a reconstruction behind it: (match job id, reconstruct job id)."""

    def follow_hint(self, job_id: str) -> str: ...

    def wait(self, job_id: str, on_update: Callable[[JobStatus], object]) -> JobStatus: ...

    def download(self, project_id: str, dest: Path) -> Path:
        """The model as a zip at ``dest``."""

    def failure(self, error: Exception) -> tuple[str, int] | None:
        """(message, exit code) for an error of this transport; None for any other."""

    def close(self) -> None: ...


def submit(args: argparse.Namespace, connect: Callable[[], SubmitClient]) -> int:
    """The batch flow over the client ``connect`` opens (once the inputs are known to be good)."""
    from tqdm import tqdm

    inputs = submit_inputs(args)
    if isinstance(inputs, int):
        return inputs
    files, captures = inputs
    wait = args.wait or args.out is not None
    quiet = args.no_progress
    client = connect()
    try:
        pid = client.create_project(args.name or args.images.resolve().name)
        print(f"project {pid}: uploading {len(files)} images to {client.where}", file=sys.stderr)
        total = sum(p.stat().st_size for p in files)
        with tqdm(total=total, unit="B", unit_scale=True, desc="upload", disable=quiet) as bar:
            client.upload(pid, [(p, captures[p]) for p in files], bar.update)
        match_id, recon_id = client.match_and_reconstruct(
            pid, pairs=args.pairs, method=args.method, resize=args.resize, mapper=args.mapper
        )
        print(f"match job {match_id}, then reconstruct job {recon_id}", file=sys.stderr)
        if not wait:
            print(f"follow with: {client.follow_hint(recon_id)}")
            print(pid)
            return 0
        for job_id, desc in ((match_id, "match"), (recon_id, "reconstruct")):
            with tqdm(total=0, unit="pair" if desc == "match" else "step", desc=desc, disable=quiet) as bar:

                def show(job: JobStatus, bar: Any = bar) -> None:
                    bar.total, bar.n = job.total, job.done
                    bar.set_postfix_str(job.state)
                    bar.refresh()

                job = client.wait(job_id, show)
            if job.state != "succeeded":
                print(f"geomatch: {desc} job {job_id} {job.state}: {job.error}", file=sys.stderr)
                return EXIT_FAILED
        summary = job.result
        print(
            f"registered {summary.get('registered', 0):.0f}/{summary.get('images', 0):.0f} images, "
            f"{summary.get('points3D', 0):.0f} 3D points, "
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
    except Exception as e:
        failed = client.failure(e)
        if failed is None:
            raise
        message, code = failed
        print(f"geomatch: error: {message}", file=sys.stderr)
        return code
    finally:
        client.close()


# -- over HTTP -------------------------------------------------------------------------------------
class HttpSubmitClient:
    """:class:`SubmitClient` over the REST client (``service.clients.rest``): one request per image."""

    def __init__(self, server: str, key: str, **options: Any) -> None:
        from .rest import Client

        self.where = server
        self.client = Client(server, key, **options)

    def create_project(self, name: str) -> str:
        return str(self.client.create_project(name)["id"])

    def upload(
        self, project_id: str, images: list[tuple[Path, str]], on_bytes: Callable[[int], object]
    ) -> None:
        for path, capture in images:
            self.client.upload(project_id, path, capture, on_bytes=on_bytes)

    def match_and_reconstruct(
        self, project_id: str, pairs: str | None, method: str | None, resize: int | None, mapper: str | None
    ) -> tuple[str, str]:
        accepted = self.client.match(
            project_id, pairs=pairs, method=method, resize=resize, reconstruct=True, mapper=mapper
        )
        return accepted["job_id"], accepted["reconstruct_job_id"]

    def follow_hint(self, job_id: str) -> str:
        return f"curl -N -H 'Authorization: Bearer ...' {self.where}/v1/jobs/{job_id}/events"

    def wait(self, job_id: str, on_update: Callable[[JobStatus], object]) -> JobStatus:
        def view(job: dict[str, Any]) -> JobStatus:
            progress = job["progress"]
            return JobStatus(
                job["state"], progress["done"], progress["total"], job.get("error"), job.get("result") or {}
            )

        return view(self.client.wait(job_id, lambda job: on_update(view(job))))

    def download(self, project_id: str, dest: Path) -> Path:
        return self.client.download(project_id, dest)

    def failure(self, error: Exception) -> tuple[str, int] | None:
        import httpx

        from .rest import ApiError

        if isinstance(error, ApiError):
            return str(error), EXIT_BAD_INPUT if 400 <= error.status < 500 else EXIT_FAILED
        if isinstance(error, httpx.TransportError):
            return f"{self.where} unreachable ({error})", EXIT_UNREACHABLE
        return None

    def close(self) -> None:
        self.client.close()
