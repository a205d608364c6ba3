"""``geomatch submit``: the batch client. What both transports share (which files go, with which
capture) is here, with the HTTP flow; ``service.grpcapi.submit`` is the gRPC flow.
"""

from __future__ import annotations

import argparse
import fnmatch
import sys
import zipfile
from pathlib import Path
from typing import Any

from geomatch.options import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_UNREACHABLE, IMAGE_SUFFIXES


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


def submit_http(args: argparse.Namespace) -> int:
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
