"""The web console in a real browser (Debian's Chromium, driven by Playwright), against a real
embedded server (`geomatch serve`: uvicorn and the in-process job runner, no Redis).

A person's way from photos to a point cloud, through the page only: key, project, upload by the
file input behind the drop area, match with reconstruct, progress from the event stream, the
pairs' match picture, the model in the viewer. What the viewer drew is compared with the model
endpoint's numbers fetched directly over REST. Names chosen by clients must render as text.
Screenshots of each page land in the test's temporary folder; a failure prints the browser's
console log.
"""

from __future__ import annotations

import base64
import contextlib
import io
import time
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
import pytest
from PIL import Image

from .browser import chromium_path, require_playwright
from .harness import Deployment, database_pairs
from .test_embedded import printed_key

pytestmark = pytest.mark.browser

# the four ground views of the session's scene, sparse at 480 px: every one registers, as in
# tests/service/test_e2e.py's batch run (with one aerial and three ground views at 320 px ground_02
# did not, and the README's pictures showed 3 of 4 registered; the whole scene registers too, but
# its eight aerial x ground pairs are tiled, ten times the time on shared cores)
IMAGES = ["ground_00.png", "ground_01.png", "ground_02.png", "ground_03.png"]
RESIZE = 480
METHOD = "sparse"
XSS = "<img src=x onerror=alert(1)>"
JOB_TIMEOUT_MS = 20 * 60 * 1000  # generous: CI machines are shared
DESKTOP = {"width": 1280, "height": 800}
PHONE = {"width": 390, "height": 844}


@dataclass
class Console:
    d: Deployment
    key: str
    browser: Any


@pytest.fixture(scope="module")
def console(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Console]:
    require_playwright()
    executable = chromium_path()
    from playwright.sync_api import sync_playwright

    d = Deployment(tmp_path_factory.mktemp("console"), None, GEOMATCH_MAX_UPLOAD_MB="1")
    try:
        d.start_server()
        key = printed_key(d)
        with sync_playwright() as p:
            try:
                browser = p.chromium.launch(executable_path=executable, args=["--no-sandbox"])
            except Exception as e:
                pytest.fail(f"Chromium at {executable} does not start under Playwright: {e}")
            try:
                yield Console(d, key, browser)
            finally:
                browser.close()
    finally:
        d.stop()


@contextlib.contextmanager
def page_of(c: Console, viewport: dict[str, int] = DESKTOP) -> Iterator[Any]:
    """A fresh tab (its own sessionStorage) whose console messages, page errors and dialogs are
    recorded; on failure they are printed with the server's log."""
    context = c.browser.new_context(viewport=viewport)
    page = context.new_page()
    log: list[str] = []
    dialogs: list[str] = []
    page.on("console", lambda m: log.append(f"console.{m.type}: {m.text}"))
    page.on("pageerror", lambda e: log.append(f"pageerror: {e}"))

    def dialog(d: Any) -> None:
        dialogs.append(d.message)
        d.dismiss()

    page.on("dialog", dialog)
    page.set_default_timeout(60_000)
    try:
        yield page
    except BaseException:
        print("--- browser console log\n" + "\n".join(log or ["(empty)"]))
        print(c.d.logs())
        raise
    finally:
        context.close()
    assert not dialogs, f"a dialog opened: {dialogs} (injected script?)"
    assert not [m for m in log if m.startswith("pageerror")], log
    # the page needs nothing its policy forbids (the browser logs every refusal)
    assert not [m for m in log if "Content Security Policy" in m], log


def wait_until(page: Any, expression: str, timeout: float = 60_000) -> Any:
    """Poll a JavaScript expression until it is truthy. Not Playwright's wait_for_function: that
    evaluates its predicate with eval(), which the console's policy (no unsafe-eval) rightly
    forbids, and the tests run under the policy a user's browser enforces."""
    deadline = time.monotonic() + timeout / 1000
    while True:
        value = page.evaluate(expression)
        if value:
            return value
        if time.monotonic() > deadline:
            raise TimeoutError(f"still false after {timeout / 1000:.0f}s: {expression}")
        time.sleep(0.25)


def sign_in(page: Any, c: Console, shots: Path | None = None) -> None:
    response = page.goto(c.d.url + "/")
    assert response.status == 200
    page.wait_for_selector("#key-view:not([hidden])")
    if shots:
        page.screenshot(path=shots / "key.png")
    page.fill("#key-input", c.key)
    page.click("#key-form button[type=submit]")
    page.wait_for_selector("#projects-view:not([hidden])")
    assert c.key not in page.url
    assert page.evaluate("sessionStorage.getItem('geomatch.key')") == c.key


def create_project(page: Any, name: str) -> str:
    page.fill("#project-name", name)
    page.click("#create-form button[type=submit]")
    page.wait_for_selector("#project-view:not([hidden])")
    wait_until(page, "document.getElementById('project-title').textContent.length > 0")
    return str(page.evaluate("decodeURIComponent(location.hash.split('/')[2])"))


def jpeg(seed: int, size: tuple[int, int] = (64, 48)) -> bytes:
    rng = np.random.default_rng(seed)
    out = io.BytesIO()
    Image.fromarray(rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)).save(out, "JPEG")
    return out.getvalue()


def test_console_security_headers(console: Console) -> None:
    c = console.d.client(console.key)
    for path in ("/", "/console/app.js", "/console/style.css"):
        r = c.get(path)
        assert r.status_code == 200, path
        csp = r.headers["content-security-policy"]
        assert "script-src 'self'" in csp and "frame-ancestors 'none'" in csp and "unsafe-inline" not in csp
        assert r.headers["x-content-type-options"] == "nosniff"
    assert "<script" not in c.get("/").text.replace('<script type="module" src="/console/app.js">', "")
    # the API's own pages are untouched: /docs loads Swagger UI's scripts, which this policy forbids
    assert "content-security-policy" not in c.get("/docs").headers
    assert c.get("/healthz").json() == {"status": "ok"}


def test_names_render_as_text_and_upload_errors_show(console: Console, tmp_path: Path, scene: Path) -> None:
    with page_of(console) as page:
        sign_in(page, console)
        pid = create_project(page, XSS)
        assert page.text_content("#project-title") == XSS
        drop_file(page, f"{XSS}.jpg", jpeg(1))  # a real drop event on the drop area
        page.set_input_files(
            "#file-input",
            [
                {"name": "broken.jpg", "mimeType": "image/jpeg", "buffer": b"not an image at all"},
                {"name": "anim.gif", "mimeType": "image/gif", "buffer": gif()},
                {"name": "big.jpg", "mimeType": "image/jpeg", "buffer": b"\xff" * (1024 * 1024 + 10)},
            ],
        )
        wait_until(
            page,
            "[...document.querySelectorAll('#upload-list li')].every("
            "li => li.dataset.state === 'done' || li.dataset.state === 'error') "
            "&& document.querySelectorAll('#upload-list li').length === 4",
        )
        status = {
            li["name"]: li
            for li in page.eval_on_selector_all(
                "#upload-list li",
                "els => els.map(li => ({name: li.dataset.name, state: li.dataset.state, "
                "status: li.querySelector('.status').textContent}))",
            )
        }
        assert status[f"{XSS}.jpg"]["state"] == "done", status
        assert status["broken.jpg"]["state"] == "error"
        assert status["broken.jpg"]["status"].startswith("400 broken.jpg: not a readable image"), status
        assert status["anim.gif"]["status"].startswith("415 anim.gif: GIF images are not accepted"), status
        assert status["big.jpg"]["status"].startswith("413 big.jpg: larger than the upload limit"), status

        page.wait_for_selector("#thumbs li.thumb")
        names = page.eval_on_selector_all("#thumbs .thumb .name", "els => els.map(e => e.textContent)")
        assert names == [f"{XSS}.jpg"]
        # the thumbnail itself loaded (fetched with the key, shown from a blob: URL)
        wait_until(page, "document.querySelector('#thumbs img')?.naturalWidth === 64")
        # nothing was injected: the only <img> elements are the console's own
        assert (
            page.eval_on_selector_all("img", "els => els.filter(e => e.getAttribute('src') === 'x').length")
            == 0
        )
        assert XSS in page.inner_text("#project-view")
        page.screenshot(path=tmp_path / "xss-project.png", full_page=True)

        # the API's refusal shows as sent: one image cannot be matched
        page.click("#start-match")
        wait_until(page, "!document.getElementById('notice').hidden")
        assert page.text_content("#notice") == "the project has 1 image(s); matching needs at least 2"

        # the project list shows the name as text too
        page.goto(console.d.url + "/#/")
        page.wait_for_selector(f"#project-rows a[href='#/projects/{pid}']")
        assert page.text_content(f"#project-rows a[href='#/projects/{pid}']") == XSS


def drop_file(page: Any, name: str, data: bytes) -> None:
    """Drop one file on the drop area as a person's drag would: a DataTransfer holding a File."""
    transfer = page.evaluate_handle(
        """([name, b64]) => {
            const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
            const dt = new DataTransfer();
            dt.items.add(new File([bytes], name, { type: "image/jpeg" }));
            return dt;
        }""",
        [name, base64.b64encode(data).decode()],
    )
    page.dispatch_event("#drop", "dragenter", {"dataTransfer": transfer})
    page.dispatch_event("#drop", "drop", {"dataTransfer": transfer})


def gif() -> bytes:
    out = io.BytesIO()
    Image.new("RGB", (32, 32), (200, 30, 30)).save(out, "GIF")
    return out.getvalue()


def test_photos_to_point_cloud(console: Console, scene: Path, tmp_path: Path) -> None:
    t0 = time.monotonic()
    with page_of(console) as page:
        sign_in(page, console, tmp_path)
        page.screenshot(path=tmp_path / "projects.png")
        pid = create_project(page, "console e2e")
        page.select_option("#capture", "auto")  # EXIF/XMP decide: no DJI XMP, so ground
        page.set_input_files("#file-input", [str(scene / "images" / n) for n in IMAGES])
        wait_until(
            page, f"document.querySelectorAll('#upload-list li[data-state=done]').length === {len(IMAGES)}"
        )
        wait_until(page, f"document.querySelectorAll('#thumbs li.thumb').length === {len(IMAGES)}")
        page.screenshot(path=tmp_path / "uploaded.png", full_page=True)

        page.fill("#resize", str(RESIZE))
        page.select_option("#method", METHOD)
        page.select_option("#mapper", "incremental")
        assert page.is_checked("#with-reconstruct")
        page.click("#start-match")
        page.wait_for_selector("#job:not([hidden])")
        page.wait_for_selector("#job[data-kind=match]")
        page.screenshot(path=tmp_path / "matching.png", full_page=True)
        # a reload picks the jobs up again (the server lists them) and follows them to the end
        page.reload()
        page.wait_for_selector("#project-view:not([hidden])")
        page.wait_for_selector("#job:not([hidden])")
        wait_until(
            page,
            "['failed', 'cancelled'].includes(document.getElementById('job').dataset.state) || "
            "(document.getElementById('job').dataset.kind === 'reconstruct' && "
            "document.getElementById('job').dataset.state === 'succeeded')",
            timeout=JOB_TIMEOUT_MS,
        )
        state = page.eval_on_selector("#job", "e => [e.dataset.kind, e.dataset.state]")
        assert state == ["reconstruct", "succeeded"], (state, page.text_content("#job"))
        assert page.text_content("#job-state") == "succeeded"
        # the project's job list: the reconstruct above the match it waited for, both done
        wait_until(
            page,
            "[...document.querySelectorAll('#job-rows tr[data-id]')].map("
            "r => r.dataset.kind + ' ' + r.dataset.state).join() === "
            "'reconstruct succeeded,match succeeded'",
        )

        # the model as the API serves it, fetched directly
        c = console.d.client(console.key)
        summary = c.get(f"/v1/projects/{pid}/model", params={"format": "json"}).json()
        scene_json = c.get(f"/v1/projects/{pid}/model", params={"format": "scene"}).json()
        assert summary["points3D"] > 0 and summary["registered"] == summary["images"] == len(IMAGES), summary
        assert scene_json["points"] == summary["points3D"]
        assert len(scene_json["cameras"]) == summary["registered"]
        assert sorted(cam["name"] for cam in scene_json["cameras"]) == summary["registered_names"]

        # what the viewer drew: every point (the first view frames the whole model: the synthetic
        # one has no far strays, which the viewer leaves out of its framing) and every camera
        wait_until(page, f"window.geomatchViewer && window.geomatchViewer.points === {summary['points3D']}")
        drawn = page.evaluate(
            "(({points, cameras, drawnPoints, frames}) => ({points, cameras, drawnPoints, frames}))"
            "(window.geomatchViewer)"
        )
        assert drawn["points"] == drawn["drawnPoints"] == summary["points3D"], drawn
        assert drawn["cameras"] == summary["registered"], drawn
        assert page.get_attribute("#viewer", "data-points") == str(summary["points3D"])

        # the survey report card: the report endpoint's numbers (no GCPs here: no GCP table)
        report = c.get(f"/v1/projects/{pid}/report").json()
        wait_until(page, "document.getElementById('report-card').dataset.state === 'shown'")
        card = facts(page)
        assert card["registered"] == f"{summary['registered']} of {len(IMAGES)}", card
        assert card["unregistered"] == "none" and card["points"] == str(summary["points3D"]), card
        assert card["reprojection"] == f"{report['model']['mean_reprojection_error_px']} px", card
        assert page.is_hidden("#report-gcp")
        lengths = page.locator("#report-tracks tr:last-child td").all_text_contents()
        assert lengths == [str(v) for v in report["model"]["track_lengths"].values()] and lengths
        stages = page.eval_on_selector_all(
            "#report-timings tr[data-stage]", "els => els.map(e => e.dataset.stage)"
        )
        assert stages == list(report["timings_s"]) and "mapping" in stages, stages

        wait_until(
            page,
            f"[...document.querySelectorAll('#thumbs img')].filter(i => i.naturalWidth === 640).length"
            f" === {len(IMAGES)}",
        )
        page.evaluate("window.scrollTo(0, 0)")
        page.screenshot(path=tmp_path / "project-top.png")

        # thumbnails know which images the model registered
        registration = dict(
            page.eval_on_selector_all(
                "#thumbs li.thumb", "els => els.map(e => [e.dataset.name, e.dataset.registration])"
            )
        )
        assert registration == {
            n: "registered" if n in summary["registered_names"] else "not registered" for n in IMAGES
        }

        # a pair's match picture, drawn by the worker and fetched with the key
        page.wait_for_selector("#pair-rows tr[data-name0]")
        pairs = c.get(f"/v1/projects/{pid}/pairs").json()["pairs"]
        n_pairs = len(IMAGES) * (len(IMAGES) - 1) // 2
        assert len(pairs) == n_pairs and page.locator("#pair-rows tr[data-name0]").count() == n_pairs
        assert sorted(tuple(sorted((p["name0"], p["name1"]))) for p in pairs) == database_pairs(
            c, pid, tmp_path / "database.db"
        )
        assert all(0 <= p["inliers"] <= p["matches"] for p in pairs) and pairs[0]["inliers"] > 0
        page.click("#pair-rows tr[data-name0] button")
        wait_until(
            page,
            "(() => { const i = document.getElementById('match-picture'); "
            "return !i.hidden && i.complete && i.naturalWidth > 0; })()",
            timeout=180_000,
        )

        # turn the model, then click a camera: its image shows beside the viewer
        page.locator("#viewer").scroll_into_view_if_needed()
        box = page.locator("#viewer").bounding_box()
        page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
        page.mouse.down()
        page.mouse.move(box["x"] + box["width"] / 2 + 80, box["y"] + box["height"] / 2 + 20, steps=5)
        page.mouse.up()
        frames = page.evaluate("window.geomatchViewer.frames")
        assert frames > drawn["frames"]
        # a camera the user can click: inside the canvas and not under another element (CI once
        # waited 60 s for an image after clicking camera 0's point: off the canvas after the turn,
        # or the view changed between reading the point and the click); a user whose click
        # missed clicks again, and so does the test, three times at most
        shown = (
            "(() => { const i = document.getElementById('camera-image'); "
            "return !i.hidden && i.complete && i.naturalWidth > 0; })()"
        )
        for attempt in range(3):
            point = page.evaluate(
                """() => {
                  const v = window.geomatchViewer, c = document.getElementById('viewer');
                  const r = c.getBoundingClientRect();
                  for (let i = 0; i < v.cameras; i++) {
                    const p = v.cameraPoint(i);
                    if (!p || p.x < 2 || p.y < 2 || p.x > r.width - 2 || p.y > r.height - 2) continue;
                    const x = r.left + p.x, y = r.top + p.y;
                    if (document.elementFromPoint(x, y) === c) return {x, y};
                  }
                  return null;
                }"""
            )
            assert point is not None, "no camera of the model is visible and clickable in the viewer"
            page.mouse.click(point["x"], point["y"])
            try:
                wait_until(page, shown, timeout=20_000)
                break
            except TimeoutError as e:
                if attempt == 2:
                    raise TimeoutError(f"{e}; caption: {page.text_content('#camera-caption')!r}") from None
        assert page.text_content("#camera-caption") in summary["registered_names"]
        page.locator("#model-title").scroll_into_view_if_needed()
        page.screenshot(path=tmp_path / "model.png")
        page.locator("#report-card").screenshot(path=tmp_path / "report.png")
        page.screenshot(path=tmp_path / "project.png", full_page=True)

        # the report's Markdown page, downloaded as the other files are (the key in a header)
        with page.expect_download() as download:
            page.click("button[data-download='report?format=md']")
        assert download.value.suggested_filename == f"{pid}-report.md"
        page_md = Path(download.value.path()).read_text()
        assert page_md.startswith("# Survey report: console e2e\n") and f"of {len(IMAGES)}" in page_md
        assert page_md == c.get(f"/v1/projects/{pid}/report", params={"format": "md"}).text

        # a download: the model's zip, fetched with the key and saved from a blob: URL
        with page.expect_download() as download:
            page.click("button[data-download='model?format=zip']")
        assert download.value.suggested_filename == f"{pid}-model.zip"
        with zipfile.ZipFile(download.value.path()) as z:
            assert "summary.json" in z.namelist() and "sparse/0/points3D.txt" in z.namelist()
            z.extractall(tmp_path / "model")
        # the scene's poses are COLMAP's: the same camera centres as pycolmap reads from the zip
        rec = pycolmap.Reconstruction(str(tmp_path / "model" / "sparse" / "0"))
        centres = {im.name: np.asarray(im.projection_center()) for im in rec.images.values() if im.has_pose}
        for cam in scene_json["cameras"]:
            assert np.allclose(cam["center"], centres[cam["name"]], atol=1e-4), cam["name"]

        # the same page at phone width: nothing wider than the screen
        page.set_viewport_size(PHONE)
        page.wait_for_timeout(300)
        assert page.evaluate("document.documentElement.scrollWidth") <= PHONE["width"]
        page.screenshot(path=tmp_path / "phone.png")

        # a report with ground control points (as a reconstruct with a gcp_list.txt writes it:
        # tests/service/test_gcp_api.py makes a real one) shows their table and RMSE, names as text
        page.set_viewport_size(DESKTOP)
        page.route(f"**/v1/projects/{pid}/report?format=json", with_gcps)
        page.reload()
        wait_until(page, "document.getElementById('report-card').dataset.state === 'shown'")
        page.wait_for_selector("#report-gcp:not([hidden])")
        rows = page.eval_on_selector_all(
            "#report-gcp-rows tr", "els => els.map(r => [...r.cells].map(c => c.textContent))"
        )
        assert rows == [
            ["gcp00", "control", "3 (3)", "0.012", "-0.020", "0.031", "0.039", "reprojection 0.8 px"],
            [XSS, "check", "2 (2)", "0.110", "0.040", "-0.105", "0.157", "reprojection 1.2 px"],
            ["gcp09", "unused", "1 (1)", "", "", "", "", "seen in one photo only"],
        ], rows
        assert facts(page)["check-rmse"] == "0.117 m horizontal, 0.157 m 3D"
        assert facts(page)["control-rmse"] == "0.012 m horizontal, 0.039 m 3D"
        assert page.locator("#report-gcp-rows img").count() == 0  # a point's name is text, never markup
        page.locator("#report-card").screenshot(path=tmp_path / "report-gcp.png")
        print(f"console: photos to point cloud in {time.monotonic() - t0:.0f}s; screenshots in {tmp_path}")


def facts(page: Any) -> dict[str, str]:
    """The survey report card's facts, by their data-fact keys."""
    return dict(
        page.eval_on_selector_all(
            "#report-card dd[data-fact]", "els => els.map(e => [e.dataset.fact, e.textContent])"
        )
    )


# the georeferencing.gcp of a report, as geomatch.report copies it from the reconstruct's gcp
GCP_IN_REPORT = {
    "crs": "EPSG:32632",
    "points": [
        {"name": "gcp00", "role": "control", "observations": 3, "observations_registered": 3,
         "reprojection_px": 0.8, "dx_m": 0.012, "dy_m": -0.02, "dz_m": 0.031, "3d_m": 0.039},
        {"name": XSS, "role": "check", "observations": 2, "observations_registered": 2,
         "reprojection_px": 1.2, "dx_m": 0.11, "dy_m": 0.04, "dz_m": -0.105, "3d_m": 0.157},
        {"name": "gcp09", "role": "unused", "observations": 1, "observations_registered": 1,
         "reason": "seen in one photo only"},
    ],
    "control_rmse_horizontal_m": 0.012, "control_rmse_3d_m": 0.039,
    "check_rmse_horizontal_m": 0.117, "check_rmse_3d_m": 0.157,
}  # fmt: skip


def with_gcps(route: Any) -> None:
    """The server's report with GCP_IN_REPORT in it (a Playwright route handler)."""
    response = route.fetch()
    report = response.json()
    report["georeferencing"]["gcp"] = GCP_IN_REPORT
    route.fulfill(response=response, json=report)


def test_cancel_from_the_page(console: Console, scene: Path, tmp_path: Path) -> None:
    """A running match stops from its Cancel button; the page shows the state the API reports."""
    with page_of(console) as page:
        sign_in(page, console)
        pid = create_project(page, "console cancel")
        page.set_input_files(
            "#file-input", [str(scene / "images" / n) for n in ("aerial_01.png", "ground_03.png")]
        )
        wait_until(page, "document.querySelectorAll('#upload-list li[data-state=done]').length === 2")
        page.fill("#resize", "0")  # full size: long enough to be cancelled while it runs
        page.uncheck("#with-reconstruct")
        page.click("#start-match")
        page.wait_for_selector("#job[data-kind=match]")
        page.click("#cancel-job")
        wait_until(page, "document.getElementById('job').dataset.state === 'cancelled'")
        assert page.text_content("#job-state") == "cancelled"
        assert page.is_disabled("#cancel-job")
        page.screenshot(path=tmp_path / "cancelled.png")
        job_id = page.evaluate("document.getElementById('job').dataset.id")
        c = console.d.client(console.key)
        assert c.get(f"/v1/jobs/{job_id}").json()["state"] == "cancelled"
        assert c.get(f"/v1/projects/{pid}").json()["has_model"] is False


def test_a_second_tab_sees_the_projects_jobs(console: Console, scene: Path, tmp_path: Path) -> None:
    """The jobs are the server's, not the tab's: a page in another browser context (its own
    sessionStorage, as another device) opened on the project lists a job started elsewhere,
    follows it and can cancel it; the first page sees the cancellation."""
    with page_of(console) as first, page_of(console) as second:
        sign_in(first, console)
        pid = create_project(first, "console two tabs")
        first.set_input_files(
            "#file-input", [str(scene / "images" / n) for n in ("aerial_01.png", "ground_03.png")]
        )
        wait_until(first, "document.querySelectorAll('#upload-list li[data-state=done]').length === 2")
        first.fill("#resize", "0")  # full size: still running when the second page looks
        first.uncheck("#with-reconstruct")
        first.click("#start-match")
        first.wait_for_selector("#job[data-kind=match]")
        job_id = first.evaluate("document.getElementById('job').dataset.id")
        wait_until(first, f"document.querySelector('#job-rows tr[data-id=\"{job_id}\"]')")

        sign_in(second, console)
        second.goto(f"{console.d.url}/#/projects/{pid}")
        second.wait_for_selector("#project-view:not([hidden])")
        row = f"#job-rows tr[data-id='{job_id}']"
        second.wait_for_selector(row)
        assert second.get_attribute(row, "data-kind") == "match"
        assert second.get_attribute(row, "data-state") in ("queued", "running")
        assert second.locator("#job-rows tr[data-id]").count() == 1
        # the open job is followed on this page too, and cancelled from it
        second.wait_for_selector(f"#job[data-id='{job_id}']")
        second.screenshot(path=tmp_path / "second-tab.png", full_page=True)
        second.click("#cancel-job")
        wait_until(second, "document.getElementById('job').dataset.state === 'cancelled'")
        wait_until(second, f"document.querySelector(\"{row}\").dataset.state === 'cancelled'")
        wait_until(first, "document.getElementById('job').dataset.state === 'cancelled'")
        wait_until(first, f"document.querySelector(\"{row}\").dataset.state === 'cancelled'")
        assert console.d.client(console.key).get(f"/v1/jobs/{job_id}").json()["state"] == "cancelled"


def test_ground_control_points_card(console: Console, scene: Path, tmp_path: Path) -> None:
    """A gcp_list.txt chosen on the project page: its usable points and problems show (names as
    text), a reload reads them back from the server, a file the project cannot use shows the API's
    reason and leaves the stored one, Reconstruct only sends the check points, Remove removes it."""
    c = console.d.client(console.key)
    pid = c.post("/v1/projects", json={"name": "console gcps"}).json()["id"]
    files = [("files", (n, (scene / "images" / n).read_bytes(), "image/png")) for n in IMAGES[:2]]
    assert c.post(f"/v1/projects/{pid}/images", files=files).status_code == 201
    # three points off one line: a collinear set cannot fix a rotation and is refused on upload
    lines = [
        f"{465000 + 40 * i} {5247000 + 30 * i * i} 408 {100 + 50 * i} 200 {n} g{i}"
        for i in range(3)
        for n in IMAGES[:2]
    ]
    lines += ["465009 5247009 408 10 10 ground_00.png <b>lone</b>", "465008 5247008 408 5 5 missing.png g8"]
    good = "EPSG:32632\n" + "\n".join(lines) + "\n"
    card = "document.getElementById('gcp-card').dataset.state"
    with page_of(console) as page:
        sign_in(page, console)
        page.goto(f"{console.d.url}/#/projects/{pid}")
        wait_until(page, f"{card} === 'none' && document.getElementById('gcp-status').textContent")
        assert page.is_hidden("#gcp-remove") and page.is_hidden("#gcp-details")

        page.set_input_files(
            "#gcp-input", [{"name": "gcp_list.txt", "mimeType": "text/plain", "buffer": good.encode()}]
        )
        wait_until(page, f"{card} === 'stored'")
        assert page.locator("#gcp-points li").all_text_contents() == ["g0", "g1", "g2"]
        problems = page.locator("#gcp-problems li").all_text_contents()
        assert any("<b>lone</b>: seen in one photo only" in p for p in problems), problems
        assert any("image 'missing.png' is not in the project" in p for p in problems), problems
        assert page.locator("#gcp-problems b").count() == 0  # a point's name is text, never markup
        assert "3 usable points in EPSG:32632" in page.text_content("#gcp-status")
        page.reload()
        wait_until(page, f"{card} === 'stored'")
        assert page.locator("#gcp-points li").all_text_contents() == ["g0", "g1", "g2"]
        page.locator("#gcp-card").screenshot(path=tmp_path / "gcp.png")

        bad = {"name": "bad.txt", "mimeType": "text/plain", "buffer": b"NAD99\n1 2 3 4 5 ground_00.png a\n"}
        page.set_input_files("#gcp-input", [bad])
        wait_until(page, "document.getElementById('gcp-status').dataset.state === 'error'")
        assert "bad.txt was refused: line 1: unknown coordinate system" in page.text_content("#gcp-status")
        assert page.locator("#gcp-points li").all_text_contents() == ["g0", "g1", "g2"]  # the stored one
        assert c.get(f"/v1/projects/{pid}/gcp").json()["points"] == ["g0", "g1", "g2"]

        page.fill("#checkpoints", "g1, g2")
        with page.expect_request(lambda r: r.url.endswith("/reconstruct")) as sent:
            page.click("#start-reconstruct")
        assert sent.value.post_data_json == {"checkpoints": ["g1", "g2"]}
        wait_until(page, "document.getElementById('notice').textContent.includes('nothing to reconstruct')")

        page.click("#gcp-remove")
        wait_until(page, f"{card} === 'none'")
        assert c.get(f"/v1/projects/{pid}/gcp").status_code == 404
