"""Chaos with real processes on loopback: a full storage root, the API and a worker SIGKILLed at
awkward moments, Redis and PostgreSQL restarted. After each: every accepted upload is present and
intact (sha256), every job ends in a truthful state, the COLMAP database passes `PRAGMA
integrity_check`, and no pair is lost or written twice.

A full disk is the storage layer's test hook GEOMATCH_TEST_FILL_LIMIT (bytes the storage root may
hold; writes beyond it raise ENOSPC), since a small file system needs root.
"""

from __future__ import annotations

import contextlib
import hashlib
import signal
import sqlite3
import threading
import time
from pathlib import Path

import httpx
import pytest
import redis

from geomatch_core.storage import disk_usage

from .harness import (
    Deployment,
    PrivatePostgres,
    PrivateRedis,
    database_pairs,
    ground_match_under_kill,
    reconstruct_held_mid_job,
    upload,
    wait_job,
)

pytestmark = pytest.mark.chaos

GROUND = ["ground_00.png", "ground_01.png", "ground_02.png", "ground_03.png"]
ALL_PAIRS = sorted((a, b) for i, a in enumerate(GROUND) for b in GROUND[i + 1 :])


def sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def assert_uploads_intact(d: Deployment, c: httpx.Client, pid: str, accepted: dict[str, str]) -> None:
    """Exactly the accepted images are listed, and each stored file has the sha256 it was sent with."""
    listed = {i["name"]: i["sha256"] for i in c.get(f"/v1/projects/{pid}/images").json()["images"]}
    assert listed == accepted
    images = d.home / "projects" / pid / "images"
    assert sorted(p.name for p in images.iterdir()) == sorted(accepted)
    for name, digest in accepted.items():
        assert sha(images / name) == digest, name


def serve_two_accepted(
    d: Deployment, scene: Path, tenant: str
) -> tuple[str, httpx.Client, str, dict[str, str]]:
    """Start ``d``'s server and give ``tenant`` a project with the first two ground images: (key,
    client, project id, the accepted uploads' sha256 by name) for a test that then breaks the server."""
    d.start_server()
    key = d.create_key(tenant)
    c = d.client(key)
    pid = c.post("/v1/projects", json={"name": tenant}).json()["id"]
    first = [scene / "images" / n for n in GROUND[:2]]
    assert upload(c, pid, first, "ground").status_code == 201
    return key, c, pid, {p.name: sha(p) for p in first}


def integrity(db: Path) -> str:
    with contextlib.closing(sqlite3.connect(db)) as con:
        return str(con.execute("PRAGMA integrity_check").fetchone()[0])


# -- e. the storage root fills up -----------------------------------------------------------------
def test_full_storage_refuses_upload_with_507_and_keeps_nothing(tmp_path_factory, scene: Path) -> None:
    root = tmp_path_factory.mktemp("enospc-upload")
    d = Deployment(root, None, GEOMATCH_TEST_FILL_LIMIT=str(50 * 1024 * 1024))
    try:
        key, c, pid, accepted = serve_two_accepted(d, scene, "full")
        d.stop()
        # the disk is now full but for a few bytes: the next upload cannot be stored
        d.env["GEOMATCH_TEST_FILL_LIMIT"] = str(disk_usage(d.home) + 1000)
        d.start_server()
        c = d.client(key)  # a new port
        r = upload(c, pid, [scene / "images" / n for n in GROUND[2:]], "ground")
        assert r.status_code == 507, r.text
        assert "no space left" in r.json()["detail"]
        assert_uploads_intact(d, c, pid, accepted)
        assert list((d.home / "tmp").glob("upload-*")) == []  # nothing half-written left behind
    finally:
        d.stop()


def test_full_storage_during_database_write_fails_job_with_reason(
    tmp_path_factory, redis_url: str, scene: Path, tmp_path: Path
) -> None:
    d = Deployment(tmp_path_factory.mktemp("enospc-db"), redis_url)
    try:
        d.start_server()
        c = d.client(d.create_key("fulldb"))
        pid = c.post("/v1/projects", json={"name": "fulldb"}).json()["id"]
        paths = [scene / "images" / n for n in GROUND]
        assert upload(c, pid, paths, "ground").status_code == 201
        # the worker's disk fills up once the images are stored: its first pair write finds no room
        d.env["GEOMATCH_TEST_FILL_LIMIT"] = str(disk_usage(d.home) + 64 * 1024)
        d.start_worker()
        job_id = c.post(f"/v1/projects/{pid}/match", json={"resize": 320}).json()["job_id"]
        job = wait_job(c, job_id, timeout=900)  # a deadline for shared CPUs, not a speed target
        assert job["state"] == "failed", job
        assert "No space left on device" in (job["error"] or ""), job
        assert integrity(d.home / "projects" / pid / "database.db") == "ok"
        pairs = database_pairs(c, pid, tmp_path / "db.db")
        assert len(pairs) == len(set(pairs)) and set(pairs) <= set(ALL_PAIRS)
        assert_uploads_intact(d, c, pid, {p.name: sha(p) for p in paths})
    finally:
        d.stop()


# -- c. the API SIGKILLed mid-request -------------------------------------------------------------
def test_api_killed_during_upload_keeps_accepted_uploads_only(
    tmp_path_factory, redis_url: str, scene: Path
) -> None:
    d = Deployment(tmp_path_factory.mktemp("api-kill-upload"), redis_url)
    try:
        key, c, pid, accepted = serve_two_accepted(d, scene, "apikill")

        # a multipart body sent slowly, the server killed half-way through it
        req = c.build_request(
            "POST",
            f"/v1/projects/{pid}/images",
            files=[
                ("files", (p.name, p.read_bytes(), "image/png"))
                for p in [scene / "images" / n for n in GROUND[2:]]
            ],
            data={"capture": "ground"},
        )
        body = req.read()
        half = threading.Event()

        def slow():
            for i in range(0, len(body), 64 * 1024):
                if i >= len(body) // 2:
                    half.set()
                    time.sleep(0.5)
                yield body[i : i + 64 * 1024]

        result: list[object] = []

        def send():
            try:
                result.append(
                    c.post(req.url, content=slow(), headers={"content-type": req.headers["content-type"]})
                )
            except httpx.HTTPError as e:
                result.append(e)

        t = threading.Thread(target=send)
        t.start()
        assert half.wait(60)
        Deployment.kill(d.server)  # type: ignore[arg-type]  # started: not None
        t.join(60)
        assert result and isinstance(result[0], httpx.HTTPError), result  # never a false 201

        d.start_server()
        c = d.client(key)  # a new port
        assert_uploads_intact(d, c, pid, accepted)
        r = upload(c, pid, [scene / "images" / n for n in GROUND[2:]], "ground")  # the retry works
        assert r.status_code == 201, r.text
        accepted.update({n: sha(scene / "images" / n) for n in GROUND[2:]})
        assert_uploads_intact(d, c, pid, accepted)
    finally:
        d.stop()


# -- c + d. the API SIGKILLed during a reconstruct request, a worker during the reconstruction ------
def test_api_and_worker_killed_around_reconstruct(
    tmp_path_factory, redis_url: str, scene: Path, tmp_path: Path
) -> None:
    root = tmp_path_factory.mktemp("kill-reconstruct")
    with ground_match_under_kill(root, redis_url, scene, GROUND, "killrec") as k:
        d, first, key, c, pid, job_id = k.d, k.worker, k.key, k.c, k.pid, k.job_id
        paths = [scene / "images" / n for n in GROUND]
        assert wait_job(c, job_id, timeout=300)["state"] == "succeeded"

        # the API dies while a reconstruct request is in flight
        answers: list[object] = []
        t = threading.Thread(
            target=lambda: answers.append(_try(lambda: c.post(f"/v1/projects/{pid}/reconstruct")))
        )
        t.start()
        time.sleep(0.05)
        Deployment.kill(d.server)  # type: ignore[arg-type]  # started: not None
        t.join(60)
        d.start_server()
        c = d.client(key)
        # whatever the killed request left (no job, or a job) must end truthfully, never hang queued
        for (jid,) in d.metadata("SELECT id FROM jobs WHERE project_id = ? AND kind = 'reconstruct'", pid):
            job = wait_job(c, jid, timeout=120)
            assert job["state"] in ("succeeded", "failed"), job

        # a worker dies in the middle of a reconstruction: another one does it again, to the end
        project = d.home / "projects" / pid
        with reconstruct_held_mid_job(d, c, redis.Redis.from_url(redis_url), pid) as rec:
            Deployment.kill(first)
            assert c.get(f"/v1/jobs/{rec}").json()["state"] == "running"  # killed mid-job, not after
        assert list(project.glob(".work-reconstruct-*"))  # the dead attempt's folder is left
        d.start_worker()
        job = wait_job(c, rec, timeout=300)
        assert job["state"] == "succeeded", (job, d.logs())
        assert integrity(d.home / "projects" / pid / "database.db") == "ok"
        assert database_pairs(c, pid, tmp_path / "db.db") == ALL_PAIRS  # every pair, exactly once
        assert_uploads_intact(d, c, pid, {p.name: sha(p) for p in paths})
        assert list(project.glob(".work-*")) == []  # the redo removed the dead attempt's folder


def _try(f):
    try:
        return f()
    except httpx.HTTPError as e:
        return e


# -- b. PostgreSQL restarted during uploads --------------------------------------------------------
def _png(path: Path, seed: int) -> Path:
    """A small image of its own (distinct bytes per seed)."""
    import numpy as np
    from PIL import Image

    rng = np.random.default_rng(seed)
    Image.fromarray(rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)).save(path)
    return path


def test_postgres_restart_during_uploads_answers_503_and_recovers(tmp_path_factory, tmp_path: Path) -> None:
    pg = PrivatePostgres()
    d = Deployment(tmp_path_factory.mktemp("pg-restart"), None)
    try:
        pg.start()
        d.env["DATABASE_URL"] = pg.url
        d.start_server()
        c = d.client(d.create_key("pgrestart"))
        pid = c.post("/v1/projects", json={"name": "pgrestart"}).json()["id"]
        accepted: dict[str, str] = {}
        answers: list[tuple[str, int, str]] = []
        stop = threading.Event()
        lock = threading.Lock()
        counter = iter(range(10**6))

        def uploader() -> None:
            cc = d.client(c.headers["Authorization"].split()[1])
            while not stop.is_set():
                with lock:
                    n = next(counter)
                p = _png(tmp_path / f"img_{n:04d}.png", n)
                try:
                    r = upload(cc, pid, [p])
                except httpx.HTTPError as e:  # never expected: the API stays up
                    answers.append((p.name, -1, repr(e)))
                    continue
                answers.append((p.name, r.status_code, r.text))
                if r.status_code == 201:
                    with lock:
                        accepted[p.name] = sha(p)
                time.sleep(0.02)

        threads = [threading.Thread(target=uploader) for _ in range(3)]
        for t in threads:
            t.start()
        time.sleep(1.5)
        pg.stop("immediate")  # as after a crash: connections drop, recovery on start
        down_from = len(answers)
        time.sleep(3)
        down_to = len(answers)
        pg.start()
        # the API reconnects by itself: wait for uploads to succeed again (how soon depends on the
        # machine's load: PostgreSQL's crash recovery, the pool's next connection attempt), then a
        # little longer, so the run ends on answers given after the recovery
        back_from = len(answers)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not any(a[1] == 201 for a in answers[back_from:]):
            time.sleep(0.1)
        time.sleep(1)
        stop.set()
        for t in threads:
            t.join(60)

        codes = [code for _, code, _ in answers]
        assert set(codes) <= {201, 503}, [a for a in answers if a[1] not in (201, 503)]
        outage = answers[down_from + 3 : down_to]  # answered while the database was down
        assert outage and all(code == 503 for _, code, _ in outage), outage
        assert all("metadata database" in text for _, code, text in answers if code == 503)
        assert any(a[1] == 201 for a in answers[back_from:]), answers[-6:]  # reconnected by itself
        assert answers[-1][1] == 201, answers[-6:]  # and stays up
        # one more, after the fact: the pool works again without an API restart
        p = _png(tmp_path / "after.png", 10**6 + 1)
        assert upload(c, pid, [p]).status_code == 201
        accepted[p.name] = sha(p)
        # an upload answered 503 as the database went down may still have been committed: its
        # commit reached PostgreSQL and the acknowledgement was lost with the connection, so its
        # outcome was unknown to the API (seen once in CI: one such image listed). A client retries
        # what it was refused; the same bytes again are idempotent, so after the retries the
        # project holds exactly what the client believes, each file intact
        refused = {name for name, code, _ in answers if code == 503} - set(accepted)
        landed = {i["name"] for i in c.get(f"/v1/projects/{pid}/images").json()["images"]} & refused
        for name in sorted(refused):
            r = upload(c, pid, [tmp_path / name])
            assert r.status_code == 201, r.text
            assert r.json()["images"][0]["created"] is (name not in landed), (name, r.text)
            accepted[name] = sha(tmp_path / name)
        assert_uploads_intact(d, c, pid, accepted)
        assert list((d.home / "tmp").glob("upload-*")) == []  # nothing half-written left behind
    finally:
        d.stop()
        pg.destroy()


# -- a. Redis restarted during a match job ---------------------------------------------------------
def test_redis_restart_during_match_job_ends_truthfully(
    tmp_path_factory, scene: Path, tmp_path: Path
) -> None:
    root = tmp_path_factory.mktemp("redis-restart")
    rs = PrivateRedis(root / "redis")
    rs.start()
    d = Deployment(root, rs.url, GEOMATCH_VISIBILITY_TIMEOUT="15", GEOMATCH_LOCK_TIMEOUT="15")
    try:
        d.start_server()
        d.start_worker()
        c = d.client(d.create_key("redisrestart"))
        pid = c.post("/v1/projects", json={"name": "redisrestart"}).json()["id"]
        paths = [scene / "images" / n for n in GROUND]
        assert upload(c, pid, paths, "ground").status_code == 201
        job_id = c.post(f"/v1/projects/{pid}/match", json={"resize": 320}).json()["job_id"]
        job = wait_job(c, job_id, timeout=120, until=lambda j: j["state"] == "running")
        assert job["state"] == "running", job
        rs.stop(signal.SIGKILL)  # mid-job: queued and unacknowledged steps only in the append-only file
        time.sleep(2)
        rs.start()  # the same port and data folder
        job = wait_job(c, job_id, timeout=150)
        assert job["state"] == "succeeded" or (job["state"] == "failed" and job["error"]), (job, d.logs())
        assert integrity(d.home / "projects" / pid / "database.db") == "ok"
        pairs = database_pairs(c, pid, tmp_path / "db.db")
        assert len(pairs) == len(set(pairs)) and set(pairs) <= set(ALL_PAIRS)  # none written twice
        if job["state"] == "succeeded":
            assert pairs == ALL_PAIRS, (job, d.logs())  # none lost
        assert_uploads_intact(d, c, pid, {p.name: sha(p) for p in paths})
        assert c.get("/readyz").status_code == 200  # the API reconnected by itself
    finally:
        d.stop()
        rs.stop()
