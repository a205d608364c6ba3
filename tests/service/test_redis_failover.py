"""Redis failing over under a running job, and a job whose message Redis lost.

- A private Redis made a replica of nowhere for a few seconds mid-job, three times (every write
  answered READONLY, as in a failover: ``replicaof`` elsewhere, then ``replicaof no one``): both
  workers reconnect instead of exiting, and the job finishes with every pair written once.
- A match job some of whose pair steps are gone from the queue (deleted here, as a Redis restarted
  without them would lose them) while its worker runs: the job is left running with nothing to
  move it, and the sweep dispatches it again within two periods, no process restarted.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest
import redis

from .harness import Deployment, PrivateRedis, database_pairs, upload, wait_job

pytestmark = pytest.mark.chaos

GROUND = ["ground_00.png", "ground_01.png", "ground_02.png", "ground_03.png"]
ALL_PAIRS = sorted((a, b) for i, a in enumerate(GROUND) for b in GROUND[i + 1 :])
LEASE = "10"  # s: beats every 1.7 s, a sweep every 10 s


def test_a_few_seconds_of_read_only_redis_mid_job_strand_nothing(
    tmp_path_factory: pytest.TempPathFactory, scene: Path, tmp_path: Path
) -> None:
    root = tmp_path_factory.mktemp("redis-readonly")
    rs = PrivateRedis(root / "redis")
    rs.start()
    d = Deployment(root, rs.url, GEOMATCH_WORKER_LEASE=LEASE, GEOMATCH_LOCK_TIMEOUT="15")
    try:
        d.start_server()
        workers = [d.start_worker(), d.start_worker()]
        c = d.client(d.create_key("readonly"))
        pid = c.post("/v1/projects", json={"name": "readonly"}).json()["id"]
        assert upload(c, pid, [scene / "images" / n for n in GROUND], "ground").status_code == 201
        job_id = c.post(f"/v1/projects/{pid}/match", json={"resize": 320}).json()["job_id"]
        job = wait_job(c, job_id, timeout=180, until=lambda j: j["progress"]["done"] >= 1)
        assert job["state"] == "running", (job, d.logs())

        r = redis.Redis.from_url(rs.url)
        # three failovers of 3 s, 4 s apart: one of them meets a step publishing the next pair, or
        # acknowledging its own (the probe's workers exited there)
        for _ in range(3):
            r.replicaof("127.0.0.1", str(rs.port + 1))  # a master that is not there: writes are READONLY
            with pytest.raises(redis.ReadOnlyError):
                r.set("probe", "1")
            time.sleep(3)
            r.replicaof("NO", "ONE")
            time.sleep(4)

        job = wait_job(c, job_id, timeout=240)
        assert job["state"] == "succeeded", (job, d.logs())
        assert all(w.poll() is None for w in workers), d.logs()  # neither worker exited
        assert "Unrecoverable error" not in d.logs(tail=10**7)
        pairs = database_pairs(c, pid, tmp_path / "db.db")
        assert pairs == ALL_PAIRS, (pairs, d.logs())  # every pair, each once
        rows = d.metadata("SELECT COUNT(*), SUM(done) FROM job_pairs WHERE job_id = ?", job_id)
        assert rows == [(len(ALL_PAIRS), len(ALL_PAIRS))], rows
        # the deployment is whole afterwards: another job runs
        again = c.post(f"/v1/projects/{pid}/reconstruct").json()["job_id"]
        assert wait_job(c, again, timeout=240)["state"] == "succeeded", d.logs()
    finally:
        d.stop()
        rs.stop()


def test_a_job_whose_steps_redis_lost_is_dispatched_again_by_the_sweep(
    tmp_path_factory: pytest.TempPathFactory, scene: Path, redis_url: str, tmp_path: Path
) -> None:
    root = tmp_path_factory.mktemp("sweep")
    # four pair steps handed out at a time: one runs, one is prefetched, two wait in the queue
    d = Deployment(root, redis_url, GEOMATCH_WORKER_LEASE=LEASE, GEOMATCH_PAIRS_IN_FLIGHT="4")
    try:
        d.start_server()
        worker = d.start_worker()
        c = d.client(d.create_key("sweep"))
        pid = c.post("/v1/projects", json={"name": "sweep"}).json()["id"]
        assert upload(c, pid, [scene / "images" / n for n in GROUND], "ground").status_code == 201
        r = redis.Redis.from_url(redis_url)
        queue = f"{d.prefix}{d.env['GEOMATCH_QUEUE']}"
        job_id = c.post(f"/v1/projects/{pid}/match", json={"resize": 320}).json()["job_id"]
        deadline = time.monotonic() + 120
        lost = 0
        while not lost and time.monotonic() < deadline:
            lost = r.llen(queue)
            time.sleep(0.01)
        assert lost and r.delete(queue) == 1, d.logs()
        t0 = time.monotonic()
        job = wait_job(c, job_id, timeout=240)
        assert job["state"] == "succeeded", (job, d.logs())
        assert worker.poll() is None
        assert "left without a step" in d.logs(tail=10**7), d.logs()
        assert database_pairs(c, pid, tmp_path / "db.db") == ALL_PAIRS
        print(f"{lost} lost step(s): the job succeeded {time.monotonic() - t0:.0f} s after the loss")
    finally:
        d.stop()
