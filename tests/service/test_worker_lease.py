"""Two workers, the busy one SIGKILLed: the other finishes the job on its own, long before the
broker's visibility timeout (left at its default hour here), because the dead worker's leases
lapse with its beats and the survivor's reaper puts its steps back in the queue
(docs/service.md, worker leases). Each pair is written once, whichever worker wrote it.

The lock timeout is short (15 s) as in the other kill tests: a kill inside a write leaves the
project's writer lock to expire, which is not what these tests measure. The bounds are liveness
deadlines for loaded CPUs, not speed targets.
"""

from __future__ import annotations

import contextlib
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pycolmap
import pytest
import redis

from .harness import Deployment, database_pairs, reconstruct_held_mid_job, upload, wait_job

pytestmark = pytest.mark.chaos

GROUND = ["ground_00.png", "ground_01.png", "ground_02.png", "ground_03.png"]
ALL_PAIRS = sorted((a, b) for i, a in enumerate(GROUND) for b in GROUND[i + 1 :])
RESUMED_WITHIN_S = 120  # after the kill
# shorter than the default 30 s so the wait for the dead worker's lease to lapse is short; what is
# tested (the lease, not the visibility timeout, returns its steps) does not depend on its length
LEASE = "10"


@contextlib.contextmanager
def two_workers(root: Path, redis_url: str, scene: Path) -> Iterator[tuple[Deployment, httpx.Client, str]]:
    """A server, two workers and a project holding the four ground images (client, project id)."""
    d = Deployment(root, redis_url, GEOMATCH_LOCK_TIMEOUT="15", GEOMATCH_WORKER_LEASE=LEASE)
    try:
        d.start_server()
        d.start_worker()
        d.start_worker()
        c = d.client(d.create_key("lease"))
        pid = c.post("/v1/projects", json={"name": "lease"}).json()["id"]
        assert upload(c, pid, [scene / "images" / n for n in GROUND], "ground").status_code == 201
        yield d, c, pid
    finally:
        d.stop()


def holders(d: Deployment, r: redis.Redis) -> dict[str, int]:
    """Worker process id -> how many unacknowledged messages it holds (running or prefetched)."""
    unacked = {t.decode() for t in r.zrange(f"{d.prefix}unacked_index", 0, -1)}
    held: dict[str, int] = {}
    for tag, value in r.hgetall(f"{d.prefix}leases").items():
        if tag.decode() in unacked:
            node = value.decode().split("/", 1)[0]  # geomatch-<pid>@<host>
            pid = node.split("@", 1)[0].removeprefix("geomatch-")
            held[pid] = held.get(pid, 0) + 1
    return held


def busy_worker(d: Deployment, r: redis.Redis) -> subprocess.Popen[bytes]:
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        held = holders(d, r)
        for w in d.workers:
            if w.poll() is None and held.get(str(w.pid)):
                return w
        time.sleep(0.1)
    raise AssertionError(f"no worker holds a step: {holders(d, r)}\n{d.logs()}")


def assert_each_pair_once(d: Deployment, c, pid: str, job_id: str, db: Path) -> None:
    assert d.metadata("SELECT count(*), sum(done) FROM job_pairs WHERE job_id = ?", job_id) == [(6, 6)]
    assert database_pairs(c, pid, db) == ALL_PAIRS  # every pair, exactly once
    database = pycolmap.Database.open(str(db))
    try:
        assert database.num_images() == 4 and database.num_matched_image_pairs() == 6
    finally:
        database.close()


def survivors_reaped(d: Deployment) -> bool:
    """Whether a survivor's reaper returned the dead worker's steps, waiting for its lease to lapse.

    The job can succeed before that: the victim may have written its pair and died before the
    acknowledgement, and the rest are quick once the models are loaded. Its unacknowledged step is
    still returned once the lease lapses (LEASE), long before the visibility timeout.
    """
    deadline = time.monotonic() + RESUMED_WITHIN_S
    while "held by dead worker" not in d.logs(tail=10**6):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.5)
    return True


def test_busy_worker_killed_mid_match_the_other_finishes(
    tmp_path_factory: pytest.TempPathFactory, redis_url: str, scene: Path, tmp_path: Path
) -> None:
    with two_workers(tmp_path_factory.mktemp("lease-match"), redis_url, scene) as (d, c, pid):
        r = redis.Redis.from_url(redis_url)
        answer = c.post(f"/v1/projects/{pid}/match", json={"resize": 320, "reconstruct": True}).json()
        job_id, follower = answer["job_id"], answer["reconstruct_job_id"]
        wait_job(c, job_id, timeout=300, until=lambda j: j["progress"]["done"] >= 1)
        victim = busy_worker(d, r)
        Deployment.kill(victim)  # the worker and its pool process, holding a pair step
        job = c.get(f"/v1/jobs/{job_id}").json()
        assert job["state"] == "running" and job["progress"]["done"] < 6, job

        job = wait_job(c, job_id, timeout=RESUMED_WITHIN_S)
        assert job["state"] == "succeeded", (job, d.logs())
        assert survivors_reaped(d), d.logs()  # by the lease, not a new worker or the visibility timeout
        rec = wait_job(c, follower, timeout=RESUMED_WITHIN_S)
        assert rec["state"] == "succeeded", (rec, d.logs())
        assert_each_pair_once(d, c, pid, job_id, tmp_path / "db.db")


def test_busy_worker_killed_mid_reconstruct_the_other_finishes(
    tmp_path_factory: pytest.TempPathFactory, redis_url: str, scene: Path, tmp_path: Path
) -> None:
    with two_workers(tmp_path_factory.mktemp("lease-reconstruct"), redis_url, scene) as (d, c, pid):
        r = redis.Redis.from_url(redis_url)
        job_id = c.post(f"/v1/projects/{pid}/match", json={"resize": 320}).json()["job_id"]
        assert wait_job(c, job_id, timeout=600)["state"] == "succeeded", d.logs()

        project = d.home / "projects" / pid
        with reconstruct_held_mid_job(d, c, r, pid) as rec:
            Deployment.kill(busy_worker(d, r))
            assert c.get(f"/v1/jobs/{rec}").json()["state"] == "running"  # killed mid-job, not after

        job = wait_job(c, rec, timeout=RESUMED_WITHIN_S)
        assert job["state"] == "succeeded", (job, d.logs())
        assert survivors_reaped(d), d.logs()
        assert job["result"]["registered"] >= 3, job
        assert_each_pair_once(d, c, pid, job_id, tmp_path / "db.db")
        assert list(project.glob(".work-*")) == []  # the redo removed the dead attempt's folder
