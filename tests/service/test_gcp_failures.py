"""GCP files that cannot georeference a model, through a real reconstruct on both metadata stores:
clicks that do not meet (the documented case), eight names at one coordinate and heights past the
range of numbers (written as a file stored before the upload checks refused them would be). Each
reconstruct succeeds with ``gcp.error`` saying why, the model keeps the frame its mapping gave it
with every number finite, the stored result is JSON without NaN and holds no SQL, and the report
answers in JSON and Markdown with a row per point.

One `geomatch serve` per store, embedded (jobs on its own threads), PostgreSQL's a fresh database.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from geomatch.synth.aerial import Scene
from geomatch.synth.gcps import scene_gcps

from .conftest import SCENE_SEED
from .grpc_harness import GrpcDeployment, running_grpc
from .harness import metadata_database, upload, wait_job

pytestmark = pytest.mark.service

GROUND = ["ground_00.png", "ground_01.png", "ground_02.png", "ground_03.png"]


@pytest.fixture(params=["sqlite", "postgresql"])
def dep(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[GrpcDeployment]:
    with metadata_database(request.param) as url:
        env = {"DATABASE_URL": url} if url else {}
        with running_grpc(tmp_path / "dep", None, "serve", **env) as d:
            yield d


def good_file() -> str:
    scene = Scene(SCENE_SEED)
    cams = [c for c in scene.cameras(2, 4, 640, 480) if c.name in GROUND]
    text, _ = scene_gcps(scene, cams, 8, seed=3)
    return text


def clicks_that_do_not_meet(text: str) -> str:
    """Every observation moved towards its photo's centre by 0, 30, 60 or 90 px down or up, the
    photo's own amount: any two clicks of a point are 30 px or more apart across the ground
    views' mostly horizontal epipolar lines (a shift along them only moves the point in depth)."""
    lines = text.splitlines()
    out = [lines[0]]
    for line in lines[1:]:
        x, y, z, px, py, image, name = line.split()
        m = 30.0 * GROUND.index(image)
        shifted = float(py) + m if float(py) < 240 else float(py) - m
        out.append(f"{x} {y} {z} {px} {shifted} {image} {name}")
    return "\n".join(out) + "\n"


def coincident(text: str) -> str:
    """Every point at the first point's coordinates, under its own name."""
    lines = text.splitlines()
    x, y, z = lines[1].split()[:3]
    return "\n".join([lines[0], *(" ".join([x, y, z, *ln.split()[3:]]) for ln in lines[1:])]) + "\n"


def heights_past_numbers(text: str) -> str:
    lines = text.splitlines()
    return (
        "\n".join([lines[0], *(" ".join([*ln.split()[:2], "1e308", *ln.split()[3:]]) for ln in lines[1:])])
        + "\n"
    )


def finite(value: Any) -> bool:
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, dict):
        return all(finite(v) for v in value.values())
    if isinstance(value, list):
        return all(finite(v) for v in value)
    return True


def reconstruct(c: httpx.Client, pid: str) -> dict[str, Any]:
    r = c.post(f"/v1/projects/{pid}/reconstruct", json={"mapper": "global"})
    assert r.status_code == 202, r.text
    return wait_job(c, r.json()["job_id"])


def test_gcps_that_cannot_georeference_keep_the_model_as_mapped_and_every_report_answers(
    dep: GrpcDeployment, scene: Path
) -> None:
    c = dep.client(dep.create_key("surveyor"))
    pid = str(c.post("/v1/projects", json={"name": "gcp <b>failures</b> | x"}).json()["id"])
    assert upload(c, pid, [scene / "images" / n for n in GROUND], "ground").status_code == 201
    good = good_file()
    gcp_path = dep.home / "projects" / pid / "gcp_list.txt"

    # the upload checks refuse the degenerate files now: both are 422 and nothing is stored
    for bad, why in ((coincident(good), "one point"), (heights_past_numbers(good), "usable points")):
        r = c.put(f"/v1/projects/{pid}/gcp", content=bad)
        assert r.status_code == 422 and why in r.json()["detail"], r.text
        assert not gcp_path.exists()
    r = c.put(f"/v1/projects/{pid}/gcp", content=clicks_that_do_not_meet(good))
    assert r.status_code == 200, r.text
    match = wait_job(c, c.post(f"/v1/projects/{pid}/match", json={"resize": 320}).json()["job_id"])
    assert match["state"] == "succeeded", (match, dep.logs())

    cases = [
        ("clicks that do not meet", None, "do not meet"),
        # as a file stored before the upload checks would lie on disk
        ("eight names at one coordinate", coincident(good), "one point"),
        ("heights past the range of numbers", heights_past_numbers(good), "usable points"),
    ]
    for case, text, why in cases:
        if text is not None:
            gcp_path.write_text(text)
        job = reconstruct(c, pid)
        assert job["state"] == "succeeded", (case, job, dep.logs())
        result = job["result"]
        g = result["gcp"]
        assert why in g.get("error", ""), (case, g)
        assert "SQL" not in json.dumps(job), case
        assert result["frame"] != "GCP" and "gps_frame_before_gcp" not in result, (case, result["frame"])
        assert all(isinstance(p, dict) and p["role"] == "unused" for p in g["points"]), (case, g["points"])
        assert finite(result), case

        scene_json = c.get(f"/v1/projects/{pid}/model", params={"format": "scene"})
        assert scene_json.status_code == 200, scene_json.text
        assert scene_json.json()["points"] > 0 and finite(scene_json.json()), case
        assert json.loads(c.get(f"/v1/projects/{pid}/model", params={"format": "json"}).text) == result

        report = c.get(f"/v1/projects/{pid}/report")
        assert report.status_code == 200 and report.json() == result["report"], (case, report.text)
        md = c.get(f"/v1/projects/{pid}/report", params={"format": "md"})
        assert md.status_code == 200, (case, md.text)
        assert "- not georeferenced by the GCPs: " in md.text, md.text
        rows = [ln for ln in md.text.splitlines() if ln.startswith("| gcp")]
        assert len(rows) == len(g["points"]), (case, md.text)
        assert md.text.startswith("# Survey report: gcp \\<b\\>failures\\</b\\> \\| x\n"), md.text[:200]
