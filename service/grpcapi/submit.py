"""``geomatch submit IMAGES --grpc``: the batch client's flow over gRPC.

Same steps and output as the HTTP flow (``service/submit.py``): create a project, upload, match with
a reconstruction queued behind it, follow both jobs, download and unpack the model. Uploads go
as streams of a few images each: one stream per folder would make a late failure resend it all,
one per image would pay a round trip each. Re-sending is safe (same bytes, same image), so a batch
that meets UNAVAILABLE is sent again.
"""

from __future__ import annotations

import argparse
import sys
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc

from geomatch.options import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_UNREACHABLE

from ..submit import submit_inputs
from .client import GrpcClient, ImageSource, to_dict
from .pb import pb2

BATCH_BYTES = 64 * 1024 * 1024
BATCH_IMAGES = 16
RETRIES = 4
CLIENT_ERRORS = {
    grpc.StatusCode.INVALID_ARGUMENT,
    grpc.StatusCode.NOT_FOUND,
    grpc.StatusCode.UNAUTHENTICATED,
    grpc.StatusCode.RESOURCE_EXHAUSTED,
    grpc.StatusCode.FAILED_PRECONDITION,
}
STATE = {v: k for k, v in pb2.JobState.items()}


def batches(images: list[ImageSource]) -> Iterator[list[ImageSource]]:
    batch: list[ImageSource] = []
    size = 0
    for img in images:
        if batch and (len(batch) >= BATCH_IMAGES or size + img.size() > BATCH_BYTES):
            yield batch
            batch, size = [], 0
        batch.append(img)
        size += img.size()
    if batch:
        yield batch


def _upload(client: GrpcClient, pid: str, batch: list[ImageSource], bar: Any) -> None:
    sent = [0]

    def count(n: int) -> None:
        sent[0] += n
        bar.update(n)

    for attempt in range(RETRIES + 1):
        sent[0] = 0
        try:
            client.upload(pid, batch, on_bytes=count)
            return
        except grpc.RpcError as e:
            bar.update(-sent[0])  # the batch starts over
            if e.code() != grpc.StatusCode.UNAVAILABLE or attempt == RETRIES:
                raise
            time.sleep(min(30.0, 2.0**attempt))


def submit(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    inputs = submit_inputs(args)
    if isinstance(inputs, int):
        return inputs
    files, captures = inputs
    wait = args.wait or args.out is not None
    quiet = args.no_progress
    server = args.grpc_server
    client = GrpcClient(server, args.key)
    try:
        project = client.create_project(args.name or args.images.resolve().name)
        pid = project.id
        print(f"project {pid}: uploading {len(files)} images to {server} (gRPC)", file=sys.stderr)
        images = [ImageSource.of(p, captures[p]) for p in files]
        with tqdm(
            total=sum(i.size() for i in images), unit="B", unit_scale=True, desc="upload", disable=quiet
        ) as bar:
            for batch in batches(images):
                _upload(client, pid, batch, bar)
        accepted = client.submit_matching(
            pid,
            pair_spec=args.pairs,
            method=args.method,
            resize=args.resize,
            reconstruct=True,
            mapper=args.mapper,
        )
        match_id, recon_id = accepted.job.id, accepted.reconstruct_job.id
        print(f"match job {match_id}, then reconstruct job {recon_id}", file=sys.stderr)
        if not wait:
            print(f"follow with: WatchJob {{job_id: {recon_id}}} on {server}")
            print(pid)
            return 0
        job: Any = None
        for job_id, desc in ((match_id, "match"), (recon_id, "reconstruct")):
            with tqdm(total=0, unit="pair" if desc == "match" else "step", desc=desc, disable=quiet) as bar:

                def show(j: Any, bar: Any = bar) -> None:
                    bar.total, bar.n = j.progress.total, j.progress.done
                    bar.set_postfix_str(STATE[j.state].removeprefix("JOB_STATE_").lower())
                    bar.refresh()

                job = client.wait(job_id, show)
            if job.state != pb2.JOB_STATE_SUCCEEDED:
                state = STATE[job.state].removeprefix("JOB_STATE_").lower()
                print(f"geomatch: {desc} job {job_id} {state}: {job.error}", file=sys.stderr)
                return EXIT_FAILED
        summary = to_dict(job.result)
        print(
            f"registered {summary.get('registered', 0):.0f}/{summary.get('images', 0):.0f} images, "
            f"{summary.get('points3D', 0):.0f} 3D points, "
            f"mean track length {summary.get('mean_track_length', 0):.2f}, "
            f"mean reprojection error {summary.get('mean_reprojection_error', 0):.3f} px"
        )
        if args.out is not None:
            _, zpath = client.download_model(pid, Path(args.out) / "model.zip")
            with zipfile.ZipFile(zpath) as z:
                z.extractall(args.out)
            zpath.unlink()
            print(
                f"model: {args.out}/sparse/0 (binary + text), {args.out}/points.ply, {args.out}/summary.json"
            )
        print(pid)
        return 0
    except grpc.RpcError as e:
        code = e.code()
        if code == grpc.StatusCode.UNAVAILABLE:
            print(f"geomatch: error: {server} unreachable ({e.details()})", file=sys.stderr)
            return EXIT_UNREACHABLE
        print(f"geomatch: error: {code.name}: {e.details()}", file=sys.stderr)
        return EXIT_BAD_INPUT if code in CLIENT_ERRORS else EXIT_FAILED
    finally:
        client.close()
