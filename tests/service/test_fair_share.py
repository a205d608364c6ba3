"""One tenant's huge match must not hold up another tenant's small one, nor the server.

Tenant A uploads 400 tiny images. Its exhaustive match (79,800 pairs) is refused at once with the
limit and how to split the work; a plan under the per-job limit (``sequential:50``, 18,725 pairs)
is admitted and runs. Tenant B's two-image match, sent while A's runs, must finish within two
minutes, and ``/healthz`` must answer within a second throughout: A's job keeps only a window of
pair steps in the queue, so B's steps wait behind a few of A's, not behind all of them. A second
huge match of A is past the tenant's queued pairs (429 with Retry-After), and cancelling A stops
its pairs within seconds. In embedded mode (the server's own thread) and with Redis and two
Celery workers.
"""

from __future__ import annotations

import time
from pathlib import Path

import httpx
import pytest

from .harness import TERMINAL, Deployment, noise_png, noise_project

pytestmark = pytest.mark.service

IMAGES = 400
QUEUED_LIMIT = 30_000  # one admitted sequential:50 (18,725 pairs) fits, a second does not
B_WITHIN_S = 120


def upload_many(c: httpx.Client, pid: str, n: int) -> None:
    for start in range(0, n, 100):
        files = [
            ("files", (f"{i:04d}.png", noise_png(i, 24), "image/png")) for i in range(start, start + 100)
        ]
        assert c.post(f"/v1/projects/{pid}/images", files=files).status_code == 201


def wait_for(c: httpx.Client, job_id: str, ok: object, timeout: float) -> dict[str, object]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = c.get(f"/v1/jobs/{job_id}").json()
        if ok(job) or job["state"] in TERMINAL:  # type: ignore[operator]
            return dict(job)
        time.sleep(0.3)
    raise TimeoutError(f"job {job_id} not there after {timeout}s: {job}")


@pytest.mark.parametrize("mode", ["embedded", "redis"])
def test_a_huge_match_leaves_another_tenants_small_one_its_turn(
    tmp_path: Path, redis_url: str, mode: str
) -> None:
    d = Deployment(
        tmp_path, redis_url if mode == "redis" else None, GEOMATCH_MAX_QUEUED_PAIRS=str(QUEUED_LIMIT)
    )
    try:
        d.start_server()
        if mode == "redis":
            d.start_worker()
            d.start_worker()
        a, b = d.client(d.create_key("fair-a")), d.client(d.create_key("fair-b"))
        pa = str(a.post("/v1/projects", json={"name": "huge"}).json()["id"])
        upload_many(a, pa, IMAGES)

        r = a.post(f"/v1/projects/{pa}/match", json={"pairs": "exhaustive"})
        assert r.status_code == 422, r.text
        assert "79800 pairs" in r.json()["detail"] and "GEOMATCH_MAX_PAIRS_PER_JOB" in r.json()["detail"]

        r = a.post(f"/v1/projects/{pa}/match", json={"pairs": "sequential:50", "resize": 320})
        assert r.status_code == 202, r.text
        job_a = r.json()["job_id"]
        running = wait_for(a, job_a, lambda j: j["progress"]["done"] >= 2, 180)
        assert running["state"] == "running", running
        assert running["progress"]["total"] == 18_725

        pb = noise_project(b, "small")
        t0 = time.monotonic()
        job_b = b.post(f"/v1/projects/{pb}/match", json={"resize": 320}).json()["job_id"]
        slowest = 0.0
        while (jb := b.get(f"/v1/jobs/{job_b}").json())["state"] not in TERMINAL:
            assert time.monotonic() - t0 < B_WITHIN_S, f"B still {jb['state']} {jb['progress']}\n{d.logs()}"
            h0 = time.monotonic()
            assert httpx.get(f"{d.url}/healthz", timeout=5).status_code == 200
            slowest = max(slowest, time.monotonic() - h0)
            time.sleep(0.3)
        took = time.monotonic() - t0
        ja = a.get(f"/v1/jobs/{job_a}").json()
        print(
            f"\n[fair share, {mode}] B's 2-image match {took:.1f}s beside A's "
            f"{ja['progress']['total']} pairs ({ja['progress']['done']} done), "
            f"/healthz at most {slowest * 1000:.0f} ms"
        )
        assert jb["state"] == "succeeded", jb
        assert slowest < 1.0, slowest
        assert ja["state"] == "running" and ja["progress"]["done"] < 18_725, ja  # B did not wait for A

        r = a.post(f"/v1/projects/{pa}/match", json={"pairs": "sequential:50", "resize": 320})
        assert r.status_code == 429, r.text
        assert "GEOMATCH_MAX_QUEUED_PAIRS" in r.json()["detail"] and int(r.headers["Retry-After"]) > 0

        assert a.delete(f"/v1/jobs/{job_a}").json()["state"] == "cancelled"
        time.sleep(5.0)  # a pair step already running ends; the steps queued behind it skip
        settled = a.get(f"/v1/jobs/{job_a}").json()["progress"]["done"]
        time.sleep(5.0)
        assert a.get(f"/v1/jobs/{job_a}").json()["progress"]["done"] == settled
        # the window: A never had more than a few pair steps in the queue
        assert d.metadata("SELECT dispatched - done FROM jobs WHERE id = ?", job_a)[0][0] <= 4
    finally:
        d.stop()
