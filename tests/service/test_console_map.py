"""The console's Map card in a real browser (Debian's Chromium, Playwright) against a real embedded
server: a small survey flight matched and reconstructed with the map over REST, then the project
opened in the page: the preview shown, a camera marker per registered photo, the map's facts."""

from __future__ import annotations

from pathlib import Path

import pytest

from geomatch.synth.flight import write_flight

from .harness import upload, wait_job
from .test_console import Console, console, page_of, sign_in, wait_until  # noqa: F401  (fixture)

pytestmark = pytest.mark.browser


def test_the_map_card_shows_the_orthophoto_and_the_cameras(console: Console, tmp_path: Path) -> None:  # noqa: F811
    flight = tmp_path / "flight"
    write_flight(flight, photos=8, size=(320, 240), seed=5)
    c = console.d.client(console.key)
    pid = c.post("/v1/projects", json={"name": "console map", "config": {"resize": 320}}).json()["id"]
    assert upload(c, pid, sorted((flight / "images").iterdir())).status_code == 201
    r = c.post(f"/v1/projects/{pid}/match", json={"reconstruct": True, "ortho": "on"})
    assert r.status_code == 202, r.text
    recon = wait_job(c, r.json()["reconstruct_job_id"], timeout=1800)
    assert recon["state"] == "succeeded", (recon, console.d.logs())
    registered = recon["result"]["registered"]

    with page_of(console) as page:
        sign_in(page, console)
        page.goto(f"{console.d.url}/#/projects/{pid}")
        page.wait_for_selector("#map-card:not([hidden])")
        wait_until(page, "document.getElementById('map-card').dataset.state === 'shown'")
        wait_until(page, "document.getElementById('map-image').naturalWidth > 0")
        assert page.locator("#map-marks circle.map-camera").count() == registered
        gsd = page.text_content("#map-facts dd[data-fact=gsd]") or ""
        assert gsd.endswith("cm per pixel") and float(gsd.split()[0]) > 0
        assert page.text_content("#map-facts dd[data-fact=crs]") == "EPSG:32632"
        page.screenshot(path=tmp_path / "map.png", full_page=True)
