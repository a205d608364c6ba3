"""Localizing new photos against a project's model, on real processes: one embedded `geomatch serve`
(uvicorn, the gRPC server and the in-process job runner over one service) whose project holds a
model of four ground views of a synthetic scene (GPS-tagged, so georeferenced); a fifth
ground view, left out of the model, is localized over REST, over gRPC and from the web console in
Chromium. A photo of no scene (noise) must come back "not localized". The errors: a project
without a model, bad uploads, another tenant's project; none of them leaves anything behind.
"""

from __future__ import annotations

import io
import json
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
import httpx
import numpy as np
import pytest
from PIL import Image

from geomatch.geo.geodesy import EnuFrame
from geomatch.synth.aerial import write_scene
from service.clients.grpc_client import ImageSource, to_dict
from service.grpcapi.pb import pb2

from .grpc_harness import GrpcDeployment, error_of
from .harness import upload, wait_job
from .test_embedded import printed_key

# a walk of five ground views 30 degrees apart (GPS-tagged): the model is the first four, matched
# with the sparse matcher at 480 px (ground pairs only: no tiled aerial pair, which costs minutes on
# two cores), and the last, which overlaps the two before it, is left out to be localized
SCENE_SEED = 1
MODEL = ["ground_00.png", "ground_01.png", "ground_02.png", "ground_03.png"]
LEFT_OUT = "ground_04.png"
CONFIG = {"method": "sparse", "resize": 480}
# a request answers synchronously within this: long enough for a shared CI machine, so the
# synchronous path is what the tests see unless they ask for a job (wait=0)
WAIT_S = 600
# how far (metres) a localized camera may be from where the scene put it: the model is georeferenced
# on four 0.5 m GPS fixes (test_e2e's own cameras are within 2 m of the truth with six)
NEAR_M = 3.0


@dataclass
class Site:
    d: GrpcDeployment
    key: str
    pid: str  # the project with a model
    bare: str  # a project with images and no model
    scene: Path

    def client(self) -> httpx.Client:
        return self.d.client(self.key)

    def photo(self, name: str = LEFT_OUT) -> Path:
        return self.scene / "images" / name


@pytest.fixture(scope="module")
def walk(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("walk")
    write_scene(d, 0, len(MODEL) + 1, seed=SCENE_SEED, gps_noise=0.5)
    return d


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory, walk: Path) -> Iterator[Site]:
    d = GrpcDeployment(
        tmp_path_factory.mktemp("localize"),
        None,
        GEOMATCH_LOCALIZE_WAIT_S=str(WAIT_S),
        GEOMATCH_MAX_UPLOAD_MB="1",
    )
    try:
        d.start_grpc("serve")
        key = printed_key(d)
        with d.client(key) as c:
            pid = c.post("/v1/projects", json={"name": "site", "config": CONFIG}).json()["id"]
            model = build_model(c, pid, walk)
            assert model["registered"] == len(MODEL) and model["georeferenced"], model
            bare = c.post("/v1/projects", json={"name": "no model"}).json()["id"]
            assert upload(c, bare, [walk / "images" / n for n in MODEL[:2]], "ground").status_code == 201
        yield Site(d, key, pid, bare, walk)
    finally:
        d.stop()


def build_model(c: httpx.Client, pid: str, scene: Path) -> dict[str, Any]:
    """Upload the model's images, match and reconstruct; the model's summary."""
    assert upload(c, pid, [scene / "images" / n for n in MODEL], "ground").status_code == 201
    accepted = c.post(f"/v1/projects/{pid}/match", json={"reconstruct": True, "mapper": "incremental"})
    recon = wait_job(c, accepted.json()["reconstruct_job_id"], timeout=1800)
    assert recon["state"] == "succeeded", recon
    return recon["result"]  # type: ignore[no-any-return]


def truth_lat_lon(scene: Path, name: str) -> tuple[float, float, float]:
    truth = json.loads((scene / "gt" / "gps.json").read_text())
    lat, lon, alt = EnuFrame(**truth["origin"]).to_geodetic(np.array(truth["true_enu"][name]))
    return float(lat), float(lon), float(alt)


def metres_between(a: tuple[float, float], b: tuple[float, float]) -> float:
    frame = EnuFrame(a[0], a[1], 0.0)
    return float(np.linalg.norm(frame.from_geodetic(b[0], b[1], 0.0)[:2]))


def noise_jpeg(seed: int = 7, size: tuple[int, int] = (640, 480)) -> bytes:
    """A photo of no scene at all."""
    pixels = np.random.default_rng(seed).integers(0, 256, (size[1], size[0], 3), dtype=np.uint8)
    out = io.BytesIO()
    Image.fromarray(pixels).save(out, "JPEG", quality=90)
    return out.getvalue()


def localize(c: httpx.Client, pid: str, files: list[tuple[str, bytes]], **form: Any) -> httpx.Response:
    parts = [("files", (name, data, "application/octet-stream")) for name, data in files]
    return c.post(f"/v1/projects/{pid}/localize", files=parts, data={k: str(v) for k, v in form.items()})


def left_behind(site: Site, pid: str) -> list[str]:
    """A localize job's own photos (its folder inside the project): none once it ended."""
    return sorted(p.name for p in (site.d.home / "projects" / pid / "localize").glob("*/*"))


def assert_placed(site: Site, answer: dict[str, Any], name: str = LEFT_OUT) -> None:
    """Localized, confidently enough, and on the map where the scene put the camera."""
    assert answer["name"] == name and answer["localized"], answer
    assert answer["confidence"] in ("high", "low") and answer["inliers"] >= 40, answer
    assert set(answer["supporting_images"]) <= set(MODEL) and answer["supporting_images"], answer
    assert len(answer["cam_from_world"]["qvec"]) == 4 and len(answer["center"]) == 3, answer
    assert answer["camera"]["width"] == 640 and answer["camera"]["height"] == 480, answer
    lat, lon, _ = truth_lat_lon(site.scene, name)
    off = metres_between((lat, lon), (answer["wgs84"]["lat"], answer["wgs84"]["lon"]))
    assert off < NEAR_M, (off, answer)


@pytest.mark.service
def test_rest_answers_with_the_pose_of_a_photo_left_out_of_the_model(site: Site) -> None:
    t0 = time.monotonic()
    with site.client() as c:
        r = localize(c, site.pid, [(LEFT_OUT, site.photo().read_bytes())])
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["state"] == "succeeded" and body["progress"] == {"done": 1, "total": 1}, body
        [answer] = body["localizations"]
        assert_placed(site, answer)
        # the job routes read the same job: kind localize, the answers as its result
        job = c.get(f"/v1/jobs/{body['job_id']}").json()
        assert job["kind"] == "localize" and job["result"]["localizations"][0]["name"] == LEFT_OUT
        assert job["options"]["add"] is False and job["options"]["method"] == "sparse"  # the project's
        # not added: the project is as it was, and the photo is gone from the server
        names = [i["name"] for i in c.get(f"/v1/projects/{site.pid}/images").json()["images"]]
        assert names == MODEL
        assert left_behind(site, site.pid) == []
    print(f"localize over REST: {time.monotonic() - t0:.1f}s for one photo")


@pytest.mark.service
def test_rest_answers_with_a_job_when_the_wait_is_over(site: Site) -> None:
    """wait=0: 202 at once, with the job that GET /v1/jobs/{id} follows to the same answers; a
    photo of no scene is answered not localized, with a reason and no pose."""
    with site.client() as c:
        files = [(LEFT_OUT, site.photo().read_bytes()), ("noise.jpg", noise_jpeg())]
        r = localize(c, site.pid, files, wait=0)
        assert r.status_code == 202, r.text
        body = r.json()
        assert body["state"] in ("queued", "running") and body["localizations"] is None, body
        assert r.headers["location"] == f"/v1/jobs/{body['job_id']}"
        job = wait_job(c, body["job_id"], timeout=900)
        assert job["state"] == "succeeded" and job["progress"] == {"done": 2, "total": 2}, job
        placed, noise = job["result"]["localizations"]
        assert_placed(site, placed)
        assert noise["name"] == "noise.jpg" and not noise["localized"], noise
        assert noise["confidence"] == "none" and noise["reason"], noise
        assert noise["cam_from_world"] is None and noise["wgs84"] is None, noise
        assert left_behind(site, site.pid) == []


@pytest.mark.service
def test_grpc_localize(site: Site) -> None:
    with site.d.grpc_client(site.key) as g:
        reply = g.localize(site.pid, [ImageSource.of(site.photo(), "ground")])
        assert reply.job.kind == pb2.JOB_KIND_LOCALIZE and reply.job.state == pb2.JOB_STATE_SUCCEEDED
        [answer] = reply.localizations
        assert answer.name == LEFT_OUT and answer.localized and answer.confidence in ("high", "low")
        assert len(answer.cam_from_world.qvec) == 4 and answer.HasField("wgs84")
        # what the REST answer says of how it was found, the gRPC one says too
        assert set(answer.supporting_images) <= set(answer.candidates) and answer.candidates
        assert 0.25 <= answer.inlier_ratio <= 1 and answer.focal_source in ("model", "exif", "estimated")
        lat, lon, _ = truth_lat_lon(site.scene, LEFT_OUT)
        assert metres_between((lat, lon), (answer.wgs84.lat, answer.wgs84.lon)) < NEAR_M
        # wait_s 0: the job at once, its answers in its result once it succeeded
        reply = g.localize(site.pid, [ImageSource(name="noise.jpg", data=noise_jpeg(8))], wait_s=0)
        assert reply.job.state in (pb2.JOB_STATE_QUEUED, pb2.JOB_STATE_RUNNING) and not reply.localizations
        job = g.wait(reply.job.id)
        assert job.state == pb2.JOB_STATE_SUCCEEDED, job
        [noise] = to_dict(job.result)["localizations"]
        assert noise["name"] == "noise.jpg" and noise["localized"] is False and noise["reason"]
    assert left_behind(site, site.pid) == []


@pytest.mark.service
def test_add_puts_the_photo_and_its_matches_into_the_project(site: Site, tmp_path: Path) -> None:
    """add=true: the photo is one of the project's images, and its matches with the model images
    it was matched with are in the COLMAP database, so a later reconstruct maps it."""
    import pycolmap

    with site.client() as c:
        pid = c.post("/v1/projects", json={"name": "add", "config": CONFIG}).json()["id"]
        # the same model as the site's: its features are in the server's cache already
        build_model(c, pid, site.scene)
        r = localize(c, pid, [(LEFT_OUT, site.photo().read_bytes())], add="true", capture="ground")
        assert r.status_code == 200, r.text
        assert_placed(site, r.json()["localizations"][0])
        images = {i["name"]: i for i in c.get(f"/v1/projects/{pid}/images").json()["images"]}
        assert sorted(images) == sorted([*MODEL, LEFT_OUT]) and images[LEFT_OUT]["capture"] == "ground"
        (tmp_path / "db.db").write_bytes(c.get(f"/v1/projects/{pid}/database").content)
        db = pycolmap.Database.open(str(tmp_path / "db.db"))
        try:
            photo = db.read_image_with_name(LEFT_OUT)
            assert photo is not None and db.num_keypoints_for_image(photo.image_id) > 0
            others = [db.read_image_with_name(n).image_id for n in MODEL]
            assert any(db.exists_matches(photo.image_id, o) for o in others)
        finally:
            db.close()
        assert left_behind(site, pid) == []


@pytest.mark.service
def test_localize_refusals_leave_nothing_behind(site: Site) -> None:
    """No model: 409 / FAILED_PRECONDITION saying so; not an image, a GIF, a file over the limit:
    400 / 415 / 413 (INVALID_ARGUMENT over gRPC); another tenant's project: 404 / NOT_FOUND. None
    of them creates a job or leaves a file."""
    gif = io.BytesIO()
    Image.new("RGB", (32, 32)).save(gif, "GIF")
    jobs_before = site.d.metadata("SELECT count(*) FROM jobs")[0][0]
    other = site.d.create_key("someone else")
    photo = site.photo().read_bytes()
    with site.client() as c, site.d.client(other) as stranger:
        r = localize(c, site.bare, [(LEFT_OUT, photo)])
        assert r.status_code == 409 and "has no model yet" in r.json()["detail"], r.text
        cases = {
            "broken.jpg": (b"not an image at all", 400, "not a readable image"),
            "anim.gif": (gif.getvalue(), 415, "GIF images are not accepted"),
            "big.jpg": (b"\xff" * (1024 * 1024 + 10), 413, "larger than the upload limit"),
        }
        for name, (data, status, words) in cases.items():
            # with a good photo before it: all of a request's photos pass, or none is kept
            r = localize(c, site.pid, [(LEFT_OUT, photo), (name, data)])
            assert r.status_code == status and words in r.json()["detail"], (name, r.status_code, r.text)
        r = localize(c, site.pid, [(LEFT_OUT, photo), (LEFT_OUT, photo)])
        assert r.status_code == 400 and "sent twice" in r.json()["detail"], r.text
        assert localize(c, site.pid, [(LEFT_OUT, photo)], wait=-1).status_code == 422
        r = localize(stranger, site.pid, [(LEFT_OUT, photo)])
        assert r.status_code == 404, r.text
        assert localize(c, "0" * 32, [(LEFT_OUT, photo)]).status_code == 404
    with site.d.grpc_client(site.key) as g, site.d.grpc_client(other) as h:
        good = ImageSource(name=LEFT_OUT, data=photo)
        code, details = error_of(lambda: g.localize(site.bare, [good]))
        assert code == grpc.StatusCode.FAILED_PRECONDITION and "has no model yet" in details
        bad = ImageSource(name="broken.jpg", data=b"not an image at all")
        code, details = error_of(lambda: g.localize(site.pid, [good, bad]))
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "not a readable image" in details
        code, _ = error_of(lambda: h.localize(site.pid, [good]))
        assert code == grpc.StatusCode.NOT_FOUND
        code, _ = error_of(lambda: g.localize(site.pid, []))
        assert code == grpc.StatusCode.INVALID_ARGUMENT
    assert site.d.metadata("SELECT count(*) FROM jobs")[0][0] == jobs_before
    assert left_behind(site, site.pid) == [] and left_behind(site, site.bare) == []
    assert not list((site.d.home / "projects" / site.pid / "localize").glob("*"))
    assert site.d.wait_unstaged() == []


@pytest.mark.browser
def test_console_locates_a_photo(site: Site, tmp_path: Path) -> None:
    """Through the page: the project's "Locate a photo" action takes the photo left out and a
    photo of no scene; the first is drawn as a camera in the viewer beside the model's and written
    out with its latitude and longitude, the second is listed as not localized with its reason."""
    from .browser import chromium_path, require_playwright
    from .test_console import Console, page_of, sign_in, wait_until

    require_playwright()
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium_path(), args=["--no-sandbox"])
        try:
            with page_of(Console(site.d, site.key, browser)) as page:
                sign_in(page, Console(site.d, site.key, browser))
                page.goto(f"{site.d.url}/#/projects/{site.pid}")
                page.wait_for_selector("#locate-card:not([hidden])")
                wait_until(page, f"window.geomatchViewer && window.geomatchViewer.cameras === {len(MODEL)}")
                assert page.get_attribute("#viewer", "data-located") == "0"
                page.set_input_files(
                    "#locate-input",
                    [
                        {"name": LEFT_OUT, "mimeType": "image/png", "buffer": site.photo().read_bytes()},
                        {"name": "noise.jpg", "mimeType": "image/jpeg", "buffer": noise_jpeg(9)},
                    ],
                )
                wait_until(
                    page,
                    "['done', 'error'].includes(document.getElementById('locate-status').dataset.state)",
                    timeout=15 * 60 * 1000,
                )
                assert page.get_attribute("#locate-status", "data-state") == "done", page.text_content(
                    "#locate-status"
                )
                assert page.text_content("#locate-status") == "1 of 2 located"
                placed = page.locator(f"#locate-results li[data-name='{LEFT_OUT}']")
                assert placed.get_attribute("data-state") == "localized"
                lat = float(placed.locator(".wgs84").get_attribute("data-lat") or "nan")
                lon = float(placed.locator(".wgs84").get_attribute("data-lon") or "nan")
                truth = truth_lat_lon(site.scene, LEFT_OUT)
                assert metres_between(truth[:2], (lat, lon)) < NEAR_M
                assert "lat " in placed.locator(".wgs84").text_content()
                noise = page.locator("#locate-results li[data-name='noise.jpg']")
                assert noise.get_attribute("data-state") == "not-localized"
                assert noise.locator(".verdict").text_content() == "not localized"
                assert noise.locator(".reason").text_content()
                # the located camera is drawn, in its own colour, beside the model's
                wait_until(page, "window.geomatchViewer.located === 1")
                assert page.evaluate("window.geomatchViewer.cameras") == len(MODEL)
                page.locator("#locate-card").scroll_into_view_if_needed()
                page.screenshot(path=tmp_path / "located.png", full_page=True)
        finally:
            browser.close()
    with site.client() as c:  # nothing was added to the project
        assert [i["name"] for i in c.get(f"/v1/projects/{site.pid}/images").json()["images"]] == MODEL
