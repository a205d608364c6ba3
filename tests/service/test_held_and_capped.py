"""What a client can hold or start must not cost the server more than it may.

- gRPC calls that open and never send their request message, without a key (GetProject, health
  checks) or with a wrong one: each must leave health checks and other tenants' calls answering.
  Under grpc.aio they wait on the event loop and hold no handler thread; a keyless Matching call
  is refused before it is read; the rest end after GEOMATCH_GRPC_FIRST_MESSAGE_S. On both metadata
  stores.
- HTTP heads: a malformed head followed by more than 16 KiB of body is 400, not 431, and a head
  dribbled slower than GEOMATCH_HEAD_TIMEOUT_S is answered 408 and closed, while keep-alive and
  slow bodies are untouched.
- pairs per job (GEOMATCH_MAX_PAIRS_PER_JOB): an exhaustive match over too many images is refused
  before anything is planned (REST 422, gRPC RESOURCE_EXHAUSTED) with the limit, the count and how
  to split the work; a plan only its step can size (``auto``) fails its job before a pair row is
  written.
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import grpc
import httpx
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from service.grpcapi.pb import pb2

from .grpc_harness import GrpcDeployment, running_grpc
from .harness import TERMINAL, metadata_database, noise_project

pytestmark = pytest.mark.service

HELD = 80  # the probe's count: more than the server's 64 handler threads
FIRST_MESSAGE_S = 5  # the server's wait for a unary call's message, shortened for the test
HEAD_TIMEOUT_S = 2
MAX_PAIRS = 10


# -- gRPC: calls that never send their message --------------------------------------------------
class HeldCalls:
    """``n`` calls to ``method`` that send their headers (and ``metadata``) and never a message:
    a request iterator that blocks, on a stream-stream call of the method's path. Spread over a few
    connections, as a client opening many channels would."""

    def __init__(self, target: str, method: str, n: int, metadata: tuple[tuple[str, str], ...] = ()) -> None:
        self.release = threading.Event()
        self.channels = [grpc.insecure_channel(target) for _ in range(4)]
        self.calls = []
        for i in range(n):
            ch = self.channels[i % len(self.channels)]
            call = ch.stream_stream(method, request_serializer=lambda b: b, response_deserializer=lambda b: b)
            self.calls.append(call(self._never(), metadata=metadata, timeout=60))

    def _never(self) -> Iterator[bytes]:
        self.release.wait(60)
        yield from ()

    def codes(self) -> list[grpc.StatusCode | None]:
        return [c.code() if c.done() else None for c in self.calls]  # type: ignore[attr-defined]

    def close(self) -> None:
        self.release.set()
        for c in self.calls:
            c.cancel()
        for ch in self.channels:
            ch.close()


def answer_within_3s(target: str, key: str, pid: str) -> float:
    """Health and another tenant's GetProject, each with a 3 s deadline: how long they took."""
    t = time.monotonic()
    with grpc.insecure_channel(target) as ch:
        r = health_pb2_grpc.HealthStub(ch).Check(health_pb2.HealthCheckRequest(service=""), timeout=3)
        assert r.status == health_pb2.HealthCheckResponse.SERVING
        got = ch.unary_unary(
            "/geomatch.v1.Matching/GetProject",
            request_serializer=pb2.GetProjectRequest.SerializeToString,
            response_deserializer=pb2.Project.FromString,
        )(pb2.GetProjectRequest(project_id=pid), metadata=(("authorization", f"Bearer {key}"),), timeout=3)
        assert got.id == pid
    return time.monotonic() - t


@pytest.mark.parametrize("store", ["sqlite", "postgresql"])
def test_held_unary_calls_hold_no_thread(tmp_path: Path, redis_url: str, store: str) -> None:
    """80 keyless GetProject calls, 80 health checks and 80 GetProject calls with a wrong key, all
    holding their message: health and a valid tenant's GetProject answer within 3 s throughout;
    the keyless Matching calls are UNAUTHENTICATED at once, the others DEADLINE_EXCEEDED after
    GEOMATCH_GRPC_FIRST_MESSAGE_S."""
    with (
        metadata_database(store) as url,
        running_grpc(
            tmp_path,
            redis_url,
            "serve",
            GEOMATCH_GRPC_FIRST_MESSAGE_S=str(FIRST_MESSAGE_S),
            **({"DATABASE_URL": url} if url else {}),
        ) as d,
    ):
        key = d.create_key("held-b")
        with d.grpc_client(key) as b:
            pid = b.create_project("b").id
        held = [
            HeldCalls(d.target, "/geomatch.v1.Matching/GetProject", HELD),
            HeldCalls(d.target, "/grpc.health.v1.Health/Check", HELD),
            HeldCalls(
                d.target, "/geomatch.v1.Matching/GetProject", HELD, (("authorization", "Bearer gm_x"),)
            ),
        ]
        try:
            t0 = time.monotonic()
            time.sleep(1.0)  # every call is open at the server
            for _ in range(3):
                assert answer_within_3s(d.target, key, pid) < 3
            keyless, health, wrong_key = (h.codes() for h in held)
            assert keyless == [grpc.StatusCode.UNAUTHENTICATED] * HELD
            assert "missing API key" in held[0].calls[0].details()  # type: ignore[attr-defined]
            assert set(health) == set(wrong_key) == {None}  # still open, and holding nothing
            with httpx.Client(base_url=d.url, timeout=3) as h:
                assert h.get("/healthz").status_code == 200
            # their first message never came: the server ends them, none later than its wait
            for call in held[1].calls + held[2].calls:
                assert call.exception(timeout=FIRST_MESSAGE_S + 5) is not None  # type: ignore[attr-defined]
            assert time.monotonic() - t0 < FIRST_MESSAGE_S + 5
            assert set(held[1].codes()) == set(held[2].codes()) == {grpc.StatusCode.DEADLINE_EXCEEDED}
            assert "no request message within" in held[1].calls[0].details()  # type: ignore[attr-defined]
            assert answer_within_3s(d.target, key, pid) < 3
        finally:
            for h in held:
                h.close()


# -- HTTP: heads --------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def http(tmp_path_factory: pytest.TempPathFactory, redis_url: str) -> Iterator[GrpcDeployment]:
    """`geomatch serve` (REST and gRPC), Redis mode without a worker (nothing runs), a short head
    timeout and a small pair limit."""
    with running_grpc(
        tmp_path_factory.mktemp("held-http"),
        redis_url,
        "serve",
        GEOMATCH_HEAD_TIMEOUT_S=str(HEAD_TIMEOUT_S),
        GEOMATCH_MAX_PAIRS_PER_JOB=str(MAX_PAIRS),
    ) as d:
        yield d


def port_of(d: GrpcDeployment) -> int:
    return int(d.url.rsplit(":", 1)[1])


def read_all(s: socket.socket) -> bytes:
    answer = b""
    with contextlib.suppress(ConnectionResetError):
        while chunk := s.recv(65536):
            answer += chunk
    return answer


def read_response(s: socket.socket) -> bytes:
    """One response of a keep-alive connection: its head and its Content-Length of body."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = s.recv(65536)
        assert chunk, data
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    length = int(
        next(
            line.split(b":")[1] for line in head.lower().split(b"\r\n") if line.startswith(b"content-length:")
        )
    )
    while len(body) < length:
        body += s.recv(65536)
    return head + b"\r\n\r\n" + body


def test_a_malformed_head_is_400_whatever_follows(http: GrpcDeployment) -> None:
    for bad in (b"X-Bad: a\x00b", b"Bad Name: v"):  # a NUL in a value, a space in a name
        head = b"POST /v1/projects HTTP/1.1\r\nHost: x\r\n" + bad + b"\r\nContent-Length: 40000\r\n\r\n"
        for body in (b"", b"{" * 40_000):  # nothing after it, and more than h11's 16 KiB head limit
            with socket.create_connection(("127.0.0.1", port_of(http)), timeout=10) as s:
                s.sendall(head + body)
                answer = read_all(s)
            assert answer.startswith(b"HTTP/1.1 400 "), (bad, len(body), answer[:200])


def test_a_slow_head_is_closed_after_the_head_timeout(http: GrpcDeployment) -> None:
    # a head dribbled a byte every 0.2 s: 408, about HEAD_TIMEOUT_S after its first byte, and closed
    with socket.create_connection(("127.0.0.1", port_of(http)), timeout=10) as s:
        t0 = time.monotonic()
        s.sendall(b"GET /healthz HTTP/1.1\r\n")
        s.settimeout(0.2)
        answer = b""
        while not answer and time.monotonic() - t0 < HEAD_TIMEOUT_S + 5:
            s.sendall(b"X")
            with contextlib.suppress(TimeoutError):
                answer = s.recv(65536)
        took = time.monotonic() - t0
        s.settimeout(10)
        answer += read_all(s)  # then the server closes
    assert answer.startswith(b"HTTP/1.1 408 "), answer[:200]
    assert HEAD_TIMEOUT_S - 0.5 < took < HEAD_TIMEOUT_S + 2, took
    # a connection that sends nothing is closed too
    with socket.create_connection(("127.0.0.1", port_of(http)), timeout=10) as s:
        t0 = time.monotonic()
        assert read_all(s) == b""
        assert time.monotonic() - t0 < HEAD_TIMEOUT_S + 2


def test_keep_alive_and_slow_bodies_outlive_the_head_timeout(http: GrpcDeployment) -> None:
    key = http.create_key("held-http")
    with socket.create_connection(("127.0.0.1", port_of(http)), timeout=30) as s:
        # two requests on one connection, 1 s apart (within uvicorn's 5 s keep-alive)
        for _ in range(2):
            s.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
            assert read_response(s).startswith(b"HTTP/1.1 200 ")
            time.sleep(1.0)
        # a body sent over 2.5 x the head timeout, its head at once
        body = b'{"name": "slow body"}'
        s.sendall(
            b"POST /v1/projects HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
            b"Authorization: Bearer " + key.encode() + b"\r\nContent-Length: %d\r\n\r\n" % len(body)
        )
        for i in range(0, len(body), 4):
            s.sendall(body[i : i + 4])
            time.sleep(HEAD_TIMEOUT_S * 2.5 / (len(body) / 4))
        assert read_response(s).startswith(b"HTTP/1.1 201 ")


# -- pairs per job ------------------------------------------------------------------------------
def six_images(c: httpx.Client) -> str:
    """A project of 6 noise images: 15 pairs exhaustive, over the limit of 10."""
    return noise_project(c, "pairs", tuple(f"{i}.png" for i in range(6)))


def assert_split_advice(message: str, pairs: int) -> None:
    assert f"would plan {pairs} pairs" in message, message
    assert f"limit of {MAX_PAIRS} pairs per job" in message and "GEOMATCH_MAX_PAIRS_PER_JOB" in message
    for spec in ('"gps:1"', '"retrieval:1"', '"sequential:1"'):
        assert spec in message, message


def test_an_exhaustive_match_over_the_pair_limit_is_refused(http: GrpcDeployment) -> None:
    key = http.create_key("held-pairs")
    with http.client(key) as c, http.grpc_client(key) as g:
        pid = six_images(c)
        r = c.post(f"/v1/projects/{pid}/match", json={"pairs": "exhaustive"})
        assert r.status_code == 422, r.text
        assert_split_advice(r.json()["detail"], 15)
        with pytest.raises(grpc.RpcError) as e:
            g.stub.SubmitMatching(
                pb2.SubmitMatchingRequest(project_id=pid, pair_spec="exhaustive"),
                metadata=g.metadata,
                timeout=10,
            )
        assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED  # type: ignore[attr-defined]
        assert_split_advice(e.value.details(), 15)  # type: ignore[attr-defined]
        assert c.get(f"/v1/projects/{pid}/jobs").json()["jobs"] == []  # nothing started
        # a plan under the limit is queued: sequential:1 is 5 pairs
        assert c.post(f"/v1/projects/{pid}/match", json={"pairs": "sequential:1"}).status_code == 202


def test_a_plan_only_its_step_can_size_fails_before_writing_a_pair(tmp_path: Path) -> None:
    """Embedded mode (the plan step runs in the server): ``auto`` over 6 images without GPS is
    exhaustive, which the API cannot tell without reading the images: the job fails with the
    advice and has no pair rows."""
    with running_grpc(tmp_path, None, "serve", GEOMATCH_MAX_PAIRS_PER_JOB=str(MAX_PAIRS)) as d:
        with d.client(d.create_key("held-auto")) as c:
            pid = six_images(c)
            r = c.post(f"/v1/projects/{pid}/match", json={"pairs": "auto"})
            assert r.status_code == 202, r.text
            job = r.json()["job_id"]
            deadline = time.monotonic() + 120
            while (j := c.get(f"/v1/jobs/{job}").json())["state"] not in TERMINAL:
                assert time.monotonic() < deadline, j
                time.sleep(0.3)
        assert j["state"] == "failed", j
        assert_split_advice(j["error"], 15)
        assert "exhaustive over 6 images" in j["error"]
        assert d.metadata("SELECT count(*) FROM job_pairs WHERE job_id = ?", job) == [(0,)]
