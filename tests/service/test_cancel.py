"""Cancelling a running match job: the job ends cancelled, the pair steps still queued do
nothing, and matching again later matches only the pairs the cancelled job left."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
import redis

from .harness import Deployment, database_pairs, upload, wait_job

pytestmark = pytest.mark.service

GROUND = ["ground_00.png", "ground_01.png", "ground_02.png", "ground_03.png"]


def queue_drained(d: Deployment) -> bool:
    """No message waiting, none delivered and unacknowledged: every step has run to its end."""
    assert d.redis_url is not None
    r = redis.Redis.from_url(d.redis_url)
    return r.llen(f"{d.prefix}{d.env['GEOMATCH_QUEUE']}") == 0 and r.hlen(f"{d.prefix}unacked") == 0


def test_cancel_stops_outstanding_pairs(
    deployment: Deployment, key_a: str, scene: Path, tmp_path: Path
) -> None:
    c = deployment.client(key_a)
    pid = c.post("/v1/projects", json={"name": "cancel"}).json()["id"]
    assert upload(c, pid, [scene / "images" / n for n in GROUND], "ground").status_code == 201
    job_id = c.post(f"/v1/projects/{pid}/match", json={"resize": 320}).json()["job_id"]
    job = wait_job(c, job_id, until=lambda j: j["progress"]["done"] >= 1)
    assert job["state"] == "running" and job["progress"]["total"] == 6, job

    r = c.delete(f"/v1/jobs/{job_id}")
    assert r.status_code == 200 and r.json()["state"] == "cancelled"
    deadline = time.monotonic() + 120
    while not queue_drained(deployment):
        assert time.monotonic() < deadline, "the worker did not drain the cancelled job's steps"
        time.sleep(0.5)
    time.sleep(1.0)
    job = c.get(f"/v1/jobs/{job_id}").json()
    assert job["state"] == "cancelled" and job["error"] == "cancelled by the client"
    done = job["progress"]["done"]
    assert 1 <= done < 6, job  # the rest were skipped, not matched
    assert len(database_pairs(c, pid, tmp_path / "db.db")) == done  # nothing written after the cancel
    assert c.delete(f"/v1/jobs/{job_id}").json()["state"] == "cancelled"  # idempotent

    again = wait_job(c, c.post(f"/v1/projects/{pid}/match", json={"resize": 320}).json()["job_id"])
    assert again["state"] == "succeeded" and again["progress"] == {"done": 6 - done, "total": 6 - done}
    assert len(database_pairs(c, pid, tmp_path / "db.db")) == 6


def test_cancel_of_a_chained_match_cancels_its_reconstruct(
    deployment: Deployment, key_a: str, scene: Path
) -> None:
    c = deployment.client(key_a)
    pid = c.post("/v1/projects", json={"name": "cancel-chain"}).json()["id"]
    upload(c, pid, [scene / "images" / n for n in GROUND[:2]], "ground")
    accepted = c.post(f"/v1/projects/{pid}/match", json={"resize": 320, "reconstruct": True}).json()
    c.delete(f"/v1/jobs/{accepted['job_id']}")
    follower = wait_job(c, accepted["reconstruct_job_id"], timeout=30)
    assert follower["state"] == "cancelled" and accepted["job_id"] in follower["error"]
    assert follower["after_job_id"] == accepted["job_id"]
