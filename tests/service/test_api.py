"""The REST contract against a running server: auth and tenants, every kind of bad input
(a clear 4xx, nothing stored), idempotent uploads, health, metrics, OpenAPI."""

from __future__ import annotations

import io
import struct
import subprocess
import zlib
from pathlib import Path

import httpx
import pytest
from PIL import Image

from .harness import GEOMATCH, Deployment, sse_events, upload, wait_job

pytestmark = pytest.mark.service


def png_header_bomb(width: int = 50_000, height: int = 50_000) -> bytes:
    """A PNG whose header claims 2.5 gigapixels over a few kilobytes of data."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    comp = zlib.compressobj(9)
    row = b"\0" * (1 + 3 * width)
    idat = b"".join(comp.compress(row) for _ in range(20)) + comp.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def bmp_header(width: int, height: int, bits: int, compression: int = 0, data_size: int = 0) -> bytes:
    """A BITMAPFILEHEADER + BITMAPINFOHEADER (with a grey palette below 16 bits a pixel)."""
    colours = 1 << bits if bits <= 8 else 0
    offset = 14 + 40 + 4 * colours
    row = (width * bits + 31) // 32 * 4
    total = offset + (data_size or row * height)
    dpm = 2835  # 72 dpi in pixels a metre
    fields = (40, width, height, 1, bits, compression, data_size, dpm, dpm, colours, 0)
    info = struct.pack("<IiiHHIIiiII", *fields)
    palette = b"".join(bytes((i, i, i, 0)) for i in range(colours))
    return b"BM" + struct.pack("<IHHI", total, 0, 0, offset) + info + palette


def big_bmp_cut_short() -> bytes:
    """The header of a 4000x3000 24-bit BMP and 1000 bytes in all: its bitmap (48 MB to Pillow)
    is past the decode budget, so only the promised size can find it short."""
    head = bmp_header(4000, 3000, 24)
    return head + b"\0" * (1000 - len(head))


def gif_bytes() -> bytes:
    buf = io.BytesIO()
    Image.new("RGB", (64, 64), (200, 10, 10)).save(buf, format="GIF")
    return buf.getvalue()


@pytest.fixture(scope="module")
def a(deployment: Deployment, key_a: str) -> httpx.Client:
    return deployment.client(key_a)


@pytest.fixture(scope="module")
def project(a: httpx.Client, scene: Path) -> str:
    pid = a.post("/v1/projects", json={"name": "api"}).json()["id"]
    r = upload(a, pid, [scene / "images" / "ground_00.png"], "ground")
    assert r.status_code == 201, r.text
    return str(pid)


def state(deployment: Deployment, pid: str) -> tuple[list[str], int, list[str]]:
    """What a rejected request must not change: the project's images (rows and files), its
    jobs, and the upload staging folder."""
    rows = sorted(n for (n,) in deployment.metadata("SELECT name FROM images WHERE project_id = ?", pid))
    jobs = deployment.metadata("SELECT count(*) FROM jobs WHERE project_id = ?", pid)[0][0]
    files = sorted(p.name for p in (deployment.home / "projects" / pid / "images").glob("*"))
    staged = sorted(p.name for p in (deployment.home / "tmp").glob("upload-*"))
    assert rows == files, (rows, files)
    return rows, jobs, staged


# -- auth and tenants ----------------------------------------------------------------------------
def test_requests_without_a_valid_key_are_401(deployment: Deployment) -> None:
    for key in (None, "gm_not-a-key"):
        r = deployment.client(key).get("/v1/projects")
        assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
        assert "key" in r.json()["detail"]


def test_revoked_key_is_refused(deployment: Deployment) -> None:
    key = deployment.create_key("short-lived")
    assert deployment.client(key).get("/v1/projects").status_code == 200
    r = subprocess.run(
        [*GEOMATCH, "keys", "revoke", key[:10]], env=deployment.env, capture_output=True, text=True
    )
    assert r.returncode == 0, r.stderr
    assert deployment.client(key).get("/v1/projects").status_code == 401


def test_another_tenants_project_and_jobs_are_404(
    deployment: Deployment, a: httpx.Client, key_b: str, project: str, scene: Path
) -> None:
    b = deployment.client(key_b)
    upload(a, project, [scene / "images" / "ground_01.png"], "ground")
    job_id = a.post(f"/v1/projects/{project}/match", json={"resize": 320, "method": "sparse"}).json()[
        "job_id"
    ]
    before = state(deployment, project)
    assert project not in [p["id"] for p in b.get("/v1/projects").json()]
    assert project in [p["id"] for p in a.get("/v1/projects").json()]
    for method, path in [
        ("GET", f"/v1/projects/{project}"),
        ("DELETE", f"/v1/projects/{project}"),
        ("GET", f"/v1/projects/{project}/images"),
        ("POST", f"/v1/projects/{project}/reconstruct"),
        ("GET", f"/v1/projects/{project}/model"),
        ("GET", f"/v1/projects/{project}/report"),
        ("GET", f"/v1/projects/{project}/database"),
        ("GET", f"/v1/projects/{project}/pairs/ground_00.png/ground_01.png/matches.png"),
        ("GET", f"/v1/jobs/{job_id}"),
        ("GET", f"/v1/jobs/{job_id}/events"),
        ("DELETE", f"/v1/jobs/{job_id}"),
    ]:
        r = b.request(method, path)
        assert r.status_code == 404, (method, path, r.status_code, r.text)
    assert b.post(f"/v1/projects/{project}/match", json={}).status_code == 404
    assert upload(b, project, [scene / "images" / "ground_02.png"]).status_code == 404
    assert state(deployment, project) == before
    assert wait_job(a, job_id)["state"] == "succeeded"  # B's cancel did not touch A's job
    events = list(sse_events(a, job_id))  # a finished job: its final state, then the stream ends
    assert [(e["state"], e["progress"]) for e in events] == [("succeeded", {"done": 1, "total": 1})]


# -- bad uploads ---------------------------------------------------------------------------------
def bad_files(scene: Path) -> list[tuple[str, str, bytes, int, str]]:
    png = (scene / "images" / "ground_02.png").read_bytes()
    return [
        ("not an image", "notes.png", b"this is not an image, just text\n" * 10, 400, "not a readable image"),
        ("truncated", "cut.png", png[: len(png) // 2], 400, "truncated"),
        ("truncated bmp", "cut.bmp", big_bmp_cut_short(), 400, "truncated file: 1000 bytes"),
        ("zero bytes", "empty.png", b"", 400, "empty file"),
        ("decompression bomb", "bomb.png", png_header_bomb(), 413, "exceeds the limit"),
        ("over the byte limit", "huge.png", png + b"\0" * (2 * 1024 * 1024), 413, "upload limit"),
        ("unsupported format", "anim.gif", gif_bytes(), 415, "GIF"),
        ("path separator", "../evil.png", png, 400, "path separator"),
        ("nested path", "sub/dir.png", png, 400, "path separator"),
        ("backslash", "..\\evil.png", png, 400, "path separator"),
        ("dot dot", "..", png, 400, ".."),
        ("dots inside", "a..png", png, 400, ".."),
    ]


BAD_FILES = [
    "not an image",
    "truncated",
    "truncated bmp",
    "zero bytes",
    "decompression bomb",
    "over the byte limit",
    "unsupported format",
    "path separator",
    "nested path",
    "backslash",
    "dot dot",
    "dots inside",
]


@pytest.mark.parametrize("label", BAD_FILES)
def test_bad_upload_is_refused_and_nothing_stored(
    deployment: Deployment, a: httpx.Client, project: str, scene: Path, label: str
) -> None:
    cases = {c[0]: c for c in bad_files(scene)}
    assert sorted(cases) == sorted(BAD_FILES)
    _, name, data, status, message = cases[label]
    before = state(deployment, project)
    good = (scene / "images" / "ground_03.png").read_bytes()
    # the bad file together with a good one: all or nothing
    r = a.post(
        f"/v1/projects/{project}/images",
        files=[("files", ("good.png", good, "image/png")), ("files", (name, data, "image/png"))],
    )
    assert r.status_code == status, (label, r.status_code, r.text)
    assert message in r.json()["detail"], (label, r.json())
    assert "upload-" not in r.json()["detail"], r.json()  # no server-side staging path leaks out
    assert state(deployment, project) == before, label


def test_upload_to_unknown_project_is_404(a: httpx.Client, scene: Path) -> None:
    r = upload(a, "0123456789abcdef0123456789abcdef", [scene / "images" / "ground_00.png"])
    assert r.status_code == 404 and "not found" in r.json()["detail"]


def test_upload_needs_files_and_a_known_capture(a: httpx.Client, project: str, scene: Path) -> None:
    assert a.post(f"/v1/projects/{project}/images", data={"capture": "ground"}).status_code == 422
    r = upload(a, project, [scene / "images" / "ground_00.png"], "satellite")
    assert r.status_code == 422 and "capture" in r.json()["detail"]


def test_reupload_is_idempotent_and_name_clash_is_409(
    deployment: Deployment, a: httpx.Client, project: str, scene: Path
) -> None:
    first = a.get(f"/v1/projects/{project}/images").json()["images"][0]
    r = a.post(
        f"/v1/projects/{project}/images",
        files=[("files", (first["name"], (scene / "images" / first["name"]).read_bytes(), "image/png"))],
    )
    assert r.status_code == 201
    again = r.json()["images"][0]
    assert again["id"] == first["id"] and again["sha256"] == first["sha256"] and again["created"] is False
    before = state(deployment, project)
    other = (scene / "images" / "aerial_00.png").read_bytes()
    r = a.post(f"/v1/projects/{project}/images", files=[("files", (first["name"], other, "image/png"))])
    assert r.status_code == 409 and "other content" in r.json()["detail"]
    assert state(deployment, project) == before


def test_reupload_restores_a_listed_image_whose_file_is_gone(
    deployment: Deployment, a: httpx.Client, scene: Path
) -> None:
    """A commit whose acknowledgement is lost with the database connection leaves a listed image
    whose request was answered 503; the client's retry of the same bytes must leave the file in
    place, or every job reading that image fails."""
    pid = a.post("/v1/projects", json={"name": "lost-file"}).json()["id"]
    src = scene / "images" / "ground_01.png"
    assert upload(a, pid, [src]).status_code == 201
    stored = deployment.home / "projects" / pid / "images" / src.name
    stored.unlink()
    r = upload(a, pid, [src])
    assert r.status_code == 201 and r.json()["images"][0]["created"] is False, r.text
    assert stored.read_bytes() == src.read_bytes()
    assert a.get(f"/v1/projects/{pid}/images/{src.name}").status_code == 200


# -- bad requests ----------------------------------------------------------------------------------
def test_unknown_project_and_job_are_404(a: httpx.Client) -> None:
    missing = "0123456789abcdef0123456789abcdef"
    for method, path in [
        ("GET", f"/v1/projects/{missing}"),
        ("DELETE", f"/v1/projects/{missing}"),
        ("GET", f"/v1/projects/{missing}/images"),
        ("POST", f"/v1/projects/{missing}/reconstruct"),
        ("GET", f"/v1/projects/{missing}/model"),
        ("GET", f"/v1/projects/{missing}/report"),
        ("GET", f"/v1/jobs/{missing}"),
        ("DELETE", f"/v1/jobs/{missing}"),
        ("GET", f"/v1/jobs/{missing}/events"),
        ("GET", "/v1/projects/not-an-id"),
    ]:
        r = a.request(method, path)
        assert r.status_code == 404, (method, path, r.text)
        assert "not found" in r.json()["detail"]
    assert a.post(f"/v1/projects/{missing}/match", json={}).status_code == 404


def test_malformed_json_is_400(deployment: Deployment, a: httpx.Client, project: str) -> None:
    before = state(deployment, project)
    n_projects = len(a.get("/v1/projects").json())
    headers = {"content-type": "application/json"}
    for path, body in [
        ("/v1/projects", b'{"name": "x",'),
        (f"/v1/projects/{project}/match", b"{pairs: exhaustive}"),
    ]:
        r = a.post(path, content=body, headers=headers)
        assert r.status_code == 400 and "malformed JSON" in r.json()["detail"], r.text
    assert len(a.get("/v1/projects").json()) == n_projects
    assert state(deployment, project) == before


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ({"pairs": [["ground_00.png", "nope.png"]]}, "not an image of this project"),
        ({"pairs": [["ground_00.png", "ground_00.png"]]}, "itself"),
        ({"pairs": [["ground_00.png"]]}, "two image names"),
        ({"pairs": "nearest:3"}, "bad pairs"),
        ({"pairs": "sequential:0"}, "bad pairs"),
        ({"method": "magic"}, "method must be one of"),
        ({"resize": 5}, "resize"),
        ({"tiling": "sometimes"}, "tiling"),
        ({"reconstruct": True, "mapper": "hierarchical"}, "mapper"),
        ({"reconstruct": True, "min_pose_inliers": 2}, "min_pose_inliers must be 0 (auto"),
        ({"colour": "blue"}, "colour"),
        (["exhaustive"], "body"),
    ],
)
def test_bad_match_request_is_422_and_starts_nothing(
    deployment: Deployment, a: httpx.Client, project: str, body: object, message: str
) -> None:
    before = state(deployment, project)
    r = a.post(f"/v1/projects/{project}/match", json=body)
    assert r.status_code == 422 and message in r.json()["detail"], r.text
    assert state(deployment, project) == before


def test_matching_needs_two_images(deployment: Deployment, a: httpx.Client, scene: Path) -> None:
    pid = a.post("/v1/projects", json={"name": "lonely"}).json()["id"]
    r = a.post(f"/v1/projects/{pid}/match", json={})
    assert r.status_code == 422 and "has 0 image(s)" in r.json()["detail"]
    upload(a, pid, [scene / "images" / "ground_00.png"])
    r = a.post(f"/v1/projects/{pid}/match", json={})
    assert r.status_code == 422 and "has 1 image(s); matching needs at least 2" in r.json()["detail"]
    assert state(deployment, pid)[1] == 0
    assert a.post(f"/v1/projects/{pid}/reconstruct", json={}).status_code == 409
    assert a.get(f"/v1/projects/{pid}/database").status_code == 404
    for fmt in ("zip", "nerfstudio", "colmap-text", "hloc", "openmvs"):  # the exports too
        r = a.get(f"/v1/projects/{pid}/model", params={"format": fmt})
        assert r.status_code == 404 and "no model yet" in r.json()["detail"], (fmt, r.text)
    assert not (deployment.home / "projects" / pid / "model").exists()  # a refusal builds nothing


def test_bad_project_requests(a: httpx.Client) -> None:
    assert a.post("/v1/projects", json={}).status_code == 422
    assert a.post("/v1/projects", json={"name": ""}).status_code == 422
    r = a.post("/v1/projects", json={"name": "x", "config": {"method": "nope"}})
    assert r.status_code == 422 and "method" in r.json()["detail"]
    r = a.post("/v1/projects", json={"name": "x", "config": {"pairs": "sequential:3", "resize": 320}})
    assert r.status_code == 201 and r.json()["config"] == {"pairs": "sequential:3", "resize": 320}


def test_delete_project_removes_rows_and_files(deployment: Deployment, a: httpx.Client, scene: Path) -> None:
    pid = a.post("/v1/projects", json={"name": "doomed"}).json()["id"]
    upload(a, pid, [scene / "images" / "ground_00.png"])
    assert (deployment.home / "projects" / pid / "images" / "ground_00.png").is_file()
    assert a.delete(f"/v1/projects/{pid}").status_code == 204
    assert a.get(f"/v1/projects/{pid}").status_code == 404
    assert not (deployment.home / "projects" / pid).exists()
    assert deployment.metadata("SELECT count(*) FROM images WHERE project_id = ?", pid) == [(0,)]


# -- health, metrics, docs ---------------------------------------------------------------------------
def test_health_metrics_and_docs(deployment: Deployment) -> None:
    c = deployment.client(None)
    assert c.get("/healthz").json() == {"status": "ok"}
    ready = c.get("/readyz").json()
    assert ready == {
        "ready": True,
        "checks": {"database": "ok", "queue": "ok", "storage": "ok", "mode": "redis", "workers": "ok"},
    }
    metrics = c.get("/metrics").text
    assert 'geomatch_http_requests_total{method="GET",route="/healthz",status="200"}' in metrics
    assert 'geomatch_jobs{kind="match",state="succeeded"}' in metrics
    assert "geomatch_http_request_duration_seconds_bucket" in metrics
    paths = c.get("/openapi.json").json()["paths"]
    for p in (
        "/v1/projects",
        "/v1/projects/{project_id}/images",
        "/v1/projects/{project_id}/match",
        "/v1/projects/{project_id}/reconstruct",
        "/v1/jobs/{job_id}/events",
        "/v1/projects/{project_id}/model",
        "/v1/projects/{project_id}/report",
        "/v1/projects/{project_id}/database",
        "/v1/projects/{project_id}/pairs/{name0}/{name1}/matches.png",
    ):
        assert p in paths, p
    assert c.get("/docs").status_code == 200
