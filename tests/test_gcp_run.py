"""``geomatch run --gcp``: the model comes out in the control points' frame, judged at check points
the fit never saw, on the small synthetic scene whose truth is exact (tests/small_scene.py), and a
GCP file the run cannot use stops it before any work with the reason."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from geomatch.cli import main
from geomatch.synth.aerial import Scene
from geomatch.synth.camera import Camera
from geomatch.synth.gcps import OFFSET, scene_gcps

from .small_scene import SEED, copy_of_run, run_options


def _cameras() -> list[Camera]:
    return Scene(SEED).cameras(2, 4, 640, 480)  # tests/small_scene.py's layout and size


@pytest.mark.pipeline
def test_the_model_is_written_in_the_gcps_frame_and_judged_at_the_check_points(
    small_run: Path, small_scene: Path, tmp_path: Path
) -> None:
    run_dir = copy_of_run(small_run, tmp_path / "run")
    cams = _cameras()
    text, truth = scene_gcps(Scene(SEED), cams, 7, seed=3)
    gcp = tmp_path / "gcp_list.txt"
    gcp.write_text(text)
    args = ["run", str(small_scene / "images"), "--out", str(run_dir), *run_options(small_scene)]
    assert main([*args, "--gcp", str(gcp), "--checkpoints", "2"]) == 0
    s = json.loads((run_dir / "summary.json").read_text())
    g = s["gcp"]
    assert "error" not in g and s["frame"] == "GCP" and s["georeferenced"]
    roles = [p["role"] for p in g["points"]]
    assert roles.count("check") == 2 and roles.count("control") >= 3
    # the aerial views see the ground at 2-5 cm a pixel (height over focal length): the check
    # points must come out within twice the coarser of those
    gsd = max(float(c.centre[2] / c.K[0, 0]) for c in cams if c.aerial)
    assert g["check_rmse_3d_m"] < 2 * gsd, g
    # the adjustment holding the control points may only bring the check points nearer
    assert g["bundle_adjusted"] and g["check_rmse_3d_m"] <= g["check_rmse_similarity_only_m"]["3d"] + 1e-3
    # the survey report carries the same numbers
    assert s["report"]["georeferencing"]["gcp"]["check_rmse_3d_m"] == g["check_rmse_3d_m"]
    # not only the report: the cameras as written, against where they truly stood
    rec = pycolmap.Reconstruction(str(run_dir / "sparse" / "0"))
    true_centre = {c.name: c.centre + OFFSET for c in cams}
    origin = np.asarray(g["origin"])
    errors = [
        np.linalg.norm(np.asarray(im.projection_center()) + origin - true_centre[im.name])
        for im in rec.images.values()
        if im.has_pose
    ]
    # (2+6 seed 2 of the sweep, mapped the same way: median 2.4 cm, the farthest ground camera 37 cm).
    # On this 2+4 scene the median sits at 2.0-2.2 GSD depending on the machine's float kernels
    # (the same tree and packages give 0.102 m on one CPU and passed under 2 GSD on another):
    # the bar is 2.5 GSD, and a camera the adjustment misplaces is metres off
    assert len(errors) == 6 and float(np.median(errors)) < 2.5 * gsd and max(errors) < 1.0, errors
    # every point is in the file's frame: the check points' truth is what the report compares with
    for p in g["points"]:
        if p["role"] == "check":
            assert p["3d_m"] < 2 * gsd and p["name"] in truth


@pytest.mark.unit
@pytest.mark.parametrize(
    ("content", "reason"),
    [
        ("EPSG:32632\n465000 5247000 408 10 10 a.png gcp00\n", "leaves 0 usable points"),
        ("EPSG:32632\n465000 5247000 408 10 10 a.png gcp00\n", "gcp00: seen in one photo only (line 2)"),
        ("NAD99 / nowhere\n465000 5247000 408 10 10 a.png gcp00\n", "line 1: unknown coordinate system"),
        ("EPSG:32632\n465000 5247000 408 10 10 missing.png gcp00\n", "line 2: gcp00: image 'missing.png'"),
        ("EPSG:32632\n465000 5247000 408 90 10 a.png gcp00\n", "pixel (90, 10) is outside a.png (64x48)"),
    ],
)
def test_a_gcp_file_the_run_cannot_use_stops_it_with_the_reason(
    content: str, reason: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    images = tmp_path / "images"
    images.mkdir()
    rng = np.random.default_rng(0)
    for name in ("a.png", "b.png"):
        cv2.imwrite(str(images / name), rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
    bad = tmp_path / "gcp_list.txt"
    bad.write_text(content)
    out = tmp_path / "o"
    assert main(["run", str(images), "--out", str(out), "--gcp", str(bad)]) == 2
    err = capsys.readouterr().err
    assert f"GCP file {bad}" in err and reason in err, err
    assert not (out / "database.db").exists()  # refused before any work


@pytest.mark.pipeline
def test_metre_level_control_is_weighed_at_metres_and_leaves_the_clicks_meeting(
    small_run: Path, small_scene: Path, tmp_path: Path
) -> None:
    """Control surveyed to 1.5 m per axis (a handheld fix) on the scene the matcher mapped: the
    adjustment weighs it at metres (the estimate from its residuals), every check point is still
    judged with its clicks meeting, and the check points come out no worse than the similarity
    alone placed them."""
    run_dir = copy_of_run(small_run, tmp_path / "run")
    text, _ = scene_gcps(Scene(SEED), _cameras(), 7, seed=3, noise_m=1.5)
    gcp = tmp_path / "gcp_list.txt"
    gcp.write_text(text)
    args = ["run", str(small_scene / "images"), "--out", str(run_dir)]
    args += run_options(small_scene)
    assert main([*args, "--gcp", str(gcp), "--checkpoints", "2"]) == 0
    g = json.loads((run_dir / "summary.json").read_text())["gcp"]
    check = [p for p in g["points"] if p["role"] == "check"]
    assert len(check) == 2 and all(p["reprojection_px"] < 2.0 for p in check), check
    assert g["accuracy_m"]["source"] == "estimated" and g["accuracy_m"]["horizontal"] > 0.3, g["accuracy_m"]
    assert g["check_rmse_3d_m"] <= 1.02 * g["check_rmse_similarity_only_m"]["3d"] + 0.01, g
