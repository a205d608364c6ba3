"""What a failed job says: the reason, with the project's files by their names and no path of
the server's. The service test damages stored images behind the upload check's back (a disk
fault, an operator's copy) so that a worker fails on them, first in a match job, then in a
reconstruct job."""

from __future__ import annotations

import re
from pathlib import Path

import httpx
import pytest

from workers.redact import MAX_MESSAGE, client_message, without_paths

from .harness import Deployment, upload, wait_job

# a "/" starting a word, as an absolute path's does (not "0/0", not a URL's)
ABSOLUTE_PATH = re.compile(r"(?<![\w.:/~-])/[^\s/]")


@pytest.mark.unit
def test_a_store_or_redis_error_reaches_the_client_as_the_part_that_failed(tmp_path: Path) -> None:
    """No SQL, parameters or driver text in a job's error (PostgreSQL's refusal of a NaN once
    reached clients with the whole UPDATE); a step's own reasons as written; all capped."""
    import redis
    import sqlalchemy.exc

    from workers.context import PermanentError

    sql = sqlalchemy.exc.DataError(
        "UPDATE jobs SET state=%(state)s, result=%(result)s WHERE jobs.id = %(id_1)s",
        {"result": '{"x": NaN}'},
        Exception('invalid input syntax for type json DETAIL: Token "NaN" is invalid.'),
    )
    text = client_message(sql, tmp_path)
    assert text == "the metadata store refused or lost the operation (Exception)", text
    ro = redis.ReadOnlyError("You can't write against a read only replica.")
    assert client_message(ro, tmp_path) == "the queue (Redis) refused or lost the operation (ReadOnlyError)"
    assert client_message(PermanentError("bad options"), tmp_path) == "bad options"
    assert client_message(ValueError("x" * 10**5), tmp_path).endswith("...")
    assert len(client_message(ValueError("x" * 10**5), tmp_path)) == MAX_MESSAGE


@pytest.mark.unit
def test_paths_become_names_relative_to_the_project(tmp_path: Path) -> None:
    root = tmp_path / "home"
    project = root / "projects" / "0123abcd"
    (project / "images").mkdir(parents=True)
    linked = tmp_path / "link"
    linked.symlink_to(root)
    image = project / "images" / "my photo (1).jpg"
    for text, expected in [
        (
            f"ImageReadError: {image}: not a readable image (cannot identify image file '{image}')",
            "ImageReadError: my photo (1).jpg: not a readable image "
            "(cannot identify image file 'my photo (1).jpg')",
        ),
        (f"OSError: {project}/work/reconstruct-1/model", "OSError: work/reconstruct-1/model"),
        (f"{root}/features/ab/cd.npz is gone", "features/ab/cd.npz is gone"),
        (f"{linked}/projects/0123abcd/images/a.png", "a.png"),  # the root through a link
        (
            "FileNotFoundError: '/usr/lib/python3/dist-packages/x/weights.pth'",
            "FileNotFoundError: 'weights.pth'",
        ),
        (
            "GPSAltitude 0/0 and/or redis://127.0.0.1:6379/0, 4 / 3",
            "GPSAltitude 0/0 and/or redis://127.0.0.1:6379/0, 4 / 3",
        ),
    ]:
        assert without_paths(text, linked, linked / "projects" / "0123abcd") == expected, text
    assert without_paths(str(image), root) == "projects/0123abcd/images/my photo (1).jpg"


def corrupt(deployment: Deployment, project: str, name: str) -> bytes:
    """Overwrite a stored image with bytes no reader decodes; returns what was there."""
    path = deployment.home / "projects" / project / "images" / name
    whole = path.read_bytes()
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + b"this is no longer an image" * 40)
    return whole


def assert_no_server_path(error: str, deployment: Deployment) -> None:
    assert str(deployment.home) not in error and str(deployment.root) not in error, error
    assert not ABSOLUTE_PATH.search(error), error


@pytest.mark.service
def test_job_errors_name_images_not_server_paths(deployment: Deployment, key_a: str, scene: Path) -> None:
    c: httpx.Client = deployment.client(key_a)
    pid = c.post(
        "/v1/projects", json={"name": "errors", "config": {"resize": 256, "method": "sparse"}}
    ).json()["id"]
    names = ["ground_00.png", "ground_01.png"]
    assert upload(c, pid, [scene / "images" / n for n in names], "ground").status_code == 201

    whole = corrupt(deployment, pid, "ground_01.png")
    job = wait_job(c, c.post(f"/v1/projects/{pid}/match", json={}).json()["job_id"])
    assert job["state"] == "failed" and "ground_01.png" in job["error"], job
    assert_no_server_path(job["error"], deployment)

    (deployment.home / "projects" / pid / "images" / "ground_01.png").write_bytes(whole)
    job = wait_job(c, c.post(f"/v1/projects/{pid}/match", json={}).json()["job_id"])
    assert job["state"] == "succeeded", (job, deployment.logs())
    corrupt(deployment, pid, "ground_00.png")
    job = wait_job(c, c.post(f"/v1/projects/{pid}/reconstruct", json={}).json()["job_id"])
    assert job["state"] == "failed" and job["error"].startswith("reconstruct: "), job
    assert "ground_00.png" in job["error"], job
    assert_no_server_path(job["error"], deployment)
