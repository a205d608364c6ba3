"""Localizing new photos against a project's model (geomatch/localize/), on the session's run of
the small scene (tests/small_scene.py: 2 aerial + 4 ground, georeferenced from three fixes).

The photo left out is ``ground_02.png`` (it has a GPS fix, so the GPS candidates and the WGS84
answer are exercised): the model without it is the run's model with its frame deregistered
(geomatch/eval/leaveout.py). One matcher (the run's settings) serves every test, so the model
images' features are computed once.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
import pytest
from PIL import Image

from geomatch.eval.leaveout import pose_error, without_image
from geomatch.geo.geodesy import EnuFrame
from geomatch.localize import Localization, Project, localize_photos, project_matcher
from geomatch.synth.photos import photo

from .small_scene import copy_of_run

pytestmark = pytest.mark.pipeline

LEFT_OUT = "ground_02.png"
ROOT = Path(__file__).resolve().parents[1]
GEO_TOLERANCE_M = 2.0


@pytest.fixture(scope="module")
def run_matcher(small_run: Path) -> Any:
    return project_matcher(Project.find(small_run))


@pytest.fixture(scope="module")
def other_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A photo of something else entirely (scikit-image's coffee cup), at the scene's size."""
    path = tmp_path_factory.mktemp("other") / "coffee.png"
    Image.fromarray(photo("coffee")).resize((640, 480)).save(path)
    return path


@pytest.fixture(scope="module")
def reduced(small_run: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return without_image(small_run / "sparse" / "0", LEFT_OUT, tmp_path_factory.mktemp("loo") / "model")


@pytest.fixture(scope="module")
def answers(
    small_run: Path, small_scene: Path, reduced: Path, other_scene: Path, run_matcher: Any
) -> list[Localization]:
    calls: list[tuple[int, int]] = []
    out = localize_photos(
        small_run,
        [small_scene / "images" / LEFT_OUT, other_scene],
        matcher=run_matcher,
        model_dir=reduced,
        progress=lambda done, total: calls.append((done, total)),
    )
    assert calls == [(1, 2), (2, 2)]
    return out


def test_left_out_photo_is_localized(answers: list[Localization], reduced: Path, small_scene: Path) -> None:
    loc = answers[0]
    assert loc.name == LEFT_OUT
    assert loc.localized and loc.reason is None, loc
    assert loc.confidence == "high", loc
    assert loc.cam_from_world is not None and loc.center is not None
    w, x, y, z = loc.cam_from_world["qvec"]
    R = pycolmap.Rotation3d(np.array([x, y, z, w])).matrix()
    err = pose_error(
        pycolmap.Reconstruction(str(reduced)),
        pycolmap.Reconstruction(str(small_scene / "gt")),
        LEFT_OUT,
        R,
        np.array(loc.center),
    )
    assert err is not None
    rotation_deg, _, percent_of_extent = err
    assert rotation_deg <= 1.0 and percent_of_extent <= 1.0, err
    assert len(loc.supporting_images) >= 2
    assert loc.camera is not None and loc.camera["width"] == 640
    # the model is georeferenced: the answer is on the globe, near the photo's true position
    assert loc.wgs84 is not None
    truth = json.loads((small_scene / "gt" / "gps.json").read_text())
    frame = EnuFrame(**truth["origin"])
    where = frame.from_geodetic(loc.wgs84["lat"], loc.wgs84["lon"], loc.wgs84["alt"])
    # the model is placed by three fixes of 0.5 m noise: its frame is off by about that much
    assert np.linalg.norm(where - np.array(truth["true_enu"][LEFT_OUT])) < GEO_TOLERANCE_M
    assert 0.0 <= loc.wgs84["heading_deg"] < 360.0


def test_the_model_images_features_come_from_the_runs_folder(
    answers: list[Localization], run_matcher: Any, small_run: Path
) -> None:
    """``geomatch localize`` runs in a process of its own, after the run: the model images' features
    are read from the run's folder (extracting them again was most of a cold photo's time), and the
    folder is not written to (the session's check of ``small_run`` sees every file time)."""
    store = run_matcher.store
    assert store.root == small_run / "features" and not store.writable
    assert store.hits >= 3, store.hits  # retrieval reads every model image, matching its candidates


def test_other_scene_is_not_localized(answers: list[Localization]) -> None:
    loc = answers[1]
    assert loc.name == "coffee.png"
    assert not loc.localized and loc.confidence == "none"
    assert loc.reason and "does not seem to show this scene" in loc.reason
    assert loc.cam_from_world is None and loc.center is None and loc.wgs84 is None
    json.dumps(loc.to_json())  # every field is plain JSON


def test_cli_json(small_run: Path, small_scene: Path, other_scene: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "2"}
    res = subprocess.run(
        [sys.executable, "-m", "geomatch.cli", "localize", str(small_run), str(other_scene), "--json"],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
        timeout=600,
    )
    assert res.returncode == 0, res.stderr[-2000:]
    doc = json.loads(res.stdout)
    assert doc["total"] == 1 and doc["localized"] == 0
    assert doc["photos"][0]["name"] == "coffee.png" and doc["photos"][0]["reason"]


def test_add_writes_the_photo_and_its_matches_once(
    small_run: Path, small_scene: Path, reduced: Path, run_matcher: Any, tmp_path: Path
) -> None:
    run = copy_of_run(small_run, tmp_path / "run")
    images = tmp_path / "images"  # the project's images, without the photo to add
    images.mkdir()
    for p in (small_scene / "images").iterdir():
        if p.name != LEFT_OUT:
            (images / p.name).write_bytes(p.read_bytes())
    # the run's database holds the photo already: start from one without it
    db_path = run / "database.db"
    db = pycolmap.Database.open(str(db_path))
    try:
        before_images = {im.name for im in db.read_all_images()}
    finally:
        db.close()
    assert LEFT_OUT in before_images
    fresh = tmp_path / "photo" / "new_view.png"
    fresh.parent.mkdir()
    fresh.write_bytes((small_scene / "images" / LEFT_OUT).read_bytes())

    def state() -> tuple[int, int, int, int]:
        d = pycolmap.Database.open(str(db_path))
        try:
            image = d.read_image_with_name("new_view.png")
            pairs = [
                pycolmap.pair_id_to_image_pair(p)
                for p in d.read_all_matches()[0]
                if image.image_id in pycolmap.pair_id_to_image_pair(p)
            ]
            return int(d.num_images()), len(pairs), int(d.num_keypoints()), int(d.num_matches())
        finally:
            d.close()

    kwargs: dict[str, Any] = {"matcher": run_matcher, "model_dir": reduced, "images_dir": images, "add": True}
    [first] = localize_photos(run, [fresh], **kwargs)
    assert first.localized
    after = state()
    assert after[0] == len(before_images) + 1
    assert 2 <= after[1] <= len(first.candidates)  # its matches to the model images it was matched with
    assert (images / "new_view.png").read_bytes() == fresh.read_bytes()
    [again] = localize_photos(run, [fresh], **kwargs)
    assert again.localized
    assert state() == after  # nothing written twice
