"""Real processes for the service tests: `geomatch serve` (uvicorn) on a free loopback port,
`geomatch worker` (Celery) processes, keys made with `geomatch keys create`.

Each deployment gets its own GEOMATCH_HOME, Redis key prefix and queue name, so test runs (and
deployments within one run) sharing one Redis never see each other's messages or locks.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import httpx
import pytest
import redis

GEOMATCH = [sys.executable, "-m", "geomatch_app"]  # the `geomatch` command (geomatch_app.cli:main)
TERMINAL = ("succeeded", "failed", "cancelled")


_HANDED_OUT: set[int] = set()


def free_port() -> int:
    """A loopback port nothing listens on and this test process has not handed out before.

    The probe socket is closed before the server binds, so the kernel may offer the same
    ephemeral port to the next probe; a deployment that asks for an HTTP and a gRPC port in a row
    would then give both to one server, which fails to bind the second.
    """
    while True:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = int(s.getsockname()[1])
        if port not in _HANDED_OUT:
            _HANDED_OUT.add(port)
            return port


class Deployment:
    def __init__(self, root: Path, redis_url: str | None, **env: str) -> None:
        self.root = root
        self.home = root / "home"
        self.uid = uuid.uuid4().hex[:10]
        self.redis_url = redis_url
        self.prefix = f"gmtest-{self.uid}:"
        base = {
            k: v
            for k, v in os.environ.items()
            if not k.startswith(("GEOMATCH_", "REDIS_URL", "DATABASE_URL"))
        }
        self.env = {
            **base,
            "GEOMATCH_HOME": str(self.home),
            "GEOMATCH_LOG_FORMAT": "text",
            "GEOMATCH_QUEUE": f"gmtest-{self.uid}",
            "GEOMATCH_REDIS_PREFIX": self.prefix,
            **env,
        }
        if redis_url:
            self.env["REDIS_URL"] = redis_url
        self.server: subprocess.Popen[bytes] | None = None
        self.workers: list[subprocess.Popen[bytes]] = []
        self.url = ""
        self.node_port = 0
        self.server_out = ""  # what `geomatch serve` printed before it was ready

    # -- processes ---------------------------------------------------------------------------
    def spawn(self, args: list[str], log: str) -> subprocess.Popen[bytes]:
        self.root.mkdir(parents=True, exist_ok=True)
        out = (self.root / log).open("ab")
        return subprocess.Popen(
            [*self.command(), *args],
            env=self.env,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )

    def command(self) -> list[str]:
        """How this deployment runs `geomatch` (ImageDeployment: inside the built image)."""
        return GEOMATCH

    def start_server(self, timeout: float = 120.0, node: bool = False) -> str:
        """``node``: with the NodeODM node on a port of its own (``node_port``); without, none, so
        that deployments never race for its default port."""
        port = free_port()
        self.node_port = free_port() if node else 0
        extra = ["--node-port", str(self.node_port)] if node else ["--no-node"]
        self.server = self.spawn(["serve", "--host", "127.0.0.1", "--port", str(port), *extra], "server.log")
        self.url = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.server.poll() is not None:
                raise RuntimeError(f"geomatch serve exited with {self.server.returncode}:\n{self.logs()}")
            with contextlib.suppress(httpx.HTTPError, ValueError):
                if serving(httpx.get(f"{self.url}/readyz", timeout=2).json()):
                    self.server_out = (self.root / "server.log").read_text()
                    return self.url
            time.sleep(0.3)
        raise RuntimeError(f"geomatch serve not ready after {timeout}s:\n{self.logs()}")

    def start_worker(self, timeout: float = 120.0) -> subprocess.Popen[bytes]:
        """A `geomatch worker`, returned once it takes work (it beats: readiness counts it)."""
        before = self.live_workers()
        w = self.spawn(["worker", "--concurrency", "1"], f"worker-{len(self.workers)}.log")
        self.workers.append(w)
        deadline = time.monotonic() + timeout
        while len(self.live_workers() - before) < 1:
            if w.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"geomatch worker not alive after {timeout}s:\n{self.logs()}")
            time.sleep(0.3)
        return w

    def live_workers(self) -> set[str]:
        """Ids of this deployment's workers heard from within their lease (Redis mode)."""
        if not self.redis_url:
            return set()
        import redis

        from geomatch_core.config import Settings
        from workers.liveness import Registry

        lease = int(self.env.get("GEOMATCH_WORKER_LEASE") or Settings.worker_lease_s)
        return Registry(redis.Redis.from_url(self.redis_url), self.prefix, lease).alive()

    @staticmethod
    def kill(proc: subprocess.Popen[bytes], sig: int = signal.SIGKILL) -> None:
        """The whole process group: a prefork worker's parent and its pool children alike."""
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=30)

    def stop(self) -> None:
        for p in [*self.workers, *([self.server] if self.server else [])]:
            if p.poll() is None:
                self.kill(p, signal.SIGTERM)
            if p.poll() is None:
                self.kill(p, signal.SIGKILL)
        if self.redis_url:
            import redis

            r = redis.Redis.from_url(self.redis_url)
            for k in r.scan_iter(f"{self.prefix}*", count=1000):
                r.delete(k)

    def logs(self, tail: int = 6000) -> str:
        out = []
        for f in sorted(self.root.glob("*.log")):
            out.append(f"--- {f.name}\n{f.read_text(errors='replace')[-tail:]}")
        return "\n".join(out)

    # -- clients -----------------------------------------------------------------------------
    def create_key(self, tenant: str) -> str:
        r = subprocess.run(
            [*self.command(), "keys", "create", tenant], env=self.env, capture_output=True, text=True
        )
        assert r.returncode == 0, r.stderr
        key = r.stdout.strip()
        assert key.startswith("gm_"), r.stdout
        return key

    def client(self, key: str | None) -> httpx.Client:
        headers = {"Authorization": f"Bearer {key}"} if key else {}
        return httpx.Client(base_url=self.url, headers=headers, timeout=180)

    def metadata(self, sql: str, *params: Any) -> list[tuple[Any, ...]]:
        """Read the metadata store directly (SQLite under GEOMATCH_HOME)."""
        with contextlib.closing(sqlite3.connect(self.home / "geomatch.sqlite", timeout=30)) as c:
            return c.execute(sql, params).fetchall()


D = TypeVar("D", bound=Deployment)


@contextlib.contextmanager
def deployed(d: D, workers: int = 1, node: bool = False, grpc: str | None = None) -> Iterator[D]:
    """``d`` serving, with ``workers`` workers (Redis mode), stopped on exit whatever happens: the
    one way the tests' deployment fixtures start and stop one. ``grpc``: a GrpcDeployment's
    server (``start_grpc``'s ``how``) instead of `geomatch serve`; ``node``: with the NodeODM node."""
    try:
        if grpc is not None:
            d.start_grpc(grpc)  # type: ignore[attr-defined]  # a GrpcDeployment
        else:
            d.start_server(node=node)
        for _ in range(workers):
            d.start_worker()
        yield d
    finally:
        d.stop()


POSTGRES_ADMIN = "postgresql://postgres@127.0.0.1:5432/postgres"


@contextlib.contextmanager
def postgres_database() -> Iterator[str | None]:
    """A fresh PostgreSQL database's URL for one deployment, dropped afterwards; None when no
    PostgreSQL answers on 127.0.0.1:5432 (the caller skips)."""
    try:
        import psycopg

        with psycopg.connect(POSTGRES_ADMIN, connect_timeout=2, autocommit=True):
            pass
    except Exception:
        yield None
        return
    name = f"gmtest_{uuid.uuid4().hex[:12]}"
    with psycopg.connect(POSTGRES_ADMIN, autocommit=True) as c:
        c.execute(f"CREATE DATABASE {name}")
    try:
        yield POSTGRES_ADMIN.rsplit("/", 1)[0] + f"/{name}"
    finally:
        with psycopg.connect(POSTGRES_ADMIN, autocommit=True) as c:
            c.execute(f"DROP DATABASE {name} WITH (FORCE)")


def noise_png(seed: int, side: int = 32) -> bytes:
    """A small PNG of random pixels: a valid upload whose bytes differ per seed (names that clash
    with other bytes are conflicts), and nothing a matcher could match."""
    import io

    import numpy as np
    from PIL import Image

    buf = io.BytesIO()
    pixels = np.random.default_rng(seed).integers(0, 256, (side, side, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(buf, format="PNG")
    return buf.getvalue()


def noise_project(c: httpx.Client, name: str, images: tuple[str, ...] = ("0.png", "1.png")) -> str:
    """A project holding a noise image under each of ``images``: enough for a match job that no
    worker needs to run, or for the routes that take an image's name."""
    pid = str(c.post("/v1/projects", json={"name": name}).json()["id"])
    files = [("files", (n, noise_png(i), "image/png")) for i, n in enumerate(images)]
    assert c.post(f"/v1/projects/{pid}/images", files=files).status_code == 201
    return pid


@contextlib.contextmanager
def metadata_database(store: str) -> Iterator[str]:
    """The DATABASE_URL a deployment of the parametrised ``store`` gets: "" (the default SQLite
    file) or a fresh PostgreSQL database; skips the test when no PostgreSQL answers."""
    if store != "postgresql":
        yield ""
        return
    with postgres_database() as url:
        if url is None:
            pytest.skip("no PostgreSQL on 127.0.0.1:5432")
        yield url


@dataclass
class KillSetup:
    d: Deployment
    worker: subprocess.Popen[bytes]
    key: str
    c: httpx.Client
    pid: str
    job_id: str


@contextlib.contextmanager
def ground_match_under_kill(
    root: Path, redis_url: str, scene: Path, names: list[str], tenant: str
) -> Iterator[KillSetup]:
    """A Redis deployment with short visibility and lock timeouts (a killed worker's task and lock
    come back in 15 s), a server and one worker, and a project whose ground images ``names`` are
    uploaded and being matched at 320 px; stopped on exit."""
    d = Deployment(root, redis_url, GEOMATCH_VISIBILITY_TIMEOUT="15", GEOMATCH_LOCK_TIMEOUT="15")
    try:
        d.start_server()
        worker = d.start_worker()
        key = d.create_key(tenant)
        c = d.client(key)
        pid = c.post("/v1/projects", json={"name": tenant}).json()["id"]
        assert upload(c, pid, [scene / "images" / n for n in names], "ground").status_code == 201
        job_id = c.post(f"/v1/projects/{pid}/match", json={"resize": 320}).json()["job_id"]
        yield KillSetup(d, worker, key, c, pid, job_id)
    finally:
        d.stop()


def serving(readiness: dict[str, Any]) -> bool:
    """/readyz's answer says the server's own parts answer: every check but the workers' ok (a
    server in queue mode is not ready until a worker beats, and tests start workers after it)."""
    checks = readiness.get("checks", {})
    return bool(checks) and all(v == "ok" for k, v in checks.items() if k not in ("mode", "workers"))


def wait_job(c: httpx.Client, job_id: str, timeout: float = 600.0, until: Any = None) -> dict[str, Any]:
    """Poll a job until it ends (or ``until(job)`` holds)."""
    deadline = time.monotonic() + timeout
    while True:
        job = c.get(f"/v1/jobs/{job_id}").json()
        if job["state"] in TERMINAL or (until is not None and until(job)):
            return job
        if time.monotonic() > deadline:
            raise TimeoutError(f"job {job_id} still {job['state']} {job['progress']} after {timeout}s")
        time.sleep(0.2)


def sse_events(c: httpx.Client, job_id: str) -> Iterator[dict[str, Any]]:
    """The `event: job` payloads of a job's server-sent event stream, until it closes."""
    import json

    with c.stream("GET", f"/v1/jobs/{job_id}/events", timeout=None) as r:
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/event-stream")
        event, data = None, []
        for line in r.iter_lines():
            if line.startswith("event:"):
                event = line[6:].strip()
            elif line.startswith("data:"):
                data.append(line[5:].strip())
            elif line == "" and data:
                if event == "job":
                    yield json.loads("\n".join(data))
                event, data = None, []


def upload(c: httpx.Client, project_id: str, paths: list[Path], capture: str = "auto") -> httpx.Response:
    files = [("files", (p.name, p.read_bytes(), "image/png")) for p in paths]
    return c.post(f"/v1/projects/{project_id}/images", files=files, data={"capture": capture})


def database_pairs(c: httpx.Client, project_id: str, dest: Path) -> list[tuple[str, str]]:
    """Every pair of the project's COLMAP database (downloaded over HTTP), as sorted name pairs,
    including pairs stored with zero matches (pycolmap's read_all_matches leaves those out)."""
    import pycolmap

    r = c.get(f"/v1/projects/{project_id}/database")
    assert r.status_code == 200, r.text
    dest.write_bytes(r.content)
    db = pycolmap.Database.open(str(dest))
    try:
        names = {im.image_id: im.name for im in db.read_all_images()}
    finally:
        db.close()
    with contextlib.closing(sqlite3.connect(dest)) as con:
        pair_ids = [int(p) for (p,) in con.execute("SELECT pair_id FROM matches")]
    # tuple(sorted(pair)) is a pair; mypy sees tuple[str, ...]
    return sorted(tuple(sorted(names[i] for i in pycolmap.pair_id_to_image_pair(p))) for p in pair_ids)  # type: ignore[misc]


# -- private servers for the chaos tests: restarted on the same port and data folder ---------------
class PrivateRedis:
    """`redis-server` on a free loopback port, persisting like docker-compose.yml's (append-only
    file on, RDB snapshots at their defaults), its data in ``root``."""

    BINARY = "/usr/bin/redis-server"

    def __init__(self, root: Path) -> None:
        self.root = root
        self.port = free_port()
        self.url = f"redis://127.0.0.1:{self.port}/0"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self, timeout: float = 30.0) -> None:
        import redis

        self.root.mkdir(parents=True, exist_ok=True)
        out = (self.root / "redis.log").open("ab")
        self.proc = subprocess.Popen(
            [
                *(self.BINARY, "--port", str(self.port), "--bind", "127.0.0.1", "--dir", str(self.root)),
                *("--appendonly", "yes", "--daemonize", "no", "--protected-mode", "no"),
            ],
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with contextlib.suppress(redis.RedisError):
                if redis.Redis.from_url(self.url, socket_connect_timeout=1).ping():
                    return
            time.sleep(0.1)
        raise RuntimeError(f"redis-server not ready: {(self.root / 'redis.log').read_text()[-2000:]}")

    def stop(self, sig: int = signal.SIGTERM) -> None:
        if self.proc is not None and self.proc.poll() is None:
            Deployment.kill(self.proc, sig)
        self.proc = None


class PrivatePostgres:
    """A PostgreSQL cluster of its own (initdb + pg_ctl, trust authentication, its unix socket in
    its folder) on a free loopback port. As root, the server runs as the `postgres` user."""

    def __init__(self) -> None:
        import glob
        import tempfile

        found = sorted(glob.glob("/usr/lib/postgresql/*/bin/pg_ctl"))
        if not found:
            raise FileNotFoundError("no /usr/lib/postgresql/*/bin/pg_ctl")
        self.bin = Path(found[-1]).parent
        # not under pytest's 0700 temporary root: the postgres user must reach it
        self.root = Path(tempfile.mkdtemp(prefix="gmtest-pg-"))
        self.data = self.root / "data"
        self.port = free_port()
        self.url = f"postgresql://postgres@127.0.0.1:{self.port}/postgres"
        self._as: list[str] = []
        if os.geteuid() == 0:
            import pwd

            pw = pwd.getpwnam("postgres")
            os.chown(self.root, pw.pw_uid, pw.pw_gid)
            self._as = ["runuser", "-u", "postgres", "--"]
        self._run("initdb", "-D", str(self.data), "-A", "trust", "-U", "postgres", "--no-sync", "-E", "UTF8")

    def _run(self, tool: str, *args: str) -> None:
        r = subprocess.run([*self._as, str(self.bin / tool), *args], capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"{tool} failed: {r.stdout}\n{r.stderr}")

    def start(self) -> None:
        opts = f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1"
        self._run("pg_ctl", "-D", str(self.data), "-o", opts, "-l", str(self.root / "pg.log"), "-w", "start")

    def stop(self, mode: str = "fast") -> None:
        """``immediate``: the server processes quit at once, as after a crash (recovery on start)."""
        self._run("pg_ctl", "-D", str(self.data), "-m", mode, "-w", "stop")

    def destroy(self) -> None:
        import shutil

        with contextlib.suppress(RuntimeError):
            self.stop("immediate")
        shutil.rmtree(self.root, ignore_errors=True)


@contextlib.contextmanager
def reconstruct_held_mid_job(
    d: Deployment, c: httpx.Client, r: redis.Redis, project_id: str
) -> Iterator[str]:
    """A reconstruct job of ``project_id``, held mid-job while the block runs (its id is yielded).

    A small model maps in well under a poll, so the project's writer lock (the Redis lock workers
    use) is held here: the worker opens its work folder, then waits for the lock to snapshot the
    database, so a worker killed in the block dies deterministically mid-job. It waits for the
    folder's owner lock, not only the folder: a folder killed before its lock file exists is left
    for remove_stale_work's grace period (it may be still being created)."""
    from geomatch_core.locks import RedisLocks

    project = d.home / "projects" / project_id
    with RedisLocks(r, d.prefix, timeout_s=300).project(project_id):
        rec = c.post(f"/v1/projects/{project_id}/reconstruct").json()["job_id"]
        wait_job(c, rec, timeout=120, until=lambda j: j["state"] == "running")
        deadline = time.monotonic() + 60
        while not list(project.glob(".work-reconstruct-*/.owner.lock")) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert list(project.glob(".work-reconstruct-*/.owner.lock")), d.logs()
        yield rec
