"""The map through the service (Redis mode, real uvicorn, Celery worker, networks, pycolmap): a
small survey flight (synth.flight: nadir photos with GPS and DJI XMP) matched with a chained
reconstruct asking for the map, its orthophoto, DSM and preview served as model formats, the map
in the report; a reconstruct of the same project without the map has none and says so (404)."""

from __future__ import annotations

import io
import zipfile
from typing import Any

import pytest
import rasterio

from geomatch.ortho.cog import is_cog
from geomatch.synth.flight import write_flight

from .harness import Deployment, upload, wait_job

pytestmark = pytest.mark.service


@pytest.fixture(scope="module")
def mapped(deployment: Deployment, key_a: str, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    flight = tmp_path_factory.mktemp("flight")
    write_flight(flight, photos=8, size=(320, 240), seed=5)
    c = deployment.client(key_a)
    pid = c.post("/v1/projects", json={"name": "map", "config": {"resize": 320}}).json()["id"]
    r = upload(c, pid, sorted((flight / "images").iterdir()))
    assert r.status_code == 201, r.text
    r = c.post(f"/v1/projects/{pid}/match", json={"reconstruct": True, "ortho": "on"})
    assert r.status_code == 202, r.text
    match = wait_job(c, r.json()["job_id"], timeout=1800)
    assert match["state"] == "succeeded", (match, deployment.logs())
    recon = wait_job(c, r.json()["reconstruct_job_id"], timeout=1800)
    assert recon["state"] == "succeeded", (recon, deployment.logs())
    return {"client": c, "pid": pid, "recon": recon, "tmp": tmp_path_factory.mktemp("map-out")}


def test_the_job_makes_the_map(mapped: dict[str, Any]) -> None:
    recon = mapped["recon"]
    assert recon["options"]["ortho"] == "on"
    record = recon["result"]["ortho"]
    assert "skipped" not in record, record
    assert record["crs"] == "EPSG:32632" and record["photos"] == recon["result"]["registered"]
    assert recon["result"]["report"]["map"]["gsd_cm"] > 0


def test_the_map_is_served(mapped: dict[str, Any]) -> None:
    c, pid, tmp = mapped["client"], mapped["pid"], mapped["tmp"]
    for fmt, media in (("orthophoto", "image/tiff"), ("dsm", "image/tiff"), ("map-preview", "image/png")):
        r = c.get(f"/v1/projects/{pid}/model", params={"format": fmt})
        assert r.status_code == 200 and r.headers["content-type"].startswith(media), (fmt, r.text[:200])
        (tmp / fmt).write_bytes(r.content)
    assert is_cog(tmp / "orthophoto")[0] and is_cog(tmp / "dsm")[0]
    with rasterio.open(tmp / "orthophoto") as src:
        assert src.count == 4 and src.crs.to_epsg() == 32632
    r = c.get(f"/v1/projects/{pid}/model", params={"format": "odm"})
    assert r.status_code == 200
    names = set(zipfile.ZipFile(io.BytesIO(r.content)).namelist())
    assert {"odm_orthophoto/odm_orthophoto.tif", "odm_dem/dsm.tif"} <= names


def test_a_reconstruct_without_the_map_has_none(mapped: dict[str, Any]) -> None:
    c, pid = mapped["client"], mapped["pid"]
    r = c.post(f"/v1/projects/{pid}/reconstruct", json={"ortho": "off"})
    assert r.status_code == 202, r.text
    job = wait_job(c, r.json()["job_id"], timeout=1800)
    assert job["state"] == "succeeded" and "ortho" not in job["result"]
    r = c.get(f"/v1/projects/{pid}/model", params={"format": "orthophoto"})
    assert r.status_code == 404 and "reconstruct with the option ortho" in r.json()["detail"]
    r = c.post(f"/v1/projects/{pid}/reconstruct", json={"ortho": "sometimes"})
    assert r.status_code == 422 and "ortho" in r.text
