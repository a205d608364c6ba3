"""The embedded default: `geomatch serve` with nothing configured (no Redis, no database URL)
runs everything itself, prints a ready-to-use key, and keeps its state across restarts."""

from __future__ import annotations

import re
import stat
import subprocess
from pathlib import Path

import pycolmap
import pytest

from .harness import GEOMATCH, Deployment, upload, wait_job

GROUND = ["ground_00.png", "ground_01.png", "ground_02.png", "ground_03.png"]


def printed_key(d: Deployment) -> str:
    m = re.search(r"API key \(tenant 'local'\): (gm_\S+)", d.server_out)
    assert m, d.server_out
    return m.group(1)


@pytest.mark.service
def test_embedded_default(tmp_path_factory: pytest.TempPathFactory, scene: Path, tmp_path: Path) -> None:
    d = Deployment(tmp_path_factory.mktemp("embedded"), None)
    assert "REDIS_URL" not in d.env and "DATABASE_URL" not in d.env
    try:
        d.start_server()
        key = printed_key(d)
        assert (d.home / "geomatch.sqlite").is_file()
        assert stat.S_IMODE((d.home / "api-key.txt").stat().st_mode) == 0o600
        c = d.client(key)
        ready = c.get("/readyz").json()
        assert ready["ready"] and ready["checks"]["mode"] == "embedded"

        pid = c.post("/v1/projects", json={"name": "embedded", "config": {"resize": 320}}).json()["id"]
        assert upload(c, pid, [scene / "images" / n for n in GROUND[:3]], "ground").status_code == 201
        accepted = c.post(f"/v1/projects/{pid}/match", json={"reconstruct": True, "mapper": "global"}).json()
        match = wait_job(c, accepted["job_id"])
        assert match["state"] == "succeeded" and match["progress"] == {"done": 3, "total": 3}, d.logs()
        assert match["options"]["resize"] == 320  # the project's config
        recon = wait_job(c, accepted["reconstruct_job_id"])  # chained: started by the match's end
        assert recon["state"] == "succeeded", (recon, d.logs())
        assert recon["result"]["images"] == 3 and recon["result"]["mapper"] == "global"
        assert c.get(f"/v1/projects/{pid}/model", params={"format": "json"}).json() == recon["result"]

        # a fourth image later: only its three pairs are matched
        assert upload(c, pid, [scene / "images" / GROUND[3]], "ground").status_code == 201
        more = wait_job(c, c.post(f"/v1/projects/{pid}/match", json={}).json()["job_id"])
        assert more["state"] == "succeeded" and more["progress"] == {"done": 3, "total": 3}
        (tmp_path / "db.db").write_bytes(c.get(f"/v1/projects/{pid}/database").content)
        db = pycolmap.Database.open(str(tmp_path / "db.db"))
        try:
            assert db.num_images() == 4 and db.num_matched_image_pairs() == 6
        finally:
            db.close()

        # a restart keeps projects, and the same key
        d.kill(d.server)  # type: ignore[arg-type]  # started: not None
        d.start_server()
        assert printed_key(d) == key
        assert [p["id"] for p in d.client(key).get("/v1/projects").json()] == [pid]
    finally:
        d.stop()


@pytest.mark.unit
def test_worker_needs_redis(tmp_path: Path) -> None:
    d = Deployment(tmp_path, None)
    r = subprocess.run([*GEOMATCH, "worker"], env=d.env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "needs REDIS_URL" in r.stderr
