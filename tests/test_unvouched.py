"""Cameras a model's own pairs do not vouch for (modelagree.unvouched), and a photo localized
against them: it is not localized unless the other cameras place it on their own, since it sits
wherever they sit, right or not (geomatch/localize/answer.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from geomatch.localize import LocalizeOptions, Project, judge
from geomatch.localize.localizer import unvouched_cameras
from geomatch.sfm.absolute import Correspondences, estimate_pose
from geomatch.sfm.modelagree import agreement, unvouched

from .colmap_synthetic import synthetic_database
from .test_absolute import _scene
from .test_modelagree import _block_turned, _model, _pairs

pytestmark = pytest.mark.unit


def test_the_true_model_vouches_for_every_camera() -> None:
    rec = _model()
    rots, inl = _pairs(rec)
    assert unvouched(rec, rots, inl) == []


def test_a_block_held_only_within_itself_is_not_vouched_for_though_it_contradicts_little() -> None:
    rec = _model()
    rots, inl = _pairs(rec)
    block = [2, 5]
    names = {rec.images[i].name for i in block}
    # the block's ties to the rest: one weak pair each, far under what misplaced_blocks takes out
    weak = {p: (10 if (p[0] in names) != (p[1] in names) else n) for p, n in inl.items()}
    bad = _block_turned(rec, block, 31.0)
    assert agreement(bad, rots, weak).clean  # the attempts' test passes such a model
    assert unvouched(bad, rots, weak) == sorted(names)
    # right, the same ties hold it
    assert unvouched(rec, rots, weak) == []


def test_localize_reads_which_cameras_the_projects_pairs_vouch_for(tmp_path: Path) -> None:
    rec = synthetic_database(tmp_path / "database.db", 6, 200)
    project = Project(tmp_path / "database.db", tmp_path, tmp_path, {})
    assert unvouched_cameras(project, rec) == frozenset()
    ids = sorted(rec.images)
    bad = _block_turned(rec, [ids[1], ids[4]], 60.0)
    assert unvouched_cameras(project, bad) == {rec.images[ids[1]].name, rec.images[ids[4]].name}


def test_a_photo_placed_against_unvouched_cameras_alone_is_not_localized() -> None:
    camera, _, world, xy = _scene(n=400)
    opts = LocalizeOptions()
    pose = estimate_pose(xy, world, camera, 4.0, estimate_focal=False)
    corr = Correspondences(xy, np.arange(400), ["a", "b"] * 200)
    assert judge("p.png", pose, corr, opts, ["a", "b"]).confidence == "high"
    doubtful = judge("p.png", pose, corr, opts, ["a", "b"], unvouched={"a", "b"})
    assert not doubtful.localized and doubtful.confidence == "none"
    assert doubtful.reason is not None and "vouch" in doubtful.reason and "a, b" in doubtful.reason
    # one vouched camera places it on its own: localized, but one image is never "high"
    half = judge("p.png", pose, corr, opts, ["a", "b"], unvouched={"b"})
    assert half.localized and half.confidence == "low"
    # a vouched camera with too few inliers of its own does not carry it
    few = Correspondences(xy, np.arange(400), ["a"] * 20 + ["b"] * 380)
    assert not judge("p.png", pose, few, opts, ["a", "b"], unvouched={"b"}).localized
