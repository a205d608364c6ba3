"""What one client may cost the service: request bodies are refused on their head (401 before the
body of a wrong key, 413 as soon as a body is over a limit), list routes answer pages, API-side
heavy calls and gRPC streams are shared fairly between tenants, and quotas and a request rate hold
per tenant.

The probes these reproduce: a 1 GiB upload or a 400 MiB JSON body with a wrong key was read to the
end before its 401 (1.2 GiB of temporary files); a 1 GiB file with a valid key got its 413 only
once spooled; 1002 projects listed in one answer; 45 waiting match pictures froze /healthz for two
minutes; 48 idle gRPC streams of three tenants locked every other tenant out; a key created 1000
projects and made 2777 requests in 15 s unchecked.
"""

from __future__ import annotations

import os
import select
import socket
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import grpc
import pytest

from service.clients.grpc_client import GrpcClient, ImageSource
from service.grpcapi.limits import STREAMS
from service.grpcapi.pb import pb2

from .grpc_harness import GrpcDeployment, error_of
from .harness import Deployment, deployed, noise_png, noise_project

pytestmark = pytest.mark.service

MiB = 1024 * 1024
GiB = 1024 * MiB


@pytest.fixture(scope="module")
def dep(tmp_path_factory: pytest.TempPathFactory, redis_url: str) -> Iterator[GrpcDeployment]:
    """Redis mode, no worker (a picture waits for one in vain), REST and gRPC in one process."""
    d = GrpcDeployment(
        tmp_path_factory.mktemp("limits"),
        redis_url,
        GEOMATCH_MAX_UPLOAD_MB="2",
        GEOMATCH_MAX_REQUEST_MB="8",
        GEOMATCH_MAX_JSON_MB="1",
        GEOMATCH_RENDER_TIMEOUT="20",
        TMPDIR=str(tmp_path_factory.mktemp("limits-tmpdir")),
    )
    with deployed(d, workers=0, grpc="serve") as running:
        yield running


@pytest.fixture(scope="module")
def key(dep: GrpcDeployment) -> str:
    return dep.create_key("limits")


@pytest.fixture(scope="module")
def project(dep: GrpcDeployment, key: str) -> str:
    with dep.client(key) as c:
        return noise_project(c, "limits")


# -- request bodies ------------------------------------------------------------------------------
def open_files_over(pid: int, size: int) -> list[tuple[str, int]]:
    """Regular files the process holds open that are larger than ``size`` (deleted ones too:
    spooled uploads are unlinked temporary files)."""
    out = []
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            st = os.stat(f"/proc/{pid}/fd/{fd}")
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if st.st_size > size and os.path.isfile(f"/proc/{pid}/fd/{fd}"):
            out.append((target, st.st_size))
    return out


def rss_mib(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        kib = next(int(line.split()[1]) for line in f if line.startswith("VmRSS:"))
    return kib / 1024


def send_until_answered(
    d: Deployment, head: bytes, body: Iterator[bytes], during: Any = None
) -> tuple[bytes, int]:
    """Sends ``head``, then ``body`` chunk by chunk until the server answers; returns the answer's
    head and how many body bytes had been sent by then. ``during()`` runs once, mid-body."""
    port = int(d.url.rsplit(":", 1)[1])
    sent, answer, checked = 0, b"", during is None
    with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
        s.sendall(head)
        s.setblocking(False)
        pending = b""
        deadline = time.monotonic() + 60
        while b"\r\n\r\n" not in answer:
            assert time.monotonic() < deadline, "no answer within 60 s"
            readable, writable, _ = select.select([s], [s] if pending is not None else [], [], 1)
            if readable:
                chunk = s.recv(65536)
                if not chunk:
                    break
                answer += chunk
                continue
            if writable:
                if not pending:
                    pending = next(body, None)
                    if pending is None:
                        continue
                try:
                    n = s.send(pending)
                except (BrokenPipeError, ConnectionResetError):
                    pending = None
                    continue
                sent += n
                pending = pending[n:]
                if not checked and sent > 4 * MiB:
                    checked = True
                    during()
    return answer, sent


def zeros(total: int, chunk: int = 256 * 1024) -> Iterator[bytes]:
    block = b"\0" * chunk
    while total > 0:
        yield block[: min(chunk, total)]
        total -= chunk


def chunked(parts: Iterator[bytes]) -> Iterator[bytes]:
    for p in parts:
        if not p:  # a chunk of 0 bytes would end the body
            continue
        yield f"{len(p):x}\r\n".encode() + p + b"\r\n"
    yield b"0\r\n\r\n"


BOUNDARY = "limitsboundary"


def upload_head(pid: str, key: str | None, length: int | None) -> bytes:
    lines = [
        f"POST /v1/projects/{pid}/images HTTP/1.1",
        "Host: x",
        f"Content-Type: multipart/form-data; boundary={BOUNDARY}",
        *([f"Authorization: Bearer {key}"] if key else []),
        f"Content-Length: {length}" if length is not None else "Transfer-Encoding: chunked",
    ]
    return ("\r\n".join(lines) + "\r\n\r\n").encode()


def part_head(name: str) -> bytes:
    return (
        f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="files"; filename="{name}"\r\n'
        "Content-Type: image/png\r\n\r\n"
    ).encode()


def assert_cheap(d: Deployment, before_mib: float) -> None:
    assert d.server is not None
    assert open_files_over(d.server.pid, MiB) == []
    assert rss_mib(d.server.pid) - before_mib < 64, (before_mib, rss_mib(d.server.pid))
    assert sorted((d.home / "tmp").glob("upload-*")) == []


def test_a_wrong_key_is_refused_before_the_body_of_a_large_upload(dep: GrpcDeployment, project: str) -> None:
    """1 GiB announced and streaming: the 401 arrives while the client is still sending, having
    sent a few MiB at most; the server holds no large file and grew by no more than noise."""
    assert dep.server is not None
    before = rss_mib(dep.server.pid)
    for key in ("gm_wrong", None):
        body = iter([part_head("big.png"), *zeros(GiB)])
        answer, sent = send_until_answered(
            dep, upload_head(project, key, GiB + 200), body, during=lambda: assert_cheap(dep, before)
        )
        assert answer.startswith(b"HTTP/1.1 401 "), answer[:300]
        assert sent < 64 * MiB, sent
        assert_cheap(dep, before)
    # chunked (no length to check): the same
    answer, sent = send_until_answered(
        dep, upload_head(project, "gm_wrong", None), chunked(iter([part_head("big.png"), *zeros(GiB)]))
    )
    assert answer.startswith(b"HTTP/1.1 401 "), answer[:300]
    assert sent < 64 * MiB, sent
    assert_cheap(dep, before)


def test_a_wrong_key_is_refused_before_a_large_json_body(dep: GrpcDeployment) -> None:
    assert dep.server is not None
    before = rss_mib(dep.server.pid)
    head = b"POST /v1/projects HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
    head += f"Content-Length: {400 * MiB}\r\n\r\n".encode()
    answer, sent = send_until_answered(dep, head, iter([b'{"name": "', *zeros(400 * MiB)]))
    assert answer.startswith(b"HTTP/1.1 401 "), answer[:300]
    assert sent < 64 * MiB, sent
    assert_cheap(dep, before)


def test_a_valid_key_over_a_limit_gets_413_early(dep: GrpcDeployment, key: str, project: str) -> None:
    """Over the request limit by its Content-Length, a file over the per-file limit in a chunked
    body, several files over the request limit together: 413 before the body is all sent, and
    nothing stored."""
    assert dep.server is not None
    before = rss_mib(dep.server.pid)
    cases = {
        "announced 1 GiB": (upload_head(project, key, GiB + 200), iter([part_head("a.png"), *zeros(GiB)])),
        "one 1 GiB file, chunked": (
            upload_head(project, key, None),
            chunked(iter([part_head("a.png"), *zeros(GiB)])),
        ),
        "six files of 1.9 MiB": (
            upload_head(project, key, None),
            chunked(
                iter(
                    [
                        p
                        for i in range(6)
                        for p in (b"\r\n" if i else b"", part_head(f"{i}.png"), *zeros(19 * MiB // 10))
                    ]
                )
            ),
        ),
    }
    for what, (head, body) in cases.items():
        answer, sent = send_until_answered(dep, head, body)
        assert answer.startswith(b"HTTP/1.1 413 "), (what, answer[:300])
        assert sent < 64 * MiB, (what, sent)
        assert_cheap(dep, before)
    with dep.client(key) as c:
        names = [i["name"] for i in c.get(f"/v1/projects/{project}/images").json()["images"]]
        assert names == ["0.png", "1.png"]
        r = c.post(
            "/v1/projects",
            content=b'{"name": "' + b"x" * (2 * MiB) + b'"}',
            headers={"content-type": "application/json"},
        )
        assert r.status_code == 413 and "over 1 MiB" in r.json()["detail"], r.text
        # under the limits the same routes still work
        files = [("files", (f"ok{i}.png", noise_png(10 + i), "image/png")) for i in range(3)]
        assert c.post(f"/v1/projects/{project}/images", files=files).status_code == 201


def test_a_grpc_upload_stream_is_bounded_over_all_its_images(
    dep: GrpcDeployment, key: str, tmp_path: Path
) -> None:
    """Five images of 1.9 MiB, each under the 2 MiB file limit, 9.5 MiB together in one stream
    against the 8 MiB request limit: RESOURCE_EXHAUSTED naming the limit, and none of them stored
    (the multipart route's six files of 1.9 MiB get 413 the same way, above)."""
    side = 800  # noise does not compress: 800 x 800 RGB is a 1.9 MiB PNG
    paths = []
    for i in range(5):
        path = tmp_path / f"big{i}.png"
        path.write_bytes(noise_png(200 + i, side))
        assert 1.8 * MiB < path.stat().st_size < 2 * MiB
        paths.append(path)
    g = dep.grpc_client(key)
    try:
        pid = g.create_project("stream-total").id
        with pytest.raises(grpc.RpcError) as caught:
            g.upload(pid, [ImageSource.of(p) for p in paths])
        assert caught.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED, caught.value.details()
        assert "8 MiB for one upload together" in (caught.value.details() or "")
        assert list(g.list_images(pid)) == []
        # the same images in two calls are two uploads under the limit
        assert len(g.upload(pid, [ImageSource.of(p) for p in paths[:3]])) == 3
        assert len(g.upload(pid, [ImageSource.of(p) for p in paths[3:]])) == 2
    finally:
        g.close()


# -- pagination ----------------------------------------------------------------------------------
def test_lists_come_in_pages(dep: GrpcDeployment) -> None:
    """REST: ?limit and ?offset, the next page in Link; gRPC: page_size and page_token."""
    key = dep.create_key("pages")
    with dep.client(key) as c, dep.grpc_client(key) as g:
        made = [c.post("/v1/projects", json={"name": f"p{i}"}).json()["id"] for i in range(5)]
        seen, url = [], "/v1/projects?limit=2"
        while url:
            r = c.get(url)
            assert r.status_code == 200 and len(r.json()) <= 2
            seen += [p["id"] for p in r.json()]
            url = r.links.get("next", {}).get("url", "")
        assert seen == made
        assert [p["id"] for p in c.get("/v1/projects").json()] == made  # default page: 100
        assert c.get("/v1/projects?limit=1001").status_code == 422
        first = g.stub.ListProjects(pb2.ListProjectsRequest(page_size=3), metadata=g.metadata, timeout=10)
        assert [p.id for p in first.projects] == made[:3] and first.next_page_token
        rest = g.stub.ListProjects(
            pb2.ListProjectsRequest(page_size=3, page_token=first.next_page_token),
            metadata=g.metadata,
            timeout=10,
        )
        assert [p.id for p in rest.projects] == made[3:] and rest.next_page_token == ""
        assert [p.id for p in g.list_projects()] == made
        code, _ = error_of(
            lambda: g.stub.ListProjects(
                pb2.ListProjectsRequest(page_token="nope"), metadata=g.metadata, timeout=10
            )
        )
        assert code == grpc.StatusCode.INVALID_ARGUMENT
        files = [("files", (f"{i}.png", noise_png(i), "image/png")) for i in range(3)]
        assert c.post(f"/v1/projects/{made[0]}/images", files=files).status_code == 201
        r = c.get(f"/v1/projects/{made[0]}/images?limit=2")
        assert [i["name"] for i in r.json()["images"]] == ["0.png", "1.png"]
        assert [i["name"] for i in c.get(r.links["next"]["url"]).json()["images"]] == ["2.png"]
        assert [i.name for i in g.list_images(made[0])] == ["0.png", "1.png", "2.png"]


# -- heavy calls ---------------------------------------------------------------------------------
def test_waiting_pictures_cannot_starve_health_or_other_tenants(
    dep: GrpcDeployment, key: str, project: str
) -> None:
    """45 concurrent matches.png of one tenant while no worker runs: two wait for a worker (the
    tenant's heavy slots), the rest are 429 with Retry-After at once; /healthz, /readyz and another
    tenant's calls answer meanwhile."""
    other = dep.create_key("limits-other")
    url = f"/v1/projects/{project}/pairs/0.png/1.png/matches.png"
    with (
        ThreadPoolExecutor(45) as pool,
        dep.client(key) as c,
        dep.client(other) as o,
        dep.client(None) as anon,
    ):
        futures = [pool.submit(c.get, url) for _ in range(45)]
        time.sleep(2)  # every request is in; two of them wait for their worker
        for _ in range(3):
            assert anon.get("/healthz", timeout=5).status_code == 200
            # it answers at once; no worker runs here, so its answer is "not ready"
            assert anon.get("/readyz", timeout=5).status_code == 503
            assert o.get("/v1/projects", timeout=5).status_code == 200
        refused = [f.result(timeout=5) for f in futures if f.done()]
        assert len(refused) == 43, len(refused)
        for r in refused:
            assert r.status_code == 429 and r.headers["retry-after"] == "1", r.text
        waited = [f.result(timeout=60) for f in futures]
    assert sorted(r.status_code for r in waited).count(503) == 2


# -- gRPC streams --------------------------------------------------------------------------------
def idle_uploads(c: GrpcClient, project_id: str, n: int, release: threading.Event) -> list[Any]:
    def messages() -> Iterator[Any]:
        yield pb2.UploadImagesRequest(project_id=project_id)
        release.wait(120)

    return [c.stub.UploadImages.future(messages(), metadata=c.metadata, timeout=120) for _ in range(n)]


def test_three_tenants_holding_idle_streams_cannot_lock_out_a_fourth(
    dep: GrpcDeployment, tmp_path: Path
) -> None:
    """Three tenants open 16 idle upload streams each (the per-tenant default): the first two hold
    16, the third only its share (4) as the last slots are kept for tenants holding few; a fourth
    tenant's upload goes through."""
    assert STREAMS == 48
    keys = [dep.create_key(f"streams-{i}") for i in range(4)]
    release = threading.Event()
    image = tmp_path / "a.png"
    image.write_bytes(noise_png(99))
    clients = [dep.grpc_client(k) for k in keys]
    try:
        pids = [g.create_project("streams").id for g in clients]
        held: list[list[Any]] = []
        for g, pid in zip(clients[:3], pids, strict=False):
            calls = idle_uploads(g, pid, 16, release)
            time.sleep(1.5)
            held.append(calls)
        refused = [[f for f in calls if f.done()] for calls in held]
        assert [len(r) for r in refused] == [0, 0, 12], [len(r) for r in refused]
        for f in refused[2]:
            assert f.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and "keeps the rest" in f.details()
        uploaded = clients[3].upload(pids[3], [ImageSource.of(image)])
        assert [i.name for i in uploaded] == ["a.png"]
    finally:
        release.set()
        for g in clients:
            g.close()


# -- quotas and rate -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Deployment]:
    """Embedded, with small quotas and a low request rate."""
    d = Deployment(
        tmp_path_factory.mktemp("quotas"),
        None,
        GEOMATCH_QUOTA_PROJECTS="3",
        GEOMATCH_QUOTA_IMAGES="3",
        GEOMATCH_QUOTA_MB="1",
        GEOMATCH_RATE_LIMIT="5",
        GEOMATCH_RATE_BURST="40",
    )
    with deployed(d, workers=0) as running:
        yield running


def test_quotas_of_a_tenant(small: Deployment) -> None:
    key = small.create_key("quota")
    with small.client(key) as c:
        pids = [c.post("/v1/projects", json={"name": f"q{i}"}).json()["id"] for i in range(3)]
        r = c.post("/v1/projects", json={"name": "q3"})
        assert r.status_code == 403 and "quota is 3" in r.json()["detail"], r.text
        files = [("files", (f"{i}.png", noise_png(i), "image/png")) for i in range(2)]
        assert c.post(f"/v1/projects/{pids[0]}/images", files=files).status_code == 201
        files = [("files", (f"{i}.png", noise_png(10 + i), "image/png")) for i in range(2)]
        r = c.post(f"/v1/projects/{pids[1]}/images", files=files)
        assert r.status_code == 403 and "images" in r.json()["detail"], r.text
        assert c.get(f"/v1/projects/{pids[1]}/images").json()["images"] == []
        big = [("files", ("big.png", noise_png(5, side=700), "image/png"))]  # ~1.4 MiB of noise
        r = c.post(f"/v1/projects/{pids[1]}/images", files=big)
        assert r.status_code == 403 and "bytes" in r.json()["detail"], r.text
        assert c.delete(f"/v1/projects/{pids[2]}").status_code == 204  # room for one again
        assert c.post("/v1/projects", json={"name": "again"}).status_code == 201
    other = small.create_key("quota-other")  # quotas are per tenant
    with small.client(other) as c:
        assert c.post("/v1/projects", json={"name": "mine"}).status_code == 201


def test_a_tenant_over_its_rate_gets_429_with_retry_after(small: Deployment) -> None:
    key, other = small.create_key("rate"), small.create_key("rate-other")
    with small.client(key) as c, small.client(other) as o:
        burst = [c.get("/v1/projects") for _ in range(120)]
        codes = [r.status_code for r in burst]
        assert codes[:40] == [200] * 40 and 429 in codes and set(codes) <= {200, 429}, codes
        # the refused answer itself says when to come back: a request sent after the burst may
        # already find a token refilled (5 a second) on a loaded machine
        refused = burst[codes.index(429)]
        assert int(refused.headers["retry-after"]) >= 1, refused.text
        assert o.get("/v1/projects").status_code == 200  # another tenant is not slowed
        assert c.get("/healthz").status_code == 200
        time.sleep(1.5)
        assert c.get("/v1/projects").status_code == 200  # tokens come back
