"""A project deleted while other calls write to it or read it: every call that loses the race gets
a defined answer (404 / NOT_FOUND or 409 / FAILED_PRECONDITION), never a server error, on both
stores and both transports.

One `geomatch serve` (HTTP and gRPC over one service) per store, in Redis mode with no worker: the
match jobs are queued and never run, which is all a race with the deletion needs. Each round makes
a project with two images and then, released by one barrier, deletes it while match (four times),
upload, reconstruct, cancel and reads of the project hit it."""

from __future__ import annotations

import contextlib
import functools
import threading
from collections.abc import Callable, Iterator

import grpc
import httpx
import pytest

from service.clients.grpc_client import GrpcClient, ImageSource

from .grpc_harness import GrpcDeployment, serving_on_store
from .harness import noise_png, noise_project

pytestmark = pytest.mark.service

ROUNDS = 8
MATCHES = 4


THIRD = noise_png(2)  # the upload racing the deletion (noise_project holds images 0 and 1)


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def dep(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory, redis_url: str
) -> Iterator[tuple[GrpcDeployment, str]]:
    root = tmp_path_factory.mktemp(f"delete-race-{request.param}")
    with serving_on_store(root, redis_url, request.param) as d:
        yield d, d.create_key("racer")


def race(calls: dict[str, Callable[[], object]]) -> dict[str, object]:
    """Every call at once (one thread each, released together); what each returned."""
    start = threading.Barrier(len(calls))
    out: dict[str, object] = {}

    def run(name: str, call: Callable[[], object]) -> None:
        start.wait()
        out[name] = call()

    threads = [threading.Thread(target=run, args=item) for item in calls.items()]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert len(out) == len(calls), f"calls still running: {sorted(set(calls) - set(out))}"
    return out


def project_with_images(c: httpx.Client, round_: int) -> tuple[str, str]:
    """A project with two images and one queued match job (something to cancel)."""
    pid = noise_project(c, f"race {round_}")
    r = c.post(f"/v1/projects/{pid}/match", json={})
    assert r.status_code == 202, r.text
    return pid, str(r.json()["job_id"])


def rest_calls(clients: list[httpx.Client], pid: str, job: str) -> dict[str, Callable[[], object]]:
    """What races the deletion over HTTP, one client each."""
    third = [("files", ("2.png", THIRD, "image/png"))]
    calls: dict[str, Callable[[], object]] = {
        "delete": lambda: clients[0].delete(f"/v1/projects/{pid}"),
        "upload": lambda: clients[1].post(f"/v1/projects/{pid}/images", files=third),
        "reconstruct": lambda: clients[2].post(f"/v1/projects/{pid}/reconstruct"),
        "cancel": lambda: clients[3].delete(f"/v1/jobs/{job}"),
        "get": lambda: clients[4].get(f"/v1/projects/{pid}"),
        "images": lambda: clients[5].get(f"/v1/projects/{pid}/images"),
        "pairs": lambda: clients[6].get(f"/v1/projects/{pid}/pairs"),
    }
    for i in range(MATCHES):
        body = {"reconstruct": i % 2 == 1}
        calls[f"match {i}"] = functools.partial(clients[7 + i].post, f"/v1/projects/{pid}/match", json=body)
    return calls


def grpc_calls(g: GrpcClient, pid: str, job: str) -> dict[str, Callable[[], object]]:
    """What races the deletion over gRPC, on one channel (calls multiplex over it)."""
    calls: dict[str, Callable[[], object]] = {
        "delete": lambda: g.delete_project(pid),
        "upload": lambda: g.upload(pid, [ImageSource("2.png", data=THIRD)], timeout=60),
        "reconstruct": lambda: g.submit_reconstruction(pid),
        "cancel": lambda: g.cancel_job(job),
        "get": lambda: g.get_project(pid),
        "images": lambda: g.list_images(pid),
    }
    for i in range(MATCHES):
        calls[f"match {i}"] = functools.partial(g.submit_matching, pid, reconstruct=i % 2 == 1)
    return calls


def test_rest_calls_racing_a_delete_get_404_or_409(dep: tuple[GrpcDeployment, str]) -> None:
    d, key = dep
    seen: dict[int, int] = {}
    with contextlib.ExitStack() as stack:
        clients = [stack.enter_context(d.client(key)) for _ in range(MATCHES + 7)]
        for round_ in range(ROUNDS):
            pid, job = project_with_images(clients[0], round_)
            for name, r in race(rest_calls(clients, pid, job)).items():
                assert isinstance(r, httpx.Response)
                seen[r.status_code] = seen.get(r.status_code, 0) + 1
                assert r.status_code < 300 or r.status_code in (404, 409), (
                    round_,
                    name,
                    r.status_code,
                    r.text,
                )
                assert name != "delete" or r.status_code == 204, r.text
            assert clients[0].get(f"/v1/projects/{pid}").status_code == 404
            assert not (d.home / "projects" / pid).exists()
    assert seen.get(404), seen  # the race was run: some calls came after the deletion


def test_grpc_calls_racing_a_delete_get_not_found_or_failed_precondition(
    dep: tuple[GrpcDeployment, str],
) -> None:
    d, key = dep
    allowed = (grpc.StatusCode.OK, grpc.StatusCode.NOT_FOUND, grpc.StatusCode.FAILED_PRECONDITION)
    seen: dict[str, int] = {}
    with d.client(key) as c, d.grpc_client(key, timeout=60) as g:
        for round_ in range(ROUNDS):
            pid, job = project_with_images(c, round_)
            calls = {name: status_of(call) for name, call in grpc_calls(g, pid, job).items()}
            for name, answer in race(calls).items():
                assert isinstance(answer, tuple)
                code, details = answer
                seen[code.name] = seen.get(code.name, 0) + 1
                assert code in allowed, (round_, name, code, details)
                assert name != "delete" or code == grpc.StatusCode.OK, details
            assert c.get(f"/v1/projects/{pid}").status_code == 404
            assert not (d.home / "projects" / pid).exists()
    assert seen.get("NOT_FOUND"), seen


def status_of(call: Callable[[], object]) -> Callable[[], tuple[grpc.StatusCode, str]]:
    def run() -> tuple[grpc.StatusCode, str]:
        try:
            call()
        except grpc.RpcError as e:
            return e.code(), e.details() or ""
        return grpc.StatusCode.OK, ""

    return run
