"""The view graph's loop check (geomatch.sfm.viewgraph): wrong pairs go, right ones stay."""

from __future__ import annotations

from contextlib import closing
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from geomatch.sfm.viewgraph import (
    inconsistent_pairs,
    judge,
    loop_error,
    rotation_angle,
    spanning_tree,
    tree_inconsistent_pairs,
)

pytestmark = pytest.mark.unit


def _graph(
    n: int, seed: int, noise_deg: float = 0.5
) -> tuple[list[np.ndarray], dict[tuple[int, int], list[np.ndarray]], np.random.Generator]:
    rng = np.random.default_rng(seed)
    world = [Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix() for _ in range(n)]
    edges: dict[tuple[int, int], list[np.ndarray]] = {}
    for i in range(n):
        for j in range(i + 1, n):
            wobble = Rotation.from_rotvec(np.radians(noise_deg) * rng.normal(size=3) / np.sqrt(3)).as_matrix()
            edges[(i, j)] = [wobble @ world[j] @ world[i].T]
    return world, edges, rng


def test_wrong_pairs_are_dropped_and_right_ones_kept() -> None:
    _, edges, rng = _graph(8, seed=0)
    wrong = [(0, 3), (2, 5), (4, 7)]
    for e in wrong:
        edges[e] = [Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()]
    # a right pair whose estimators also proposed a wrong solution (as a homography's
    # decompositions do) is still right: some choice of candidates closes its loops
    edges[(1, 2)].append(Rotation.from_euler("x", 80, degrees=True).as_matrix() @ edges[(1, 2)][0])
    dropped, loops = inconsistent_pairs(edges)
    assert loops == 56  # C(8, 3)
    assert sorted(e for e, _, _ in dropped) == wrong
    for _, bad, n in dropped:
        assert bad > n - bad


def test_ties_go_against_the_weaker_pair_and_an_image_keeps_two_pairs() -> None:
    """Image 0's pairs with 2 and 3 are wrong: every loop through 0 breaks, the right pair
    (0, 1)'s too, so the loops cannot tell its three pairs apart. The one with the fewest inliers
    goes first; then 0 is down to two pairs, which it keeps."""
    _, edges, rng = _graph(4, seed=3)
    for e in ((0, 2), (0, 3)):
        edges[e] = [Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()]
    support = {e: 500 for e in edges} | {(0, 2): 40, (0, 3): 60}
    dropped, loops = inconsistent_pairs(edges, support=support)
    assert loops == 4
    assert [e for e, _, _ in dropped] == [(0, 2)]
    support[(0, 2)], support[(0, 3)] = 60, 40
    assert [e for e, _, _ in inconsistent_pairs(edges, support=support)[0]] == [(0, 3)]


def test_a_pair_in_no_loop_is_kept_and_an_empty_graph_is_fine() -> None:
    _, edges, rng = _graph(4, seed=1)
    hanging = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
    edges[(3, 9)] = [hanging]  # image 9 is seen by one pair only: nothing can contradict it
    dropped, _ = inconsistent_pairs(edges)
    assert dropped == []
    assert inconsistent_pairs({}) == ([], 0)


def test_noise_below_the_tolerance_breaks_nothing_and_a_large_error_does() -> None:
    _, edges, _ = _graph(6, seed=2, noise_deg=1.5)
    assert inconsistent_pairs(edges)[0] == []
    a, b, c = edges[(0, 1)], edges[(1, 2)], edges[(0, 2)]
    assert loop_error(a, b, c) < 5.0
    turned = [Rotation.from_euler("z", 20, degrees=True).as_matrix() @ c[0]]
    assert 15.0 < loop_error(a, b, turned) < 25.0
    assert rotation_angle(np.eye(3)) == 0.0


def test_one_broken_loop_blames_its_weakest_pair() -> None:
    """(1, 2) is 8 deg off with 60 inliers, and (1, 5) agrees with its error, so one of (1, 2)'s
    three loops holds. The strong right pair (0, 1) has a single loop, (0, 1, 2), broken by (1, 2):
    one broken loop cannot say which of its pairs is wrong, so it goes against the weakest pair
    in it and (0, 1) stays (the e2e scene, seed 1, lost an aerial camera to the opposite choice)."""
    world, _, _ = _graph(6, seed=4, noise_deg=0.0)

    def rel(i: int, j: int) -> np.ndarray:
        return world[j] @ world[i].T

    edges = {e: [rel(*e)] for e in ((0, 1), (0, 2), (0, 3), (1, 4), (2, 3), (2, 4), (2, 5))}
    edges[(1, 2)] = [Rotation.from_euler("y", 8, degrees=True).as_matrix() @ rel(1, 2)]
    edges[(1, 5)] = [rel(2, 5) @ edges[(1, 2)][0]]  # closes the loop (1, 2, 5) with the wrong (1, 2)
    support = {e: 500 for e in edges} | {(1, 2): 60, (0, 1): 400}
    dropped, loops = inconsistent_pairs(edges, support=support)
    assert loops == 4
    assert [e for e, _, _ in dropped] == [(1, 2)]


def _mirrored_courtyard(
    n: int = 12,
) -> tuple[dict[tuple[int, int], list[np.ndarray]], dict[tuple[int, int], int]]:
    """Cameras on a circle looking outwards at the walls of a courtyard whose opposite walls look
    alike: every neighbour pair is right and strong, and every pair of views of opposite walls is
    matched as if they faced the same wall (relative rotation: identity instead of 180 deg yaw),
    weakly but consistently, so the triangles these wrong pairs form with each other close."""
    world = [Rotation.from_euler("y", 360.0 * i / n, degrees=True).as_matrix() for i in range(n)]
    edges: dict[tuple[int, int], list[np.ndarray]] = {}
    support: dict[tuple[int, int], int] = {}
    for i in range(n):
        for j in range(i + 1, n):
            gap = min(j - i, n - (j - i))
            if gap <= 2:  # overlapping neighbours
                edges[(i, j)] = [world[j] @ world[i].T]
                support[(i, j)] = 1500 - 400 * gap
            elif abs(gap - n // 2) <= 1:  # look-alike opposite walls: turned by 180 deg
                edges[(i, j)] = [
                    Rotation.from_euler("y", 180.0, degrees=True).as_matrix() @ world[j] @ world[i].T
                ]
                support[(i, j)] = 200
    return edges, support


def test_look_alike_opposite_walls_pass_the_loops_but_not_the_tree() -> None:
    """The trap of repeated structure: the wrong pairs agree with each other, so the triangle
    check keeps most of them; the tree of the strongest pairs (the neighbours) drops all of them
    and keeps every right pair."""
    edges, support = _mirrored_courtyard()
    wrong = {e for e, s in support.items() if s == 200}
    kept_by_loops = wrong - {e for e, _, _ in inconsistent_pairs(edges, support=support)[0]}
    assert kept_by_loops, "the scene no longer fools the loop check: it tests nothing"
    dropped = tree_inconsistent_pairs(edges, support)
    assert {e for e, _, _ in dropped} == wrong
    assert all(deg > 170 for _, deg, _ in dropped)


def test_the_tree_tolerates_drift_and_ignores_a_forest_edge() -> None:
    """Small errors on every pair add up along tree paths; the bound grows with the path, so a
    right pair far along the tree stays. Two components (no pair between them) judge nothing
    across."""
    edges, support = _mirrored_courtyard()
    edges = {e: r for e, r in edges.items() if support[e] != 200}
    rng = np.random.default_rng(0)
    noisy = {
        e: [Rotation.from_rotvec(np.radians(0.8) * rng.normal(size=3)).as_matrix() @ r[0]]
        for e, r in edges.items()
    }
    assert tree_inconsistent_pairs(noisy, support) == []
    assert tree_inconsistent_pairs({(0, 1): [np.eye(3)], (5, 6): [np.eye(3)]}, {}) == []
    assert tree_inconsistent_pairs({}, {}) == []


def test_a_tree_pair_takes_the_candidate_its_triangles_vote_for() -> None:
    """A flat scene's pair admits several rotations (homography decompositions); the tree must
    chain the one that closes its loops, else every image behind it turns and its right pairs go."""
    edges, support = _mirrored_courtyard()
    edges = {e: r for e, r in edges.items() if support[e] != 200}
    wrong_first = Rotation.from_euler("x", 60, degrees=True).as_matrix() @ edges[(0, 1)][0]
    edges[(0, 1)] = [wrong_first, edges[(0, 1)][0]]
    assert tree_inconsistent_pairs(edges, support) == []


def test_the_loop_check_never_drops_a_pair_of_the_spanning_tree() -> None:
    """Image 0's pairs with 2-5 are look-alike pairs that agree with each other (as if 0 were
    turned), so the loops among them hold and every loop through its one right pair, with 1,
    breaks: the loop check alone drops that pair (a 722-inlier neighbour pair on a repeated
    courtyard, which left seven cameras attached by a wrong pair). With the spanning tree's pairs
    kept it stays, and the tree check drops the look-alike ones."""
    world, edges, _ = _graph(6, seed=5)
    turned = Rotation.from_euler("y", 150, degrees=True).as_matrix() @ world[0]
    wrong = [(0, 2), (0, 3), (0, 4), (0, 5)]
    for _, j in wrong:
        edges[(0, j)] = [world[j] @ turned.T]
    support = {e: 900 for e in edges} | dict.fromkeys(wrong, 150) | {(0, 1): 1200}
    alone = [e for e, _, _ in inconsistent_pairs(edges, support=support)[0]]
    assert (0, 1) in alone
    tree = set(spanning_tree(edges, support))
    assert (0, 1) in tree
    assert (0, 1) not in [e for e, _, _ in inconsistent_pairs(edges, support=support, keep=tree)[0]]
    # all but one: image 0 keeps two pairs
    tree_dropped = [e for e, _, _ in tree_inconsistent_pairs(edges, support)]
    assert len(tree_dropped) == 3 and set(tree_dropped) <= set(wrong)


def _turn(deg: float, axis: str = "x") -> np.ndarray:
    return Rotation.from_euler(axis, deg, degrees=True).as_matrix()


def test_a_tree_pair_trusts_the_triangles_of_strong_pairs_over_those_of_weak_ones() -> None:
    """Tree pair (0, 1) admits its right rotation and one 30 deg off. The right one closes a
    triangle with two strong right pairs (through 2, 2 deg of noise); the wrong one closes a
    triangle, exactly, with a weak wrong pair (through 3). Counted alike the wrong one wins on
    closing error and turns image 1, so its right 400-inlier pair goes (as a ground pair's
    homography did on the service tests' aerial scene); counted by their pairs' inliers the right
    one wins and only the weak wrong pair goes."""
    _, edges, _ = _graph(4, seed=3, noise_deg=0.0)
    right = edges[(0, 1)][0]
    wrong = _turn(30) @ right
    edges[(0, 1)] = [wrong, right]
    edges[(1, 2)] = [_turn(2, "z") @ edges[(1, 2)][0]]
    edges[(1, 3)] = [edges[(0, 3)][0] @ wrong.T]  # closes 0-1-3 with the wrong rotation
    support = {(0, 1): 1000, (0, 2): 400, (1, 2): 400, (0, 3): 50, (1, 3): 50, (2, 3): 300}
    dropped = tree_inconsistent_pairs(edges, support)
    assert [e for e, _, _ in dropped] == [(1, 3)]
    assert dropped[0][1] == pytest.approx(30, abs=1)


def test_a_strong_right_pair_survives_loops_through_weaker_pairs_the_tree_dropped() -> None:
    """Images 4 and 5 are matched right to each other and to two images each, and wrongly (as if
    turned, so the wrong pairs agree with each other) to the two others, as an aerial image with
    its ground views on a repeated site. Every loop through the right pair (4, 5) runs through one
    wrong pair: counting them it has all its loops broken and goes; the loop check counts a loop
    through a pair the tree check dropped only against weaker pairs, so it stays."""
    world, edges, _ = _graph(6, seed=7)
    support = {e: 800 for e in edges} | {(4, 5): 900}
    wrong = [(2, 4), (3, 4), (0, 5), (1, 5)]
    for a, b in wrong:
        turned = _turn(120, "y") @ world[b]
        edges[(a, b)] = [turned @ world[a].T]
        support[(a, b)] = 40
    tree_drop, loop_drop, _ = judge(edges, support)
    assert {e for e, _, _ in tree_drop} == set(wrong)
    assert loop_drop == []
    with_them = inconsistent_pairs(edges, support=support, keep={(0, 1), (0, 2), (0, 3), (0, 4), (2, 5)})
    assert (4, 5) in {e for e, _, _ in with_them[0]}, "the scene no longer shows the trap"


def test_loops_through_judged_pairs_count_only_against_weaker_pairs() -> None:
    """Pair (0, 1) is off by 40 deg and both its loops run through pairs an earlier check judged
    wrong (100 inliers each). Weaker than them (20 inliers, as a look-alike pair on the twin ring)
    it goes; stronger (500, as a right aerial x ground pair beside weak wrong ones) those loops
    say nothing about it and it stays."""
    _, edges, _ = _graph(4, seed=11)
    edges[(0, 1)] = [_turn(40) @ edges[(0, 1)][0]]
    judged = {(0, 2), (0, 3)}
    for own, expect in ((20, [(0, 1)]), (500, [])):
        support = {e: 300 for e in edges} | dict.fromkeys(judged, 100) | {(0, 1): own}
        dropped = inconsistent_pairs(edges, support=support, keep=judged, judged=judged)[0]
        assert [e for e, _, _ in dropped] == expect, own


def test_a_pair_whose_rotation_only_weak_wrong_triangles_confirm_does_not_join_the_tree() -> None:
    """Images 0-2 and 3-5 are two groups, linked right by (2, 3) and (1, 3). Pair (0, 4) has more
    inliers than either but admits two rotations, and the only triangle its candidates close runs
    through a weak wrong pair (0, 5), so its vote takes the wrong one, 60 deg off (a flat site's
    tiled pair on an air-to-ground scene). Chained by inliers alone it would turn the second
    group and the check would drop the right links; it enters only as far as that triangle
    confirms it, after the right link, and only the wrong pair goes."""
    world, edges, _ = _graph(6, seed=11, noise_deg=0.0)
    right = {(0, 1), (0, 2), (1, 2), (3, 4), (3, 5), (4, 5), (2, 3), (1, 3)}
    edges = {e: r for e, r in edges.items() if e in right}
    support = dict.fromkeys(edges, 800) | {(2, 3): 200, (1, 3): 150}
    true04 = world[4] @ world[0].T
    wrong04 = _turn(60) @ true04
    edges[(0, 4)] = [true04, wrong04]
    edges[(0, 5)] = [edges[(4, 5)][0] @ wrong04]  # closes 0-4-5 with the wrong rotation
    support |= {(0, 4): 400, (0, 5): 50}
    assert (0, 4) in spanning_tree(edges, support), "the scene no longer shows the trap"
    dropped = tree_inconsistent_pairs(edges, support)
    assert [e for e, _, _ in dropped] == [(0, 5)]


def test_pairs_colmap_left_uncalibrated_come_last_in_the_tree() -> None:
    """Image 5's one right pair, (4, 5), admits two rotations and closes no triangle: its other
    pairs, (1, 5) and (3, 5), are look-alikes that agree with each other (as if 5 were turned),
    so the weak one confirms the other. Ranked by that confirmation, image 5 hangs on the wrong
    pair and the right one goes; the two are what COLMAP's verification leaves UNCALIBRATED (no
    essential matrix of the known cameras fits them), and marked so they come after the right
    pair, which stays while a wrong one goes (image 5 keeps two pairs)."""
    world, edges, _ = _graph(6, seed=13, noise_deg=0.0)
    edges = {e: r for e, r in edges.items() if e[1] < 5}
    support = dict.fromkeys(edges, 500)
    edges[(4, 5)] = [world[5] @ world[4].T, _turn(40) @ world[5] @ world[4].T]
    turned = _turn(120, "y") @ world[5]
    edges[(1, 5)] = [turned @ world[1].T]
    edges[(3, 5)] = [turned @ world[3].T]
    support |= {(4, 5): 114, (1, 5): 92, (3, 5): 63}
    fooled = [e for e, _, _ in tree_inconsistent_pairs(edges, support)]
    assert (4, 5) in fooled, "the scene no longer shows the trap"
    dropped = [e for e, _, _ in tree_inconsistent_pairs(edges, support, uncalibrated={(1, 5), (3, 5)})]
    assert len(dropped) == 1 and set(dropped) <= {(1, 5), (3, 5)}


def test_reading_the_kept_pairs_leaves_a_finished_projects_files_as_they_were(tmp_path: Path) -> None:
    """A localize reads the pairs a model was held to from the project's database: a finished
    run's WAL files (left beside it, as a run leaves them) keep their bytes and times."""
    import shutil
    import sqlite3
    import time

    from geomatch.sfm.viewgraph_filter import kept_pairs

    from .colmap_synthetic import synthetic_database

    live, project = tmp_path / "live", tmp_path / "project"
    live.mkdir()
    project.mkdir()
    synthetic_database(live / "database.db", 6, 100)
    with closing(sqlite3.connect(live / "database.db")) as c:
        c.execute("PRAGMA journal_mode=WAL")
        c.execute("CREATE TABLE IF NOT EXISTS x(a)")
        c.commit()
        c.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        for p in live.iterdir():  # the files as a run that ended leaves them, no connection open
            shutil.copy2(p, project / p.name)

    def listing() -> list[tuple[str, int, int]]:
        return sorted((p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in project.iterdir())

    before = listing()
    assert {n for n, _, _ in before} == {"database.db", "database.db-shm", "database.db-wal"}
    time.sleep(0.02)
    assert len(kept_pairs(str(project / "database.db")).kept_inliers) == 15
    assert listing() == before
