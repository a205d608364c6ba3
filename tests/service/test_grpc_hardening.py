"""Regression tests for what a hostile probe of the gRPC API found: text that is not UTF-8 or holds
control characters, file names over 255 bytes (INVALID_ARGUMENT, no server path in the message),
and idle streams of one tenant that, unlimited, take every handler thread, so that health checks and
GetProject miss a 3 s deadline.

The server runs in Redis mode with no worker (no job runs here), its per-tenant stream limit raised
to 30 so that two tenants reach into the slots kept for others, and a short idle timeout."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from service.clients.grpc_client import GrpcClient, ImageSource
from service.grpcapi.limits import STREAMS
from service.grpcapi.pb import pb2

from .grpc_harness import GrpcDeployment, error_of, running_grpc

pytestmark = pytest.mark.service

PER_TENANT = 30
SHARE = PER_TENANT // 4  # what a tenant may hold of the last quarter of the slots (service/slots.py)
IDLE_S = 15


@pytest.fixture(scope="module")
def dep(tmp_path_factory: pytest.TempPathFactory, redis_url: str) -> Iterator[GrpcDeployment]:
    with running_grpc(
        tmp_path_factory.mktemp("grpc-hardening"),
        redis_url,
        GEOMATCH_GRPC_TENANT_STREAMS=str(PER_TENANT),
        GEOMATCH_GRPC_STREAM_IDLE=str(IDLE_S),
    ) as d:
        yield d


@pytest.fixture(scope="module")
def keys(dep: GrpcDeployment) -> dict[str, str]:
    return {t: dep.create_key(f"hardening-{t}") for t in "abc"}


@pytest.fixture(scope="module")
def a(dep: GrpcDeployment, keys: dict[str, str]) -> Iterator[GrpcClient]:
    with dep.grpc_client(keys["a"], timeout=60) as c:
        yield c


def varint(n: int) -> bytes:
    out = b""
    while True:
        byte, n = n & 0x7F, n >> 7
        out += bytes([byte | (0x80 if n else 0)])
        if not n:
            return out


def field(number: int, data: bytes) -> bytes:
    """A length-delimited protobuf field, bytes as they are (protobuf's own encoder refuses bad
    UTF-8: a hostile client does not use it)."""
    return varint(number << 3 | 2) + varint(len(data)) + data


def raw(c: GrpcClient, method: str, streaming: bool = False) -> Any:
    path = f"/geomatch.v1.Matching/{method}"
    make = c.channel.stream_unary if streaming else c.channel.unary_unary
    return make(path, request_serializer=lambda b: b, response_deserializer=lambda b: b)


# -- text ------------------------------------------------------------------------------------------
def test_text_that_is_not_utf8_or_holds_controls_is_invalid(a: GrpcClient, dep: GrpcDeployment) -> None:
    before = len(a.list_projects())
    for name in (b"\xed\xa0\x80", b"ok\xed\xa0\xbd"):  # UTF-8 bytes of lone surrogates
        code, details = error_of(lambda n=name: raw(a, "CreateProject")(field(1, n), metadata=a.metadata))
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "malformed request" in details, details
    code, details = error_of(lambda: a.create_project("a\x00b"))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "control character U+0000" in details, details
    assert len(a.list_projects()) == before

    pid = a.create_project("names").id
    header = field(2, field(1, b"a\xed\xa0\x80.png"))  # UploadImagesRequest.image.name
    messages = [field(1, pid.encode()), header, field(3, b"\x89PNG")]
    code, details = error_of(
        lambda: raw(a, "UploadImages", streaming=True)(iter(messages), metadata=a.metadata, timeout=30)
    )
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "malformed request" in details, details
    assert dep.project_state(pid) == ([], 0, [])


def test_file_name_over_255_bytes_is_invalid_and_leaks_no_path(
    a: GrpcClient, dep: GrpcDeployment, scene: Path
) -> None:
    pid = a.create_project("long names").id
    img = scene / "images"
    code, details = error_of(
        lambda: a.upload(
            pid,
            [
                ImageSource.of(img / "ground_00.png"),
                ImageSource.of(img / "ground_01.png", name="文" * 100 + ".jpg"),
            ],
        )
    )
    assert code == grpc.StatusCode.INVALID_ARGUMENT, (code, details)
    assert "304 bytes" in details and "at most 255 bytes" in details, details
    assert str(dep.home) not in details and "upload-" not in details and "/" not in details, details
    assert dep.project_state(pid) == ([], 0, [])
    assert dep.wait_unstaged() == []


# -- idle streams ------------------------------------------------------------------------------------
class IdleStreams:
    """``n`` UploadImages calls of one key, each sending its first message and then nothing until
    ``release`` (or the server ends it)."""

    def __init__(self, c: GrpcClient, project_id: str, n: int, release: threading.Event) -> None:
        def messages() -> Iterator[Any]:
            yield pb2.UploadImagesRequest(project_id=project_id)
            release.wait(120)

        self.calls = [
            c.stub.UploadImages.future(messages(), metadata=c.metadata, timeout=120) for _ in range(n)
        ]

    def done(self) -> list[Any]:
        return [f for f in self.calls if f.done()]

    def wait_done(self, n: int, timeout: float) -> list[Any]:
        deadline = time.monotonic() + timeout
        while len(self.done()) < n and time.monotonic() < deadline:
            time.sleep(0.05)
        return self.done()


def test_idle_streams_cannot_stall_health_or_unary_calls(
    dep: GrpcDeployment, keys: dict[str, str], scene: Path
) -> None:
    """70 idle authenticated upload streams of one tenant (the probe's attack): 30 are held, 40
    refused at once; a second tenant asking for the server's remaining 18 stream slots gets its share
    (7: the last 12 are kept for tenants holding fewer); a third tenant's upload still goes through;
    health and GetProject still answer within 3 s; the idle streams are cut after
    GEOMATCH_GRPC_STREAM_IDLE and their slots come back."""
    assert STREAMS == 48
    release = threading.Event()
    with (
        dep.grpc_client(keys["a"]) as a,
        dep.grpc_client(keys["b"]) as b,
        dep.grpc_client(keys["c"]) as c,
        grpc.insecure_channel(dep.target) as ch,
    ):
        try:
            pa, pb, pc = (x.create_project("idle").id for x in (a, b, c))
            t0 = time.monotonic()
            health = health_pb2_grpc.HealthStub(ch)

            def answers_within_3s() -> None:
                t = time.monotonic()
                r = health.Check(health_pb2.HealthCheckRequest(service=""), timeout=3)
                assert r.status == health_pb2.HealthCheckResponse.SERVING
                for x, p in ((a, pa), (c, pc)):
                    asked = pb2.GetProjectRequest(project_id=p)
                    assert x.stub.GetProject(asked, metadata=x.metadata, timeout=3).id == p
                assert time.monotonic() - t < 3

            streams_a = IdleStreams(a, pa, 70, release)
            refused = streams_a.wait_done(70 - PER_TENANT, timeout=15)
            answers_within_3s()
            assert len(refused) == 70 - PER_TENANT, len(refused)
            for f in refused:
                assert f.code() == grpc.StatusCode.RESOURCE_EXHAUSTED, (f.code(), f.details())
                assert "the most one tenant may hold" in f.details(), f.details()

            # a second tenant gets its share of the rest; the reserve is left for a third
            streams_b = IdleStreams(b, pb, STREAMS - PER_TENANT, release)
            refused_b = streams_b.wait_done(STREAMS - PER_TENANT - SHARE, timeout=15)
            time.sleep(1.0)
            assert len(streams_b.done()) == len(refused_b) == STREAMS - PER_TENANT - SHARE
            assert len(streams_a.done()) == 70 - PER_TENANT
            for f in refused_b:
                assert f.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and "keeps the rest" in f.details()
            uploaded = c.upload(pc, [ImageSource.of(scene / "images" / "ground_00.png")])
            assert [i.name for i in uploaded] == ["ground_00.png"]
            for _ in range(5):  # 37 streams held open: unary calls and health still have threads
                answers_within_3s()
            assert time.monotonic() - t0 < IDLE_S, "too slow to check before the idle timeout"

            # nothing sent for IDLE_S: the server cancels them, and the slots are free again
            held = [f for f in streams_a.calls + streams_b.calls if not f.done()]
            assert len(held) == PER_TENANT + SHARE
            ended = [f for f in held if f.exception(timeout=IDLE_S + 10) is not None]
            assert len(ended) == PER_TENANT + SHARE
            assert {f.code() for f in held} == {grpc.StatusCode.CANCELLED}
            assert time.monotonic() - t0 >= IDLE_S - 1
            uploaded = a.upload(pa, [ImageSource.of(scene / "images" / "ground_00.png")])
            assert [i.name for i in uploaded] == ["ground_00.png"]
            assert dep.project_state(pb) == ([], 0, [])
        finally:
            release.set()
    assert dep.wait_unstaged() == []


def test_a_busy_stream_is_not_idle(dep: GrpcDeployment, a: GrpcClient, scene: Path) -> None:
    """An upload whose chunks keep coming, each within the idle timeout, outlives it."""
    pid = a.create_project("slow").id
    data = (scene / "images" / "ground_02.png").read_bytes()
    step = len(data) // 2 + 1

    def messages() -> Iterator[Any]:
        yield pb2.UploadImagesRequest(project_id=pid)
        h = pb2.ImageHeader(name="slow.png", capture=pb2.CAPTURE_GROUND)
        yield pb2.UploadImagesRequest(image=h)
        for i in range(0, len(data), step):
            time.sleep(IDLE_S * 0.6)
            yield pb2.UploadImagesRequest(chunk=data[i : i + step])

    r = a.stub.UploadImages(messages(), metadata=a.metadata, timeout=IDLE_S * 4)
    assert [i.name for i in r.images] == ["slow.png"]
