"""The built image, run: its configuration, its HEALTHCHECK inside it against a running `serve`
and `worker`, and a REST flow (key, project, upload, match, reconstruct, download) served by
processes started from the image's file system over loopback.

Runs where buildah is installed and the image is built (`make image`: docker/build_local.sh builds
it, then runs this file and test_e2e.py against it). Elsewhere (CI, which installs no buildah) every
test is skipped, with the reason, at the cost of one PATH lookup.
"""

from __future__ import annotations

import io
import json
import os
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from .harness import Deployment, upload, wait_job
from .image_harness import (
    IMAGE_ENV,
    IMAGE_UID,
    ImageDeployment,
    buildah,
    image_config,
    image_name,
    unavailable,
)

IMAGE = image_name()
_why = unavailable(IMAGE)
pytestmark = [pytest.mark.service, pytest.mark.skipif(_why is not None, reason=_why or "")]

GROUND = ("ground_00.png", "ground_01.png", "ground_02.png", "ground_03.png")


@pytest.fixture(scope="module")
def image_deployment(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory, redis_url: str
) -> Iterator[ImageDeployment]:
    """The session's deployment when `make image` already runs it from the image
    (GEOMATCH_TEST_IMAGE), else one of this module's own: a server and a worker from the image."""
    if os.environ.get(IMAGE_ENV):
        d = request.getfixturevalue("deployment")
        assert isinstance(d, ImageDeployment)
        yield d
        return
    own = ImageDeployment(tmp_path_factory.mktemp("image-deployment"), redis_url, IMAGE)
    try:
        own.start_server()
        own.start_worker()
        yield own
    finally:
        own.stop()


def test_image_config() -> None:
    """What `docker run` relies on: the entrypoint, the user, the ports, the health check."""
    cfg = image_config(IMAGE)
    assert cfg["Entrypoint"] == ["geomatch"]
    assert cfg["Cmd"][0] == "serve"
    assert cfg["User"] == f"{IMAGE_UID}:{IMAGE_UID}"
    assert set(cfg["ExposedPorts"]) == {"8000/tcp", "50051/tcp"}
    assert "GEOMATCH_HOME=/data" in cfg["Env"]
    assert cfg["Healthcheck"]["Test"] == ["CMD", "python", "/opt/geomatch/healthcheck.py"]
    size = buildah("images", "--format", "{{.Size}}", IMAGE).stdout.strip()
    print(f"\n[image] {IMAGE}: {size}")


def test_processes_run_from_the_image_as_its_user(image_deployment: ImageDeployment) -> None:
    for role in ("serve", "worker"):
        pid = image_deployment.main_pid(role)
        status = Path(f"/proc/{pid}/status").read_text()
        uid = next(line.split()[1] for line in status.splitlines() if line.startswith("Uid:"))
        assert int(uid) == IMAGE_UID, (role, status)
        exe = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        assert exe[1] == b"/opt/venv/bin/geomatch", exe  # the image's venv, not the host's


def test_healthcheck_serve(image_deployment: ImageDeployment) -> None:
    r = image_deployment.healthcheck(image_deployment.main_pid("serve"))
    assert r.returncode == 0, r.stdout + r.stderr + image_deployment.logs()
    print(f"\n[image healthcheck serve] {(r.stdout + r.stderr).strip()}")
    assert "/healthz" in r.stdout + r.stderr, r


def test_healthcheck_worker(image_deployment: ImageDeployment) -> None:
    """A Celery ping to the worker's node; the worker may still be connecting: a few tries."""
    pid = image_deployment.main_pid("worker")
    for _ in range(30):
        r = image_deployment.healthcheck(pid)
        if r.returncode == 0:
            break
    assert r.returncode == 0, r.stdout + r.stderr + image_deployment.logs()
    print(f"\n[image healthcheck worker] {(r.stdout + r.stderr).strip()}")


def test_healthcheck_fails_on_what_is_not_a_server(image_deployment: ImageDeployment) -> None:
    r = image_deployment.healthcheck(1)  # init: not a `geomatch` server
    assert r.returncode == 1, r


def test_rest_flow(image_deployment: Deployment, scene: Path, tmp_path: Path) -> None:
    """Key (made in the image), project, upload, match with the default method (the image's
    weights, on its CPU torch), reconstruct, download: all through the image's REST server."""
    d = image_deployment
    t0 = time.perf_counter()
    c = d.client(d.create_key("tenant-image"))
    pid = c.post("/v1/projects", json={"name": "image"}).json()["id"]
    r = upload(c, pid, [scene / "images" / n for n in GROUND], capture="ground")
    assert r.status_code == 201, r.text
    r = c.post(f"/v1/projects/{pid}/match", json={"resize": 480})
    assert r.status_code == 202, r.text
    job = wait_job(c, r.json()["job_id"], timeout=1800)
    assert job["state"] == "succeeded" and job["progress"] == {"done": 6, "total": 6}, (job, d.logs())
    r = c.post(f"/v1/projects/{pid}/reconstruct", json={"mapper": "incremental"})
    assert r.status_code == 202, r.text
    job = wait_job(c, r.json()["job_id"])
    assert job["state"] == "succeeded", (job, d.logs())
    r = c.get(f"/v1/projects/{pid}/model", params={"format": "zip"})
    assert r.status_code == 200 and r.headers["content-type"] == "application/zip"
    zipfile.ZipFile(io.BytesIO(r.content)).extractall(tmp_path)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary == job["result"] and summary["registered"] == summary["images"] == 4, summary
    assert (tmp_path / "sparse" / "0" / "cameras.bin").is_file()
    # written by the image's user into the host folder mounted at /data
    assert (d.home / "geomatch.sqlite").stat().st_uid == IMAGE_UID
    print(
        f"\n[image REST flow] 4 images, 6 pairs at 480 px, {summary['registered']} registered, "
        f"{summary['points3D']} points, {time.perf_counter() - t0:.0f} s"
    )


def test_selfcheck_in_the_image() -> None:
    """The build ran docker/selfcheck.py; a container of the finished image passes it too."""
    r = buildah("from", "--pull=never", IMAGE)
    assert r.returncode == 0, r.stderr
    ctr = r.stdout.strip().splitlines()[-1]
    try:
        r = buildah("run", "--isolation", "chroot", ctr, "--", "python", "/opt/geomatch/selfcheck.py", "cpu")
        assert r.returncode == 0, r.stdout + r.stderr
    finally:
        buildah("rm", ctr)
