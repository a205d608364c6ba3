"""End to end, as a user runs it: render a small air-to-ground scene, ``geomatch run``, ``geomatch eval``.

Real networks, real pycolmap; the scene is small (2 aerial + 4 ground, 640x480) so CI stays fast,
but every aerial x ground pair is tiled exactly as in a full run. The run is the session's one run
of that scene (tests/small_scene.py, tests/conftest.py's ``small_run``), copied once here: the
evaluation writes into the folder and the re-run maps it again.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from geomatch.cli import main

from .small_scene import PAIRS, copy_of_run, run_options


@pytest.fixture(scope="module")
def scene(small_scene: Path) -> Path:
    return small_scene


@pytest.fixture(scope="module")
def run_dir(small_run: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return copy_of_run(small_run, tmp_path_factory.mktemp("e2e") / "run")


@pytest.mark.pipeline
def test_every_image_is_registered(run_dir, scene) -> None:
    s = json.loads((run_dir / "summary.json").read_text())
    assert s["registered"] == s["images"] == 6, s
    assert s["tiled_pairs"] == 4 and s["pairs"] == len(PAIRS) == 11
    # a project with tiled pairs keeps the points only two images see (sfm/mapping.py): 2718
    # points, track length 2.39, reprojection error 0.31 px; bounds at about 1.4 times below
    # (points), 0.25 under (track length) and over 2 times (error)
    assert s["mean_track_length"] >= 2.1 and s["points3D"] > 1900, s
    assert s["mean_reprojection_error"] < 0.7
    # the loop check saw the graph (pairs with a rotation, loops among them) and said what it dropped;
    # 9 pairs and 3 loops here: the two pairs of the 11 matched whose matches verified no geometry
    # (aerial x ground pairs that share little) are not in it
    vg = s["view_graph"]
    assert vg["pairs"] >= 8 and vg["loops"] >= 2 and isinstance(vg["dropped"], list), vg
    # a tiled project's model is held to its kept pairs' rotations (sfm/modelagree.py): this one,
    # right by the ground truth (test_eval_against_ground_truth), holds at least 90 % of their inliers
    agree = s["pair_agreement"]
    assert agree["held"] > 0 and agree["contradicted"] <= 0.1 * (agree["held"] + agree["contradicted"]), agree
    assert 1 <= s["mapping_attempts"] <= 4 and isinstance(s["placed_from_pairs"], list)
    # every camera of the right model is held by its pairs to the rest: none left out for that
    assert s["unvouched_left_out"] == []


@pytest.mark.pipeline
def test_outputs_open_in_colmap_formats(run_dir) -> None:
    model = run_dir / "sparse" / "0"
    for f in ("cameras", "images", "points3D"):
        assert (model / f"{f}.bin").is_file() and (model / f"{f}.txt").is_file()
    rec = pycolmap.Reconstruction(str(model))
    s = json.loads((run_dir / "summary.json").read_text())
    assert rec.num_reg_images() == s["registered"] >= 2
    assert rec.num_points3D() == s["points3D"] > 0
    header = (run_dir / "points.ply").read_bytes()[:200]
    assert header.startswith(b"ply") and f"element vertex {rec.num_points3D()}".encode() in header
    db = pycolmap.Database.open(str(run_dir / "database.db"))
    try:
        assert db.num_images() == 6 and db.num_verified_image_pairs() == db.num_matched_image_pairs() >= 10
        assert db.num_cameras() == 2  # one per device: the drone and the handheld camera of the EXIF
    finally:
        db.close()


@pytest.mark.pipeline
def test_eval_against_ground_truth(run_dir, scene, capsys) -> None:
    assert main(["eval", str(run_dir), "--gt", str(scene / "gt")]) == 0
    printed = capsys.readouterr().out
    m = json.loads((run_dir / "eval.json").read_text())
    assert "AUC@3 deg" in printed and f"{m['registered']}/6" in printed
    assert 0.0 <= m["auc@3"] <= m["auc@5"] <= m["auc@10"] <= 100.0
    # registered and right: the poses agree with the ground truth, not just with each other
    # (spread over tests/small_scene.py's 9 mappings: AUC@5 95.3-96.9; bound 5 below the worst,
    # over 3 times the range)
    assert m["auc@5"] > 90.0, m


@pytest.mark.pipeline
def test_rerun_resumes_without_matching_again(run_dir, scene) -> None:
    before = pycolmap.Database.open(str(run_dir / "database.db"))
    try:
        kp_before = {
            im.image_id: before.num_keypoints_for_image(im.image_id) for im in before.read_all_images()
        }
        before_pairs = before.num_matched_image_pairs()
    finally:
        before.close()
    args = ["run", str(scene / "images"), "--out", str(run_dir)]
    assert main([*args, *run_options(scene)]) == 0
    s = json.loads((run_dir / "summary.json").read_text())
    assert s["pairs_matched_now"] == 0
    after = pycolmap.Database.open(str(run_dir / "database.db"))
    try:
        assert {
            im.image_id: after.num_keypoints_for_image(im.image_id) for im in after.read_all_images()
        } == kp_before
        assert after.num_matched_image_pairs() == before_pairs
    finally:
        after.close()


@pytest.mark.unit
def test_run_rejects_bad_input(tmp_path, capsys) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["run", str(empty), "--out", str(tmp_path / "o")]) == 2
    assert "need at least 2" in capsys.readouterr().err
    assert main(["run", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    for i in range(2):
        (imgs / f"{i}.png").write_bytes(np.zeros(10, np.uint8).tobytes())  # not images
    assert main(["run", str(imgs), "--out", str(tmp_path / "o2"), "--pairs", "nearest:3"]) == 2
    assert "bad pair spec" in capsys.readouterr().err
    assert main(["run", str(imgs), "--out", str(tmp_path / "o3")]) == 2
    assert "not a readable image" in capsys.readouterr().err
    assert not (tmp_path / "o3" / "database.db").exists()  # nothing half-written
