"""The README's pictures of the web console (docs/img/console-*.png), taken on a real project.

    .venv/bin/python bench/console_shots.py                      # brighton_beach's 18 DJI photos
    .venv/bin/python bench/console_shots.py --images DIR --name "my survey" --out /tmp/shots
    .venv/bin/python bench/console_shots.py --home /tmp/shots-home   # kept: a second run reuses it

It starts an embedded `geomatch serve` (a temporary GEOMATCH_HOME, a free loopback port, the key
it keeps in GEOMATCH_HOME/api-key.txt, no gRPC; `--home DIR` keeps that folder, and a later run
with the same DIR and name reuses the project's model and only takes the pictures), creates a
project, uploads every photo of the folder as they are (capture auto: the XMP decides), starts a
match with reconstruct with the service's defaults (no option sent) and waits for the reconstruct
job. Then it opens the console
in Chromium, driven by Playwright as tests/service/test_console.py does (the system's browser,
GEOMATCH_CHROMIUM to pick another), signs in with the key and writes, at 1280x800:

- console-project.png: the project page's top (uploads, images with capture and registration);
- console-model.png: the model in the viewer, a camera picked and its photo beside it;
- console-report.png: the survey report card;
- console-phone.png: the survey report at phone width (390x844).

Each PNG is reduced to 256 colours when that makes it smaller (photos' thumbnails make a full
colour screenshot of ~1 MB). It prints what the README's caption says: photos registered, points,
the time from upload to model.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
BRIGHTON = Path("/work/shared/data/real/drone/brighton_beach/images")
DESKTOP = {"width": 1280, "height": 800}
PHONE = {"width": 390, "height": 844}
PHOTOS = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
TERMINAL = ("succeeded", "failed", "cancelled")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def serving(home: Path) -> Iterator[tuple[str, str]]:
    """An embedded `geomatch serve` on a free port: (its URL, its key)."""
    port = free_port()
    mine = ("GEOMATCH_", "REDIS_URL", "DATABASE_URL")  # embedded: no Redis, SQLite in home
    env = {k: v for k, v in os.environ.items() if not k.startswith(mine)}
    env |= {"GEOMATCH_HOME": str(home), "GEOMATCH_LOG_FORMAT": "text"}
    home.mkdir(parents=True, exist_ok=True)
    log_path = home / "server.log"
    log = log_path.open("wb")
    args = ["serve", "--host", "127.0.0.1", "--port", str(port), "--no-grpc"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "geomatch_app", *args], env=env, stdout=log, stderr=subprocess.STDOUT
    )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 180
        while True:
            if proc.poll() is not None:
                raise RuntimeError(f"geomatch serve exited: {log_path.read_text()[-3000:]}")
            with contextlib.suppress(httpx.HTTPError, ValueError):
                if httpx.get(f"{url}/readyz", timeout=2).json().get("ready"):
                    break
            if time.monotonic() > deadline:
                raise RuntimeError("geomatch serve not ready after 180 s")
            time.sleep(0.5)
        yield url, (home / "api-key.txt").read_text().strip()
    finally:
        proc.terminate()
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=30)
        if proc.poll() is None:
            proc.kill()
        log.close()


def wait_job(c: httpx.Client, job_id: str) -> dict[str, Any]:
    last = ""
    while True:
        job = c.get(f"/v1/jobs/{job_id}").json()
        line = f"  {job['kind']}: {job['state']} {job['progress']['done']}/{job['progress']['total']}"
        if line != last:
            print(line, flush=True)
            last = line
        if job["state"] in TERMINAL:
            return dict(job)
        time.sleep(2)


def reconstruct(url: str, key: str, name: str, photos: list[Path]) -> tuple[str, dict[str, Any], float]:
    """A project of the photos, matched and reconstructed: (its id, the model's summary, seconds).
    A project of that name with a model already (``--home``) is taken as it is."""
    t0 = time.monotonic()
    with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {key}"}, timeout=600) as c:
        for p in c.get("/v1/projects").json():
            if p["name"] == name and p["has_model"]:
                print(f"project {name!r} has a model already: {p['id']}", flush=True)
                summary = c.get(f"/v1/projects/{p['id']}/model", params={"format": "json"}).json()
                return str(p["id"]), summary, 0.0
        pid = str(c.post("/v1/projects", json={"name": name}).json()["id"])
        for p in photos:  # one request a photo, as the console sends them
            with p.open("rb") as f:
                files = {"files": (p.name, f)}
                r = c.post(f"/v1/projects/{pid}/images", files=files, data={"capture": "auto"})
            if r.status_code != 201:
                raise RuntimeError(f"upload of {p.name}: {r.status_code} {r.text}")
        print(f"uploaded {len(photos)} photos in {time.monotonic() - t0:.0f} s", flush=True)
        accepted = c.post(f"/v1/projects/{pid}/match", json={"reconstruct": True}).json()
        for job_id in (accepted["job_id"], accepted["reconstruct_job_id"]):
            job = wait_job(c, job_id)
            if job["state"] != "succeeded":
                raise RuntimeError(f"{job['kind']} job {job['state']}: {job.get('error')}")
        summary = c.get(f"/v1/projects/{pid}/model", params={"format": "json"}).json()
    return pid, summary, time.monotonic() - t0


def chromium() -> str:
    given = os.environ.get("GEOMATCH_CHROMIUM")
    found = given or next(
        filter(None, map(shutil.which, ("chromium", "chromium-browser", "google-chrome"))), None
    )
    if not found:
        raise SystemExit("no Chromium: tests/ensure_browser.sh installs it, or set GEOMATCH_CHROMIUM")
    return found


def wait_until(page: Any, expression: str, timeout_s: float = 120) -> None:
    """Poll a JavaScript expression (the console's CSP forbids wait_for_function's eval)."""
    deadline = time.monotonic() + timeout_s
    while not page.evaluate(expression):
        if time.monotonic() > deadline:
            raise TimeoutError(f"still false after {timeout_s:.0f} s: {expression}")
        time.sleep(0.25)


def pick_camera(page: Any) -> None:
    """Click a camera of the viewer near the canvas's middle; wait for its photo beside it."""
    point = page.evaluate(
        """() => {
          const v = window.geomatchViewer, c = document.getElementById('viewer');
          const r = c.getBoundingClientRect();
          let best = null;
          for (let i = 0; i < v.cameras; i++) {
            const p = v.cameraPoint(i);
            if (!p || p.x < 4 || p.y < 4 || p.x > r.width - 4 || p.y > r.height - 4) continue;
            const x = r.left + p.x, y = r.top + p.y;
            if (document.elementFromPoint(x, y) !== c) continue;
            const d = Math.hypot(p.x - r.width / 2, p.y - r.height / 2);
            if (!best || d < best.d) best = {x, y, d};
          }
          return best;
        }"""
    )
    if point is None:
        raise RuntimeError("no camera of the model is visible in the viewer")
    page.mouse.click(point["x"], point["y"])
    wait_until(
        page,
        "(() => { const i = document.getElementById('camera-image'); "
        "return !i.hidden && i.complete && i.naturalWidth > 0; })()",
    )


def shoot(page: Any, path: Path) -> None:
    """The viewport as a PNG, in 256 colours when that is smaller."""
    png = page.screenshot()
    small = io.BytesIO()
    Image.open(io.BytesIO(png)).convert("RGB").quantize(256, dither=Image.Dither.FLOYDSTEINBERG).save(
        small, "PNG", optimize=True
    )
    data = min(png, small.getvalue(), key=len)
    path.write_bytes(data)
    print(f"  {path} ({len(data) // 1024} KiB)", flush=True)


def scroll_to(page: Any, element_id: str) -> None:
    page.evaluate(f"document.getElementById('{element_id}').scrollIntoView({{block: 'start'}})")
    page.wait_for_timeout(300)


def screenshots(url: str, key: str, pid: str, summary: dict[str, Any], out: Path) -> None:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium(), args=["--no-sandbox"])
        try:
            page = browser.new_context(viewport=DESKTOP).new_page()
            page.set_default_timeout(120_000)
            page.goto(url + "/")
            page.fill("#key-input", key)
            page.click("#key-form button[type=submit]")
            page.wait_for_selector("#projects-view:not([hidden])")
            page.goto(f"{url}/#/projects/{pid}")
            page.wait_for_selector("#project-view:not([hidden])")
            points = summary["points3D"]
            wait_until(page, f"window.geomatchViewer && window.geomatchViewer.points === {points}")
            wait_until(page, "document.getElementById('report-card').dataset.state === 'shown'")
            n = summary["images"]
            wait_until(
                page,
                f"[...document.querySelectorAll('#thumbs img')].filter(i => i.complete && i.naturalWidth > 0)"
                f".length === {n}",
            )
            page.evaluate("window.scrollTo(0, 0)")
            shoot(page, out / "console-project.png")
            page.locator("#viewer").scroll_into_view_if_needed()
            pick_camera(page)
            scroll_to(page, "model-title")
            page.evaluate("window.scrollBy(0, -12)")
            shoot(page, out / "console-model.png")
            scroll_to(page, "report-card")
            page.evaluate("window.scrollBy(0, -12)")
            shoot(page, out / "console-report.png")
            page.set_viewport_size(PHONE)
            scroll_to(page, "report-card")
            shoot(page, out / "console-phone.png")
        finally:
            browser.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", type=Path, default=BRIGHTON, help="a folder of photos (default: %(default)s)")
    ap.add_argument("--name", default="brighton_beach", help="the project's name (default: %(default)s)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "img", help="where the PNGs go (%(default)s)")
    ap.add_argument("--home", type=Path, help="the server's GEOMATCH_HOME, kept (default: a temporary one)")
    args = ap.parse_args()
    photos = sorted(p for p in args.images.iterdir() if p.suffix.lower() in PHOTOS)
    if len(photos) < 2:
        raise SystemExit(f"{args.images}: fewer than 2 photos")
    args.out.mkdir(parents=True, exist_ok=True)
    tmp = tempfile.TemporaryDirectory(prefix="console-shots-")
    home = args.home.resolve() if args.home else Path(tmp.name) / "home"
    with tmp, serving(home) as (url, key):
        print(f"geomatch serve at {url}, {len(photos)} photos from {args.images}", flush=True)
        pid, summary, took = reconstruct(url, key, args.name, photos)
        report = summary.get("report", {})
        gps = report.get("georeferencing", {}).get("gps") or {}
        print(
            f"model: {summary['registered']} of {summary['images']} photos registered, "
            f"{summary['points3D']} points, mean track length {summary['mean_track_length']:.2f}, "
            f"reprojection error {summary['mean_reprojection_error']:.2f} px, "
            f"GPS residual median {gps.get('median_m')} m, upload to model in {took:.0f} s "
            f"(mapper {summary.get('mapper')}, pairs {summary.get('pair_plan')})",
            flush=True,
        )
        screenshots(url, key, pid, summary, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
