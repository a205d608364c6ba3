"""Up as the photos know it (geomatch.sfm.upright) narrows a pair's candidate rotations, so a
survey's second family of rotations no longer turns the view graph against right pairs."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from geomatch.metadata import ImageMeta, up_in_camera
from geomatch.sfm.upright import NADIR_UP, image_up, up_error_deg, upright_candidates
from geomatch.sfm.viewgraph import judge

pytestmark = pytest.mark.unit

# cam_from_world of a nadir camera heading north: world up (z) is -z in the camera
NADIR = np.diag([1.0, -1.0, -1.0])


def _about(axis: str, deg: float) -> np.ndarray:
    return Rotation.from_euler(axis, deg, degrees=True).as_matrix()


def _nadir_survey(
    n: int, seed: int
) -> tuple[dict[tuple[int, int], list[np.ndarray]], dict[tuple[int, int], int]]:
    """Nadir photos along a line, headings turning, each pair of neighbours and next neighbours
    verified with its right rotation (0.5 deg of noise) and a second one of a consistent family
    that tilts photo i by 15 deg x i, exact, so it closes every triangle tighter than the right
    family does; (0, n-1) admits its right rotation only."""
    rng = np.random.default_rng(seed)
    world = [_about("z", float(rng.uniform(-180, 180))) @ NADIR for _ in range(n)]
    twin = [_about("x", 15.0 * i) @ world[i] for i in range(n)]
    edges: dict[tuple[int, int], list[np.ndarray]] = {}
    support: dict[tuple[int, int], int] = {}
    for i in range(n):
        for j in (i + 1, i + 2):
            if j < n:
                noise = Rotation.from_rotvec(np.radians(0.5) * rng.normal(size=3) / np.sqrt(3)).as_matrix()
                edges[(i, j)] = [noise @ world[j] @ world[i].T, twin[j] @ twin[i].T]
                support[(i, j)] = 1000
    edges[(0, n - 1)] = [world[n - 1] @ world[0].T]
    support[(0, n - 1)] = 900
    return edges, support


def test_a_survey_pair_keeps_the_rotation_that_carries_up_and_the_second_family_goes() -> None:
    edges, support = _nadir_survey(5, seed=3)
    names = {i: f"img{i}" for i in range(5)}
    # every pair is right (its first candidate), yet the tie-break chains the second family and
    # the tree check turns right pairs against it
    assert judge(edges, support)[0]
    up = dict.fromkeys(names.values(), NADIR_UP)
    narrowed = upright_candidates(edges, names, up)
    assert all(len(c) == 1 for c in narrowed.values())
    tree_drop, loop_drop, _ = judge(narrowed, support)
    assert tree_drop == [] and loop_drop == []


def test_pairs_without_up_on_both_sides_keep_every_candidate_and_none_is_left_empty() -> None:
    edges, _ = _nadir_survey(4, seed=1)
    names = {i: f"img{i}" for i in range(4)}
    only_some = upright_candidates(edges, names, {"img0": NADIR_UP, "img1": NADIR_UP})
    assert len(only_some[(0, 1)]) == 1
    assert all(len(only_some[e]) == len(edges[e]) for e in edges if e != (0, 1))
    # a pair whose every candidate tilts far still keeps its best one
    far = {(0, 1): [_about("x", 40.0), _about("x", 70.0)]}
    assert len(upright_candidates(far, names, {"img0": NADIR_UP, "img1": NADIR_UP})[(0, 1)]) == 1


def test_up_comes_from_the_gimbal_and_a_survey_without_one_is_nadir() -> None:
    dji = ImageMeta(4000, 3000, gimbal_pitch_deg=-45.0, gimbal_roll_deg=0.0, gimbal_yaw_deg=10.0)
    compact = ImageMeta(4000, 3000)
    pitched_no_roll = ImageMeta(4000, 3000, gimbal_pitch_deg=-45.0)
    up = image_up({"dji": dji, "compact": compact, "pitched": pitched_no_roll}, survey=True)
    assert np.allclose(up["dji"], up_in_camera(dji))
    assert np.allclose(up["compact"], NADIR_UP)
    assert "pitched" not in up  # pitched off nadir with no roll: up is not known well enough
    assert "compact" not in image_up({"compact": compact}, survey=False)


def test_the_up_error_of_a_pure_heading_change_is_zero_and_a_tilt_shows() -> None:
    R = _about("z", 130.0)  # a turn about the optical axis keeps a nadir camera's up
    assert up_error_deg(R, NADIR_UP, NADIR_UP) == pytest.approx(0.0, abs=1e-6)
    assert up_error_deg(_about("x", 25.0) @ R, NADIR_UP, NADIR_UP) == pytest.approx(25.0, abs=1e-6)
