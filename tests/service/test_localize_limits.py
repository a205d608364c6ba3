"""A tenant's localize requests within its storage quota and its cap of unfinished heavy jobs, on
both metadata stores: the photos a localize job stages count against the stored bytes quota (for
the next localize and for image uploads alike), and the localize and reconstruct jobs a tenant has
unfinished are capped (429 with Retry-After, gRPC RESOURCE_EXHAUSTED). Nothing of a refused request
is kept.

`geomatch serve` in Redis mode with no worker, so every job stays queued (its staged photos on disk)
and what the store holds is exactly what the requests made. The project's model is a stand-in (the
files the API looks for): no job here runs.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import grpc
import httpx
import pytest

from service.clients.grpc_client import ImageSource

from .grpc_harness import GrpcDeployment, error_of, running_grpc
from .harness import metadata_database, noise_png

pytestmark = pytest.mark.service

MiB = 1024 * 1024


@pytest.fixture(params=["sqlite", "postgresql"])
def dep(request: pytest.FixtureRequest, tmp_path: Path, redis_url: str) -> Iterator[GrpcDeployment]:
    with metadata_database(request.param) as url:
        env = {"GEOMATCH_QUOTA_MB": "1", "GEOMATCH_MAX_OPEN_JOBS": "3"}
        if url:
            env["DATABASE_URL"] = url
        with running_grpc(tmp_path / "dep", redis_url, "serve", **env) as d:
            yield d


def localize(c: httpx.Client, pid: str, name: str, data: bytes) -> httpx.Response:
    return c.post(
        f"/v1/projects/{pid}/localize", files=[("files", (name, data, "image/png"))], data={"wait": "0"}
    )


def staged(dep: GrpcDeployment, pid: str) -> list[str]:
    return sorted(p.name for p in (dep.home / "projects" / pid / "localize").glob("*/*"))


def test_staged_photos_count_against_the_quota_and_open_jobs_are_capped(dep: GrpcDeployment) -> None:
    key = dep.create_key("flood")
    c = dep.client(key)
    pid = str(c.post("/v1/projects", json={"name": "flood"}).json()["id"])
    big = [noise_png(seed, side=300) for seed in range(5)]  # ~270 kB each
    assert all(0.25 * MiB < len(b) < 0.3 * MiB for b in big), [len(b) for b in big]
    files = [("files", (f"{i}.png", big[i], "image/png")) for i in range(2)]
    assert c.post(f"/v1/projects/{pid}/images", files=files).status_code == 201
    model = dep.home / "projects" / pid / "model"
    (model / "sparse" / "0").mkdir(parents=True)
    (model / "summary.json").write_text(json.dumps({"registered": 2}))
    (model / "sparse" / "0" / "images.bin").write_bytes(b"\0" * 8)

    first = localize(c, pid, "a.png", big[2])
    assert first.status_code == 202, first.text
    # stored 2 x 270 kB + staged 270 kB: another 270 kB passes 1 MiB, as a photo or as an image
    r = localize(c, pid, "b.png", big[3])
    assert r.status_code == 403 and "staged for localizing" in r.json()["detail"], r.text
    assert staged(dep, pid) == ["a.png"]
    r = c.post(f"/v1/projects/{pid}/images", files=[("files", ("4.png", big[4], "image/png"))])
    assert r.status_code == 403 and "staged for localizing" in r.json()["detail"], r.text

    # small photos within the quota: two more jobs, and the cap of three unfinished ones is reached
    for i in range(2):
        assert localize(c, pid, f"s{i}.png", noise_png(10 + i, side=16)).status_code == 202
    r = localize(c, pid, "s2.png", noise_png(12, side=16))
    assert r.status_code == 429 and r.headers["retry-after"] == "10", r.text
    assert "3 unfinished localize and reconstruct jobs" in r.json()["detail"], r.text
    with dep.grpc_client(key, timeout=30) as g:
        code, message = error_of(
            lambda: g.localize(pid, [ImageSource("s2.png", data=noise_png(12, side=16))])
        )
    assert code == grpc.StatusCode.RESOURCE_EXHAUSTED and "GEOMATCH_MAX_OPEN_JOBS" in message, message
    assert staged(dep, pid) == ["a.png", "s0.png", "s1.png"]
    jobs = c.get(f"/v1/projects/{pid}/jobs").json()["jobs"]
    assert [j["kind"] for j in jobs] == ["localize"] * 3 and all(j["state"] == "queued" for j in jobs)

    # a cancelled job holds neither a place nor its bytes
    assert c.delete(f"/v1/jobs/{first.json()['job_id']}").status_code in (200, 202)
    r = localize(c, pid, "b.png", big[3])
    assert r.status_code == 202, r.text
