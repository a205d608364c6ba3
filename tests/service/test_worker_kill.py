"""A worker SIGKILLed in the middle of a match job: nothing is lost, nothing is written twice.

Its own deployment (server, queue and Redis prefix) so no other worker picks the job up. The
visibility timeout is short (15 s) so that Redis hands the dead worker's unacknowledged steps to
the new worker quickly; the lock timeout likewise, in case the kill lands inside a write. With no
worker left, /readyz answers 503 once the dead worker's lease (30 s) has lapsed.
"""

from __future__ import annotations

import time
from pathlib import Path

import pycolmap
import pytest

from .harness import Deployment, database_pairs, ground_match_under_kill, wait_job

pytestmark = pytest.mark.chaos

GROUND = ["ground_00.png", "ground_01.png", "ground_02.png", "ground_03.png"]


def test_killed_worker_loses_nothing_and_writes_nothing_twice(
    tmp_path_factory: pytest.TempPathFactory, redis_url: str, scene: Path, tmp_path: Path
) -> None:
    with ground_match_under_kill(tmp_path_factory.mktemp("kill"), redis_url, scene, GROUND, "kill") as k:
        d, first, c, pid, job_id = k.d, k.worker, k.c, k.pid, k.job_id
        job = wait_job(c, job_id, timeout=300, until=lambda j: j["progress"]["done"] >= 2)
        Deployment.kill(first)  # SIGKILL to the worker and its pool child, mid-job
        assert first.returncode is not None
        job = c.get(f"/v1/jobs/{job_id}").json()
        assert job["state"] == "running" and 2 <= job["progress"]["done"] < 6, job
        time.sleep(3)
        stalled = c.get(f"/v1/jobs/{job_id}").json()
        assert stalled["state"] == "running" and stalled["progress"] == job["progress"]  # nobody works

        # with no worker left, readiness says so once the dead one's lease has lapsed
        deadline = time.monotonic() + 120
        while (ready := c.get("/readyz")).status_code == 200 and time.monotonic() < deadline:
            time.sleep(0.5)
        assert ready.status_code == 503, ready.text
        assert ready.json()["checks"]["workers"].startswith("error: no worker heard from"), ready.text

        d.start_worker()
        assert c.get("/readyz").status_code == 200  # start_worker returns once the worker beats
        job = wait_job(c, job_id, timeout=400)
        assert job["state"] == "succeeded", (job, d.logs())
        assert job["progress"] == {"done": 6, "total": 6}
        assert d.metadata("SELECT count(*), sum(done) FROM job_pairs WHERE job_id = ?", job_id) == [(6, 6)]

        expected = sorted((a, b) for i, a in enumerate(GROUND) for b in GROUND[i + 1 :])
        assert database_pairs(c, pid, tmp_path / "db.db") == expected  # every pair, each exactly once
        db = pycolmap.Database.open(str(tmp_path / "db.db"))
        try:
            assert db.num_images() == 4 and db.num_matched_image_pairs() == 6
        finally:
            db.close()
