"""Regression tests for what a hostile probe of the REST API found, each on every store the service
runs on: the embedded default (SQLite, jobs in the API process), Redis mode over SQLite (the
session's deployment, with a worker) and Redis mode over PostgreSQL (``DATABASE_URL``, no worker).

Lone surrogates and control characters in stored text, file names over 255 bytes, concurrent
deletes of one project, loosely typed JSON, timestamps that changed form between POST and GET, and
the memory that validating one upload costs the API process."""

from __future__ import annotations

import re
import struct
import threading
import zlib
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import httpx
import pytest

from .harness import Deployment, deployed, metadata_database, upload, wait_job

pytestmark = pytest.mark.service

UTC_STAMP = re.compile(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{6}Z")
MiB = 1024 * 1024
JSON = {"content-type": "application/json"}


@pytest.fixture(scope="module", params=["embedded", "redis-sqlite", "redis-postgres"])
def server(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory, redis_url: str
) -> Iterator[tuple[Deployment, httpx.Client]]:
    if request.param == "redis-sqlite":
        d: Deployment = request.getfixturevalue("deployment")
        yield d, d.client(request.getfixturevalue("key_a"))
        return
    with metadata_database("postgresql" if request.param == "redis-postgres" else "sqlite") as url:
        env = {"DATABASE_URL": url} if url else {}
        d = Deployment(tmp_path_factory.mktemp(request.param), redis_url if url else None, **env)
        with deployed(d, workers=0) as running:
            yield running, running.client(running.create_key("hardening"))


def staged(d: Deployment) -> list[str]:
    return sorted(p.name for p in (d.home / "tmp").glob("upload-*"))


def two_images(c: httpx.Client, scene: Path, name: str) -> str:
    pid = str(c.post("/v1/projects", json={"name": name}).json()["id"])
    r = upload(c, pid, [scene / "images" / "ground_00.png", scene / "images" / "ground_01.png"], "ground")
    assert r.status_code == 201, r.text
    return pid


# -- text that cannot be stored ------------------------------------------------------------------
@pytest.mark.parametrize(
    ("body", "message"),
    [
        (rb'{"name": "\ud800"}', "lone UTF-16 surrogate"),
        (rb'{"name": "ok\ud83d"}', "lone UTF-16 surrogate"),
        (b'{"name": "\xed\xa0\x80"}', "lone UTF-16 surrogate"),  # the surrogate's own UTF-8 bytes
        (rb'{"name": "a\u0000b"}', "control character U+0000"),
        (rb'{"name": "tab\there"}', "control character U+0009"),
        (rb'{"name": "x", "config": {"pairs": "\udfff"}}', "bad pairs"),
        (rb'{"name": "x", "config": {"method": "geo\ud800"}}', "method must be one of"),
        (rb'{"name": "x", "\ud800": 1}', "unable to parse raw data as a unicode string"),
    ],
)
def test_text_that_cannot_be_stored_is_422(
    server: tuple[Deployment, httpx.Client], body: bytes, message: str
) -> None:
    _, c = server
    before = c.get("/v1/projects").json()
    r = c.post("/v1/projects", content=body, headers=JSON)
    assert r.status_code == 422, (r.status_code, r.text)
    assert message in r.json()["detail"], r.json()
    assert c.get("/v1/projects").json() == before


# -- file names ----------------------------------------------------------------------------------
def test_file_name_over_255_bytes_is_400_and_nothing_stored(
    server: tuple[Deployment, httpx.Client], scene: Path
) -> None:
    d, c = server
    pid = c.post("/v1/projects", json={"name": "long names"}).json()["id"]
    good = (scene / "images" / "ground_00.png").read_bytes()
    other = (scene / "images" / "ground_01.png").read_bytes()
    long_name = "文" * 100 + ".jpg"  # 104 characters, 304 bytes
    assert len(long_name) < 200 < len(long_name.encode())
    r = c.post(
        f"/v1/projects/{pid}/images",
        files=[("files", ("good.png", good, "image/png")), ("files", (long_name, other, "image/jpeg"))],
    )
    assert r.status_code == 400, r.text
    detail = r.json()["detail"]
    assert "304 bytes" in detail and "at most 255 bytes" in detail, detail
    assert str(d.home) not in detail and "upload-" not in detail, detail
    assert c.get(f"/v1/projects/{pid}/images").json()["images"] == []
    assert not list((d.home / "projects" / pid).glob("images/*"))
    assert staged(d) == []
    longest = "文" * 83 + ".png"  # 253 bytes: still a file name
    r = c.post(f"/v1/projects/{pid}/images", files=[("files", (longest, good, "image/png"))])
    assert r.status_code == 201 and r.json()["images"][0]["name"] == longest, r.text
    assert (d.home / "projects" / pid / "images" / longest).is_file()


@pytest.mark.parametrize(
    ("name", "message"),
    [("c1\x85.png", "control characters"), ("del\x7f.png", "control characters")],
)
def test_file_names_with_control_characters_are_400(
    server: tuple[Deployment, httpx.Client], scene: Path, name: str, message: str
) -> None:
    _, c = server
    pid = c.post("/v1/projects", json={"name": "controls"}).json()["id"]
    data = (scene / "images" / "ground_00.png").read_bytes()
    r = c.post(f"/v1/projects/{pid}/images", files=[("files", (name, data, "image/png"))])
    assert r.status_code == 400 and message in r.json()["detail"], r.text
    assert c.get(f"/v1/projects/{pid}/images").json()["images"] == []


# -- concurrent deletes ----------------------------------------------------------------------------
def test_concurrent_deletes_of_one_project_one_wins(
    server: tuple[Deployment, httpx.Client], scene: Path
) -> None:
    """10 clients delete one project at the same moment, 5 times: exactly one 204, nine 404."""
    d, c = server
    key = c.headers["authorization"].split()[1]
    clients = [d.client(key) for _ in range(10)]
    try:
        for round_ in range(5):
            pid = c.post("/v1/projects", json={"name": f"contested {round_}"}).json()["id"]
            assert upload(c, pid, [scene / "images" / "ground_00.png"]).status_code == 201
            start = threading.Barrier(len(clients))
            statuses: list[int] = []

            def delete(client: httpx.Client, pid: str, start: threading.Barrier, out: list[int]) -> None:
                start.wait()
                out.append(client.delete(f"/v1/projects/{pid}").status_code)

            threads = [threading.Thread(target=delete, args=(x, pid, start, statuses)) for x in clients]
            for t in threads:
                t.start()
            for t in threads:
                t.join(120)
            assert sorted(statuses) == [204] + [404] * 9, (round_, statuses)
            assert c.get(f"/v1/projects/{pid}").status_code == 404
            assert not (d.home / "projects" / pid).exists()
    finally:
        for x in clients:
            x.close()


# -- JSON types ------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("body", "message"),
    [
        ({"resize": "640"}, "resize: Input should be a valid integer"),
        ({"resize": 640.5}, "resize: Input should be a valid integer"),
        ({"resize": True}, "resize: Input should be a valid integer"),
        ({"snap_radius": "1"}, "snap_radius: Input should be a valid number"),
        ({"snap_radius": True}, "snap_radius: Input should be a valid number"),
        ({"reconstruct": "yes"}, "reconstruct: Input should be a valid boolean"),
        ({"reconstruct": 1}, "reconstruct: Input should be a valid boolean"),
        ({"method": 1}, "method: Input should be a valid string"),
        ({"pairs": 3}, "pairs"),
    ],
)
def test_loosely_typed_match_request_is_422(
    server: tuple[Deployment, httpx.Client], scene: Path, body: dict[str, object], message: str
) -> None:
    """The project has two images: a value coerced into shape would start a real job."""
    d, c = server
    pid = two_images(c, scene, "types")
    r = c.post(f"/v1/projects/{pid}/match", json=body)
    assert r.status_code == 422 and message in r.json()["detail"], r.text
    if "DATABASE_URL" not in d.env:  # SQLite under GEOMATCH_HOME: no job row either
        assert d.metadata("SELECT count(*) FROM jobs WHERE project_id = ?", pid) == [(0,)]


@pytest.mark.parametrize(
    "config",
    [{"snap_radius": True}, {"snap_radius": "1.5"}, {"resize": "320"}, {"resize": 320.5}, {"camera": 0}],
)
def test_loosely_typed_project_config_is_422(server: tuple[Deployment, httpx.Client], config: dict) -> None:
    _, c = server
    before = c.get("/v1/projects").json()
    r = c.post("/v1/projects", json={"name": "typed", "config": config})
    assert r.status_code == 422 and f"config.{next(iter(config))}" in r.json()["detail"], r.text
    assert c.get("/v1/projects").json() == before
    assert c.post("/v1/projects", json={"name": 5}).status_code == 422


def test_numbers_as_json_schema_defines_them(server: tuple[Deployment, httpx.Client]) -> None:
    """What the schema says: a JSON integer is a number, and a number with no fraction an integer."""
    _, c = server
    config = {"snap_radius": 1, "resize": 320.0}
    r = c.post("/v1/projects", json={"name": "int radius", "config": config})
    assert r.status_code == 201 and r.json()["config"] == {"snap_radius": 1.0, "resize": 320}, r.text
    assert isinstance(r.json()["config"]["resize"], int)


# -- found by tests/service/test_fuzz_rest.py --------------------------------------------------------
def test_method_not_allowed_names_every_method_of_the_path(server: tuple[Deployment, httpx.Client]) -> None:
    _, c = server
    for method, path, allow in [
        ("OPTIONS", "/v1/jobs/0123", "DELETE, GET"),
        ("PUT", "/v1/projects", "GET, POST"),
        ("PATCH", "/v1/projects/0123", "DELETE, GET"),
        ("DELETE", "/v1/projects/0123/images", "GET, POST"),
    ]:
        r = c.request(method, path)
        assert r.status_code == 405 and r.headers["allow"] == allow, (method, path, r.headers)


def test_schema_says_what_the_server_takes(server: tuple[Deployment, httpx.Client]) -> None:
    _, c = server
    schema = c.get("/openapi.json").json()
    metrics = schema["paths"]["/metrics"]["get"]["responses"]["200"]["content"]
    assert list(metrics) == ["text/plain"] and c.get("/metrics").headers["content-type"].startswith(
        "text/plain"
    )
    assert "503" in schema["paths"]["/readyz"]["get"]["responses"]
    fmt = next(
        p
        for p in schema["paths"]["/v1/projects/{project_id}/model"]["get"]["parameters"]
        if p["name"] == "format"
    )
    assert fmt["schema"]["enum"] == [
        # the files the run writes (the map's among them) come first, then those built on request
        "zip",
        "ply",
        "orthophoto",
        "dsm",
        "map-preview",
        "json",
        "scene",
        "nerfstudio",
        "colmap-text",
        "hloc",
        "openmvs",
        "odm",
        "laz",
    ]
    r = c.get("/v1/projects/0123/model", params={"format": "tar"})
    assert r.status_code == 422 and "format" in r.json()["detail"], r.text


# -- timestamps ------------------------------------------------------------------------------------
def stamp(value: str) -> datetime:
    assert UTC_STAMP.fullmatch(value), value
    t = datetime.fromisoformat(value)
    assert t.utcoffset() == timedelta(0) and abs(datetime.now(UTC) - t) < timedelta(minutes=10), value
    return t


def test_timestamps_are_utc_in_one_form(server: tuple[Deployment, httpx.Client], scene: Path) -> None:
    d, c = server
    created = c.post("/v1/projects", json={"name": "clock"}).json()
    stamp(created["created_at"])
    assert c.get(f"/v1/projects/{created['id']}").json()["created_at"] == created["created_at"]
    listed = {p["id"]: p["created_at"] for p in c.get("/v1/projects").json()}
    assert listed[created["id"]] == created["created_at"]
    if d.redis_url is None:  # the embedded runner would load the networks: the stores are the same
        return
    pid = two_images(c, scene, "clock jobs")
    body = {"pairs": [["ground_00.png", "ground_01.png"]], "method": "sparse", "resize": 64}
    job_id = c.post(f"/v1/projects/{pid}/match", json=body).json()["job_id"]
    job = c.get(f"/v1/jobs/{job_id}").json()
    stamp(job["created_at"])
    if d.workers:  # it runs: started and finished
        job = wait_job(c, job_id, timeout=300)
        assert job["state"] == "succeeded", job
        assert stamp(job["created_at"]) <= stamp(job["started_at"]) <= stamp(job["finished_at"])
    else:  # queued for ever: cancelled, it finishes
        job = c.delete(f"/v1/jobs/{job_id}").json()
        assert job["state"] == "cancelled" and job["started_at"] is None
        stamp(job["finished_at"])
    again = c.get(f"/v1/jobs/{job_id}").json()
    for k in ("created_at", "started_at", "finished_at"):
        assert again[k] == job[k], (k, again[k], job[k])


# -- memory ----------------------------------------------------------------------------------------
def png_of_zeros(width: int, height: int) -> bytes:
    """A valid black RGB PNG, compressed row by row: its bitmap is never made here either."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    comp = zlib.compressobj(9)
    row = b"\0" * (1 + 3 * width)
    idat = b"".join(comp.compress(row) for _ in range(height)) + comp.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def memory_kib(pid: int) -> dict[str, int]:
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        k, _, v = line.partition(":")
        if k in ("VmRSS", "VmHWM"):
            fields[k] = int(v.split()[0])
    return fields


def test_validating_a_large_upload_does_not_decode_its_bitmap(deployment: Deployment, key_a: str) -> None:
    """4 uploads at once of a 9400x9400 PNG (under the pixel limit, 88 Mpx: 337 MiB as a bitmap)
    raise the API process's peak resident memory by a few MiB, not by 4 bitmaps."""
    data = png_of_zeros(9400, 9400)
    assert len(data) < 2 * MiB  # the deployment's upload limit
    assert deployment.server is not None
    pid = deployment.server.pid
    c = deployment.client(key_a)
    projects = [c.post("/v1/projects", json={"name": f"big {i}"}).json()["id"] for i in range(4)]
    Path(f"/proc/{pid}/clear_refs").write_text("5")  # VmHWM := VmRSS
    base = memory_kib(pid)["VmRSS"]
    answers: list[httpx.Response] = []

    def send(project: str) -> None:
        with deployment.client(key_a) as x:
            answers.append(x.post(f"/v1/projects/{project}/images", files=[("files", ("big.png", data))]))

    threads = [threading.Thread(target=send, args=(p,)) for p in projects]
    for t in threads:
        t.start()
    for t in threads:
        t.join(300)
    assert [a.status_code for a in answers] == [201] * 4, [a.text for a in answers]
    assert {(a.json()["images"][0]["width"], a.json()["images"][0]["height"]) for a in answers} == {
        (9400, 9400)
    }
    peak = memory_kib(pid)["VmHWM"]
    grew_mib = (peak - base) / 1024
    print(f"API peak resident memory over 4 concurrent 9400x9400 uploads: +{grew_mib:.1f} MiB")
    assert grew_mib < 64, f"validating 4 uploads raised the API's peak memory by {grew_mib:.0f} MiB"
