"""Real gRPC servers for the tests: ``python -m geomatch_app grpc-serve`` (gRPC alone, the production entry),
``geomatch grpc-serve``, or ``geomatch serve`` with both APIs, on free loopback ports; ready when the
standard health check answers SERVING. Built on ``harness.Deployment`` (its own GEOMATCH_HOME,
Redis prefix and queue per deployment)."""

from __future__ import annotations

import contextlib
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc

from service.clients.grpc_client import GrpcClient

from .harness import Deployment, deployed, free_port, metadata_database

# every method of geomatch.v1.Matching, as the server must serve them (reflection lists them)
SERVED_METHODS = {
    "CreateProject",
    "GetProject",
    "ListProjects",
    "DeleteProject",
    "UploadImages",
    "ListImages",
    "PutGcp",
    "GetGcp",
    "DeleteGcp",
    "SubmitMatching",
    "SubmitReconstruction",
    "ListJobs",
    "GetJob",
    "WatchJob",
    "CancelJob",
    "Localize",
    "GetModel",
    "MatchPair",
}


class GrpcDeployment(Deployment):
    def __init__(self, root: Path, redis_url: str | None, **env: str) -> None:
        super().__init__(root, redis_url, **env)
        self.target = ""

    def start_grpc(self, how: str = "module", timeout: float = 120.0) -> str:
        """``how``: module (python -m geomatch_app grpc-serve), grpc-serve, or serve (HTTP + gRPC)."""
        port = free_port()
        self.root.mkdir(parents=True, exist_ok=True)
        if how == "module":
            args = [sys.executable, "-m", "geomatch_app", "grpc-serve", "--port", str(port)]
            out = (self.root / "server.log").open("ab")
            self.server = subprocess.Popen(
                args, env=self.env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True
            )
        elif how == "grpc-serve":
            self.server = self.spawn(["grpc-serve", "--port", str(port)], "server.log")
        else:
            http = free_port()
            self.server = self.spawn(["serve", "--port", str(http), "--grpc-port", str(port)], "server.log")
            self.url = f"http://127.0.0.1:{http}"
        self.target = f"127.0.0.1:{port}"
        deadline = time.monotonic() + timeout
        with grpc.insecure_channel(self.target) as ch:
            stub = health_pb2_grpc.HealthStub(ch)
            while time.monotonic() < deadline:
                if self.server.poll() is not None:
                    raise RuntimeError(
                        f"the gRPC server exited with {self.server.returncode}:\n{self.logs()}"
                    )
                with contextlib.suppress(grpc.RpcError):
                    r = stub.Check(health_pb2.HealthCheckRequest(service=""), timeout=2)
                    if r.status == health_pb2.HealthCheckResponse.SERVING:
                        self.server_out = (self.root / "server.log").read_text()
                        return self.target
                time.sleep(0.3)
        raise RuntimeError(f"the gRPC server is not SERVING after {timeout}s:\n{self.logs()}")

    def start_worker(self, timeout: float = 120.0) -> subprocess.Popen[bytes]:
        """Returned once the gRPC server's health counts it too (it checks every few seconds)."""
        w = super().start_worker(timeout)
        if self.target:
            deadline = time.monotonic() + timeout
            with grpc.insecure_channel(self.target) as ch:
                stub = health_pb2_grpc.HealthStub(ch)
                while time.monotonic() < deadline:
                    with contextlib.suppress(grpc.RpcError):
                        r = stub.Check(
                            health_pb2.HealthCheckRequest(service="geomatch.v1.Matching"), timeout=2
                        )
                        if r.status == health_pb2.HealthCheckResponse.SERVING:
                            return w
                    time.sleep(0.3)
            raise RuntimeError(f"geomatch.v1.Matching not SERVING after {timeout}s:\n{self.logs()}")
        return w

    def grpc_client(self, key: str | None, timeout: float = 120.0) -> GrpcClient:
        return GrpcClient(self.target, key, timeout=timeout)

    def project_state(self, pid: str) -> tuple[list[str], int, list[str]]:
        """What a refused or abandoned request must leave as it was: the project's image rows and
        files (equal), its jobs, and staged uploads (none)."""
        rows = sorted(n for (n,) in self.metadata("SELECT name FROM images WHERE project_id = ?", pid))
        jobs = self.metadata("SELECT count(*) FROM jobs WHERE project_id = ?", pid)[0][0]
        files = sorted(p.name for p in (self.home / "projects" / pid / "images").glob("*"))
        assert rows == files, (rows, files)
        return rows, jobs, self.staged()

    def staged(self) -> list[str]:
        return sorted(
            p.name for p in (self.home / "tmp").glob("*") if p.name.startswith(("upload-", "pair-"))
        )

    def wait_unstaged(self, timeout: float = 30.0) -> list[str]:
        """Staged files of calls the server is still winding down go within ``timeout``."""
        deadline = time.monotonic() + timeout
        while self.staged() and time.monotonic() < deadline:
            time.sleep(0.1)
        return self.staged()


@contextlib.contextmanager
def running_grpc(
    root: Path, redis_url: str | None, how: str = "module", **env: str
) -> Iterator[GrpcDeployment]:
    """A deployment whose gRPC server is up (``how`` as in ``start_grpc``), stopped on exit."""
    with deployed(GrpcDeployment(root, redis_url, **env), workers=0, grpc=how) as d:
        yield d


@contextlib.contextmanager
def serving_on_store(root: Path, redis_url: str, store: str) -> Iterator[GrpcDeployment]:
    """`geomatch serve` (REST and gRPC in one process) over the parametrised metadata ``store``
    (``metadata_database``), in Redis mode with no worker: jobs stay queued, so what a test
    finds in the store is exactly what it made."""
    with (
        metadata_database(store) as url,
        running_grpc(root, redis_url, "serve", **({"DATABASE_URL": url} if url else {})) as d,
    ):
        yield d


def code_of(call: Any) -> grpc.StatusCode:
    """The status of ``call()`` (a thunk), which must fail."""
    try:
        call()
    except grpc.RpcError as e:
        return e.code()
    raise AssertionError("the call succeeded")


def error_of(call: Any) -> tuple[grpc.StatusCode, str]:
    try:
        call()
    except grpc.RpcError as e:
        return e.code(), e.details() or ""
    raise AssertionError("the call succeeded")
