"""What every HTTP response says about itself, and what a client cannot make the server keep or
choke on: security headers and no server banner, a bounded /metrics whatever methods clients make
up, and a readable 431 for a request head over the limit (a 200 KB header reset the connection).

One `geomatch serve` in Redis mode with no worker (no job runs here)."""

from __future__ import annotations

import re
import socket
from collections.abc import Iterator

import pytest

from .harness import Deployment, deployed, noise_project

pytestmark = pytest.mark.service


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory, redis_url: str) -> Iterator[tuple[Deployment, str]]:
    with deployed(Deployment(tmp_path_factory.mktemp("http-surface"), redis_url), workers=0) as d:
        yield d, d.create_key("surface")


def test_responses_carry_nosniff_no_store_on_tenant_data_and_no_server_banner(
    server: tuple[Deployment, str],
) -> None:
    d, key = server
    with d.client(key) as c, d.client(None) as anonymous:
        pid = noise_project(c, "headers")
        job = c.post(f"/v1/projects/{pid}/match", json={}).json()["job_id"]
        assert c.delete(f"/v1/jobs/{job}").json()["state"] == "cancelled"  # its event stream ends
        tenant_data = {
            "list": c.get("/v1/projects"),
            "project": c.get(f"/v1/projects/{pid}"),
            "image bytes": c.get(f"/v1/projects/{pid}/images/0.png"),
            "job events": c.get(f"/v1/jobs/{job}/events"),
            "404": c.get(f"/v1/projects/{'0' * 32}"),
            "422": c.post("/v1/projects", json={"name": ""}),
            "401": anonymous.get("/v1/projects"),
        }
        public = {
            "healthz": anonymous.get("/healthz"),
            "metrics": anonymous.get("/metrics"),
            "openapi": anonymous.get("/openapi.json"),
            "unknown path": anonymous.get("/nowhere"),
        }
    assert tenant_data["job events"].headers["content-type"].startswith("text/event-stream")
    for what, r in {**tenant_data, **public}.items():
        assert r.headers.get("x-content-type-options") == "nosniff", (what, r.headers)
        assert "server" not in r.headers, (what, r.headers)
    for what, r in tenant_data.items():
        assert r.headers.get("cache-control") == "no-store", (what, r.headers)


def method_labels(text: str) -> set[str]:
    return set(re.findall(r'^geomatch_http_requests_total\{method="([^"]*)"', text, re.M))


def test_made_up_methods_add_at_most_one_label_to_metrics(server: tuple[Deployment, str]) -> None:
    d, key = server
    with d.client(key) as c:
        assert c.get("/v1/projects").status_code == 200
        before = c.get("/metrics").text
        for i in range(200):
            r = c.request(f"MADEUP{i}", "/v1/projects" if i % 2 else "/healthz")
            assert r.status_code in (401, 405), r.text
        after = c.get("/metrics").text
    assert "GET" in method_labels(before)
    assert len(method_labels(after) - method_labels(before)) <= 1, method_labels(after) - method_labels(
        before
    )
    assert not any(label.startswith("MADEUP") for label in method_labels(after))
    assert len(after) - len(before) < 20_000, (len(before), len(after))


def test_a_request_head_over_the_limit_is_a_readable_431(server: tuple[Deployment, str]) -> None:
    d, key = server
    with d.client(key) as c:
        assert c.get("/v1/projects", headers={"X-Padding": "a" * 8000}).status_code == 200
        r = c.get("/v1/projects", headers={"X-Padding": "a" * 200_000})
        assert r.status_code == 431, r.text
        assert c.get("/v1/projects").status_code == 200  # the server goes on
    # a raw client that sends the whole head before it reads reads the answer, not a reset
    port = int(d.url.rsplit(":", 1)[1])
    with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
        s.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Padding: " + b"a" * 200_000 + b"\r\n\r\n")
        answer = b""
        while chunk := s.recv(65536):
            answer += chunk
    assert answer.startswith(b"HTTP/1.1 431 "), answer[:200]
