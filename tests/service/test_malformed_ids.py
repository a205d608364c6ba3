"""Ids in paths and messages that no resource could have (a NUL byte, other control characters,
the wrong characters or length) are 404 / NOT_FOUND on every route and every gRPC method that
takes one, and never reach the store: PostgreSQL refuses NUL in text with an error of its own,
which was a 500 / INTERNAL on every such route and method.

The routes and methods are read from the OpenAPI schema and the service descriptor, so one added
later is tested too. One `geomatch serve` (HTTP and gRPC) per store, Redis mode with no worker."""

from __future__ import annotations

import re
from collections.abc import Iterator
from typing import Any

import grpc
import pytest

from service.grpcapi.pb import SERVICE, pb2

from .grpc_harness import SERVED_METHODS, serving_on_store
from .harness import noise_png, noise_project

pytestmark = pytest.mark.service

# as they go into the URL (percent-encoded) and as the server reads them
BAD = ["%00", "x%00y", "a%00.jpg", "%0A", "%7F", "Z" * 300, "g" * 32, "0" * 31]
NAMES = ("a.png", "b.png")
PARAM = re.compile(r"\{(\w+)\}")


@pytest.fixture(scope="module", params=["postgresql", "sqlite"])
def world(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory, redis_url: str
) -> Iterator[dict[str, Any]]:
    """A server, a key and the valid ids the other parameters of a path take."""
    with serving_on_store(tmp_path_factory.mktemp(f"ids-{request.param}"), redis_url, request.param) as d:
        key = d.create_key("ids")
        with d.client(key) as c:
            pid = noise_project(c, "ids", NAMES)
            job = c.post(f"/v1/projects/{pid}/match", json={}).json()["job_id"]
        good = {"project_id": pid, "job_id": job, "name": NAMES[0], "name0": NAMES[0], "name1": NAMES[1]}
        yield {"d": d, "key": key, "good": good}


def bodies(template: str, method: str) -> dict[str, Any]:
    """A request body the route takes, so that the id is what it stops at."""
    if method == "post" and template.endswith(("/images", "/localize")):
        return {"files": [("files", ("c.png", noise_png(9), "image/png"))]}
    if method == "post":  # match, reconstruct
        return {"json": {}}
    return {}


def test_every_route_answers_404_for_an_id_no_resource_can_have(world: dict[str, Any]) -> None:
    d, good = world["d"], world["good"]
    with d.client(world["key"]) as c:
        schema = c.get("/openapi.json").json()
        tried: list[str] = []
        for template, operations in schema["paths"].items():
            params = PARAM.findall(template)
            if not params:
                continue
            for method in operations:
                for param in params:
                    for bad in BAD:
                        path = template.format(**{**good, param: bad})
                        r = c.request(method.upper(), path, **bodies(template, method))
                        assert r.status_code == 404, (method, template, param, bad, r.status_code, r.text)
                        assert r.json()["detail"], r.text
                    tried.append(f"{method.upper()} {template} {param}")
        # the 15 operations on paths with an id today (a route added later is tried too)
        assert len({t.rsplit(" ", 1)[0] for t in tried}) >= 15, tried
        assert c.get(f"/v1/projects/{good['project_id']}").status_code == 200  # nothing was deleted


def requests_with(method: Any, bad: str) -> tuple[str, Any] | None:
    """(the id field, the method's request with it set to ``bad``), or None for a method without one."""
    cls = getattr(pb2, method.input_type.name)
    for field in ("project_id", "job_id"):
        if field in cls.DESCRIPTOR.fields_by_name:
            return field, cls(**{field: bad})
    return None


def test_every_grpc_method_answers_not_found_for_an_id_no_resource_can_have(world: dict[str, Any]) -> None:
    d = world["d"]
    covered = set()
    with d.grpc_client(world["key"], timeout=30) as g:
        for m in SERVICE.methods:
            for bad in ["\x00", "x\x00y", "\n", "\x7f", "Z" * 300, "g" * 32, "0" * 31]:
                found = requests_with(m, bad)
                if found is None:
                    continue
                field, req = found
                path = f"/{SERVICE.full_name}/{m.name}"
                kind = {
                    (False, False): g.channel.unary_unary,
                    (True, False): g.channel.stream_unary,
                    (False, True): g.channel.unary_stream,
                }[(m.client_streaming, m.server_streaming)]
                call = kind(
                    path, request_serializer=lambda x: x.SerializeToString(), response_deserializer=bytes
                )
                try:
                    answer = call(iter([req]) if m.client_streaming else req, metadata=g.metadata, timeout=30)
                    if m.server_streaming:
                        list(answer)
                except grpc.RpcError as e:
                    code, details = e.code(), e.details()
                else:
                    code, details = grpc.StatusCode.OK, ""
                assert code == grpc.StatusCode.NOT_FOUND, (m.name, field, bad, code, details)
                covered.add(m.name)
    assert covered == SERVED_METHODS - {"CreateProject", "ListProjects", "MatchPair"}  # those take no id
