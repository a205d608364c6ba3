"""`geomatch run` and the service run one orchestration: a small mixed project (one aerial photo,
three street-level ones) matched and mapped both ways gets the same plan, the same mapper settings
and a summary with the same fields, with tiling off and with the defaults, and with a PnP minimum
of its own (`--min-pose-inliers`, the service's `min_pose_inliers`)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import pytest

from geomatch.pipeline import RunOptions, run
from geomatch.pipeline.summary import JOB_FIELDS, RUN_FIELDS

from .harness import Deployment, upload, wait_job

pytestmark = pytest.mark.service

AERIAL = ["aerial_00.png"]
GROUND = ["ground_00.png", "ground_01.png", "ground_02.png"]
# the service is under test here, not the matcher: the sparse method at 320 px keeps both runs short
MATCHING = {"method": "sparse", "resize": 320}
ALIGNED = {"frame", "origin", "ecef_from_enu", "vertical", "alignment"}  # georef.summary_fields


def served(d: Deployment, key: str, scene: Path, tiling: str, **options: Any) -> tuple[dict[str, Any], Path]:
    """The reconstruct job's summary of the project matched through the service (``options``: more
    of the match body's), and its folder."""
    with d.client(key) as c:
        pid = c.post("/v1/projects", json={"name": f"parity-{tiling}"}).json()["id"]
        assert upload(c, pid, [scene / "images" / n for n in AERIAL], "aerial").status_code == 201
        assert upload(c, pid, [scene / "images" / n for n in GROUND], "ground").status_code == 201
        body = {**MATCHING, "tiling": tiling, **options, "reconstruct": True}
        accepted = c.post(f"/v1/projects/{pid}/match", json=body).json()
        match = wait_job(c, accepted["job_id"])
        assert match["state"] == "succeeded", (match, d.logs())
        recon = wait_job(c, accepted["reconstruct_job_id"])
        assert recon["state"] == "succeeded", (recon, d.logs())
        return dict(recon["result"]), d.home / "projects" / pid


def ran(scene: Path, out: Path, tiling: str, **options: Any) -> dict[str, Any]:
    images = out.parent / f"images-{tiling}"
    images.mkdir()
    for n in AERIAL + GROUND:
        shutil.copy(scene / "images" / n, images / n)
    opts = RunOptions(**MATCHING, tiling=tiling, aerial_names=AERIAL, progress=False, **options)
    return run(images, out, opts)


# tiling off with a PnP minimum of its own (below COLMAP's 30, so that the small scene still maps
# whatever it lets in), and the defaults
@pytest.mark.parametrize(("tiling", "pnp"), [("off", 12), ("auto", 0)])
def test_service_and_run_plan_and_map_alike(
    deployment: Deployment, key_a: str, scene: Path, tmp_path: Path, tiling: str, pnp: int
) -> None:
    given = {"min_pose_inliers": pnp} if pnp else {}
    by_run = ran(scene, tmp_path / "run", tiling, **given)
    by_service, project = served(deployment, key_a, scene, tiling, **given)
    assert by_run["mapping_settings"]["min_pose_inliers"] == pnp

    # tiling off: no pair tiled, and the mapper takes the plain project's settings both ways
    assert by_run["mapping_settings"]["tiled"] is (tiling != "off")
    assert by_service["mapping_settings"] == by_run["mapping_settings"]
    plan_fields = ("pairs", "pair_plan", "tiled_pairs", "aerial")  # plan.Plan.summary_fields
    assert {k: by_service[k] for k in plan_fields} == {k: by_run[k] for k in plan_fields}
    assert by_run["tiled_pairs"] == (0 if tiling == "off" else len(GROUND))
    plan_run = json.loads((tmp_path / "run" / "plan.json").read_text())
    plan_service = json.loads((project / "plan.json").read_text())
    assert plan_service == plan_run
    # the fields a client reads (the console, the report) are there both ways: all but the run's
    # own (its folder, options, pairs matched by this call) and the job's id; the frame's fields
    # come with a model of three or more cameras with fixes, and the mapper is not repeatable from
    # run to run, so where the two registered different photos those may differ
    aligned = set() if by_service["registered_names"] == by_run["registered_names"] else ALIGNED
    assert set(by_service) - JOB_FIELDS - aligned == set(by_run) - RUN_FIELDS - aligned
    assert set(by_service) >= JOB_FIELDS and set(by_run) >= RUN_FIELDS
    assert by_service["report"].keys() == by_run["report"].keys()
    if pnp:
        reconstruct_takes_its_own_pnp_minimum(deployment, key_a, project.name, by_run)


def test_a_mixed_project_matched_untiled_is_mapped_untiled(
    deployment: Deployment, key_a: str, scene: Path
) -> None:
    """The reconstruct job maps by what its match job planned: one aerial x ground pair matched with
    tiling off is no tiled pair, and the mapping gets the plain project's settings (it once decided
    "tiled" from the image kinds and the reconstruct job's own options, which never hold tiling)."""
    with deployment.client(key_a) as c:
        pid = c.post("/v1/projects", json={"name": "untiled"}).json()["id"]
        assert upload(c, pid, [scene / "images" / AERIAL[0]], "aerial").status_code == 201
        assert upload(c, pid, [scene / "images" / GROUND[0]], "ground").status_code == 201
        body = {**MATCHING, "tiling": "off", "pairs": [[AERIAL[0], GROUND[0]]], "reconstruct": True}
        accepted = c.post(f"/v1/projects/{pid}/match", json=body).json()
        recon = wait_job(c, accepted["reconstruct_job_id"])
    assert recon["state"] == "succeeded", (recon, deployment.logs())
    assert recon["result"]["mapping_settings"]["tiled"] is False


def reconstruct_takes_its_own_pnp_minimum(d: Deployment, key: str, pid: str, by_run: dict[str, Any]) -> None:
    """A reconstruct body's ``min_pose_inliers`` reaches its mapper; one outside the option's range
    is refused before any job is queued."""
    with d.client(key) as c:
        for bad in (2, 10001):
            r = c.post(f"/v1/projects/{pid}/reconstruct", json={"min_pose_inliers": bad})
            assert r.status_code == 422 and "min_pose_inliers must be 0 (auto" in r.text, r.text
        r = c.post("/v1/projects", json={"name": "bad pnp", "config": {"min_pose_inliers": 2}})
        assert r.status_code == 422 and "min_pose_inliers" in r.text, r.text
        r = c.post(f"/v1/projects/{pid}/reconstruct", json={"min_pose_inliers": 25})
        assert r.status_code == 202, r.text
        recon = wait_job(c, r.json()["job_id"])
    assert recon["state"] == "succeeded", (recon, d.logs())
    assert recon["options"]["min_pose_inliers"] == 25
    assert recon["result"]["mapping_settings"] == {**by_run["mapping_settings"], "min_pose_inliers": 25}
