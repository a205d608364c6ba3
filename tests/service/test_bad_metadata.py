"""Metadata a camera wrote wrong degrades a job, never fails it: four photos with GPS fixes, one
with a GPSAltitude of 0/0 (Pillow reads NaN) and one with a DJI AbsoluteAltitude of 1e999,
matched and reconstructed through the service. The reconstruct once failed with
``LinAlgError: SVD did not converge`` naming neither image nor field."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
from PIL import Image
from PIL.ExifTags import GPS, IFD
from PIL.TiffImagePlugin import IFDRational

from .harness import Deployment, upload, wait_job

ABSURD_XMP = (
    '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:Description drone-dji:AbsoluteAltitude="1e999"/></x:xmpmeta>'
)


def as_jpeg(png: Path, dest: Path, altitude: object = None, xmp: str = "") -> Path:
    """The scene's PNG as a camera's JPEG with the same EXIF (its GPS fix), the altitude replaced
    when given, and an XMP packet when given."""
    with Image.open(png) as im:
        exif = im.getexif()
        if altitude is not None:
            exif.get_ifd(IFD.GPSInfo)[GPS.GPSAltitude] = altitude
        buf = io.BytesIO()
        im.convert("RGB").save(
            buf, "JPEG", quality=95, exif=exif.tobytes(), **({"xmp": xmp.encode()} if xmp else {})
        )
    dest.write_bytes(buf.getvalue())
    return dest


@pytest.mark.service
def test_absurd_gps_altitudes_are_ignored_and_the_reconstruct_succeeds(
    deployment: Deployment, key_a: str, scene: Path, tmp_path: Path
) -> None:
    images = scene / "images"
    files = [
        as_jpeg(images / "ground_00.png", tmp_path / "ground_00.jpg"),
        as_jpeg(images / "ground_01.png", tmp_path / "ground_01.jpg", altitude=IFDRational(0, 0)),
        as_jpeg(images / "ground_02.png", tmp_path / "ground_02.jpg", xmp=ABSURD_XMP),
        as_jpeg(images / "ground_03.png", tmp_path / "ground_03.jpg"),
    ]
    c = deployment.client(key_a)
    pid = c.post("/v1/projects", json={"name": "bad metadata"}).json()["id"]
    assert upload(c, pid, files, "ground").status_code == 201
    # what test_e2e.py's batch test measured to register all four views
    options = {"method": "sparse", "resize": 480, "reconstruct": True}
    accepted = c.post(f"/v1/projects/{pid}/match", json=options).json()
    assert wait_job(c, accepted["job_id"])["state"] == "succeeded", deployment.logs()
    recon = wait_job(c, accepted["reconstruct_job_id"])
    assert recon["state"] == "succeeded", (recon, deployment.logs())
    result = recon["result"]
    assert result["registered"] == 4 and result["gps_images"] == 4, result
    # every image keeps its horizontal fix; the two without a usable altitude sit at the others'
    assert result["georeferenced"] and result["alignment"]["correspondences"] == 4, result
    logs = deployment.logs(tail=10**7)
    assert "ground_01.jpg: EXIF GPSAltitude ignored" in logs
    assert "ground_02.jpg: XMP AbsoluteAltitude ignored" in logs
