"""View-graph check before mapping: drop verified pairs whose relative rotation disagrees with
the loops of pairs around them.

Why: a pair can pass two-view verification with a geometrically consistent but wrong set of
matches (repeated facades and tiles, a wrong quarter turn of an aerial image), and one pair
carries no evidence against itself; the graph does. For three images i, j, k with all three pairs
verified the relative rotations compose, R_ik = R_jk R_ij: a wrong pair breaks every loop it is
in, a right one only the loops that contain a wrong pair. The loop check (as 1DSfM and GLOMAP
filter view graphs) removes, one at a time, the pair with the largest share of broken loops while
more of its loops are broken than hold. A pair in no loop is kept, and so are an image's last
``MIN_PAIRS`` pairs; a pair with a single broken loop is dropped only when it has the fewest
inliers of that loop, since one broken loop does not say which of its three pairs is wrong.

Where the scene repeats, non-overlapping views of look-alike facades can match each other
consistently, so their loops hold. They cannot agree with the chain of the strongest pairs, hence
the tree check (:func:`tree_inconsistent_pairs`): a spanning tree of the strongest pairs
(:func:`trusted_tree`: by inlier count, a pair admitting several rotations only as far as a
triangle confirms the one it chains) gives every image an absolute rotation, and a pair outside
the tree more than ``TREE_DEG + TREE_DEG_PER_HOP * hops`` from the tree's rotation is dropped.
A wrong pair whose rotation is right (the same facade shifted by a window) passes: rotations alone
cannot tell. The scenes behind the thresholds are in docs/benchmarks.md.

The relative rotations judged are each verified pair's candidates (pairrotations.py); the checks
run on a COLMAP database in viewgraph_filter.py.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Set

import numpy as np

from .pairrotations import rotation_angle

# a loop holds when the composed rotation is within this angle of the identity; three noisy
# estimates compose their errors, and pairs with little parallax give rotations to about a degree
LOOP_DEG = 5.0
MIN_INLIERS = 15  # COLMAP's min_num_inliers: pairs below it are not used by the mapper either
# an image keeps at least this many pairs: the mapper registers an image only from points that
# other views triangulated, and with one pair left it rarely has them; a wrong pair kept beside a
# right one costs less, since the mapper's PnP RANSAC rejects its wrong correspondences
MIN_PAIRS = 2
# the tree check's bound: an image's rotation chained over a tree path gathers each pair's error
# (a fraction of a degree per pair), far below how far off the wrong pairs of repeated structure
# are (docs/benchmarks.md)
TREE_DEG = 10.0
TREE_DEG_PER_HOP = 0.5


def loop_error(ij: list[np.ndarray], jk: list[np.ndarray], ik: list[np.ndarray]) -> float:
    """Degrees from the identity of R_ik^T R_jk R_ij, for the best choice of candidates."""
    return float(_closing_errors(np.stack(ij), np.stack(jk), np.stack(ik)).min())


def inconsistent_pairs(
    rotations: Mapping[tuple[int, int], list[np.ndarray]],
    loop_deg: float = LOOP_DEG,
    support: Mapping[tuple[int, int], int] | None = None,
    keep: Set[tuple[int, int]] = frozenset(),
    judged: Set[tuple[int, int]] = frozenset(),
) -> tuple[list[tuple[tuple[int, int], int, int]], int]:
    """Greedy loop check over ``rotations`` {(i, j): candidate R_ij, i < j}: the pairs to drop,
    each with (broken loops, loops) at the time it was dropped, and the number of loops at the
    start. A loop holds when some choice of one candidate per pair closes it. Ties (the same share
    and number of broken loops: an image whose pairs are mostly wrong breaks every loop through
    it, the right pair's too) go against the pair with the least ``support`` (its inliers).

    ``keep`` pairs are never dropped. ``judged`` pairs (wrong by an earlier check) are never
    dropped either, and a loop through one counts for a pair only when that pair has fewer inliers
    than it: a weak wrong pair breaks the loops it closes with stronger wrong ones
    (tests/test_twin_scene.py), while a strong right pair's loops through weak wrong pairs say
    nothing about it, and dropping it for them can leave an image out."""
    support = support or {}

    def counts(a: int, b: int, t: tuple[int, int, int]) -> bool:
        own = support.get((a, b), 0)
        others = [_key(x, y) for x, y in ((t[0], t[1]), (t[1], t[2]), (t[0], t[2])) if {x, y} != {a, b}]
        return all(e not in judged or own < support.get(e, 0) for e in others)

    edges = dict(rotations)

    def rot(a: int, b: int) -> list[np.ndarray]:
        return edges[(a, b)] if a < b else [R.T for R in edges[(b, a)]]

    nbrs = _neighbours(edges)
    broken: dict[tuple[int, int, int], bool] = {}
    for a, b in edges:
        for c in nbrs[a] & nbrs[b]:
            tri = tuple(sorted((a, b, c)))
            if tri not in broken:
                i, j, k = tri
                broken[tri] = loop_error(rot(i, j), rot(j, k), rot(i, k)) > loop_deg
    n_loops = len(broken)
    dropped: list[tuple[tuple[int, int], int, int]] = []
    while True:
        worst, worst_key = None, (0.0, 0, 0.0)
        for a, b in edges:
            if (a, b) in keep or (a, b) in judged:
                continue
            loops = [
                t for c in nbrs[a] & nbrs[b] if (t := tuple(sorted((a, b, c)))) in broken and counts(a, b, t)
            ]
            bad = sum(broken[t] for t in loops)
            if len(nbrs[a]) <= MIN_PAIRS or len(nbrs[b]) <= MIN_PAIRS:
                continue  # the last pairs of an image: dropping them would leave it out for sure
            if bad == 1 and not _weakest_in_broken(a, b, loops, broken, support):
                continue  # one broken loop does not say which of its three pairs is wrong
            if loops and bad > len(loops) - bad:
                key = (bad / len(loops), bad, -float(support.get((a, b), 0)))
                if key > worst_key:
                    worst, worst_key = (a, b, bad, len(loops)), key
        if worst is None:
            return dropped, n_loops
        a, b, bad, n = worst
        dropped.append(((a, b), bad, n))
        del edges[(a, b)]
        nbrs[a].discard(b)
        nbrs[b].discard(a)
        for t in [t for t in broken if a in t and b in t]:
            del broken[t]


def spanning_tree(
    pairs: Iterable[tuple[int, int]], support: Mapping[tuple[int, int], int]
) -> list[tuple[int, int]]:
    """The maximum spanning forest of ``pairs`` by ``support`` (Kruskal), strongest pair first;
    equal support in a fixed order, so a run is reproducible."""
    parent: dict[int, int] = {}

    def root(x: int) -> int:
        while parent.setdefault(x, x) != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    out = []
    for a, b in sorted(pairs, key=lambda e: (-support.get(e, 0), e)):
        if root(a) != root(b):
            parent[root(a)] = root(b)
            out.append((a, b))
    return out


def trusted_tree(
    rotations: Mapping[tuple[int, int], list[np.ndarray]],
    support: Mapping[tuple[int, int], int],
    uncalibrated: Set[tuple[int, int]] = frozenset(),
) -> dict[tuple[int, int], np.ndarray]:
    """The spanning forest the tree check chains, each pair with the candidate rotation it
    chains (:func:`_voted_candidate`).

    A pair enters by its inliers where it admits one rotation. Where it admits several, by how far
    the rotation its triangles voted for is confirmed: its inliers, but no more than the weaker
    other pair of the strongest triangle that closes with that rotation (closing none, after every
    confirmed pair, by its inliers). Inliers alone say how many
    matches agree with one geometry, not that the rotation the tree takes from them is right: a
    flat site's pair admits several, and where its triangles all run through wrong pairs (an
    image whose other pairs are all look-alikes) the vote can only pick among wrong closures. On
    the air-to-ground scenes two such strong pairs, chained far off, turned half the images and
    the check dropped the right pairs that were the only link between two groups of cameras,
    which the mapper then built as two models; confirmed first, the chain crosses through a right
    pair whose triangle with two right pairs confirms it (docs/benchmarks.md, "`geomatch run` over
    many seeds"). Where the strongest pairs close triangles with each other (a courtyard's
    neighbour pairs) the forest is the one inliers alone give.

    ``uncalibrated`` pairs (COLMAP's verification found an F their inliers fit but no essential
    matrix of the known cameras) come after every other pair, by inliers: on the air-to-ground
    seeds nearly all wrong verified pairs were such pairs and few right ones (docs/benchmarks.md,
    "`geomatch run` over many seeds"), and so on castle-P19 and fountain-P11. Confirmed by another
    such pair (an image's look-alike pairs agree with each other), a wrong pair would otherwise
    come before the image's one right pair when that admits several rotations and closes no
    triangle."""
    edges = dict(rotations)

    def rot(a: int, b: int) -> list[np.ndarray]:
        return edges[(a, b)] if a < b else [R.T for R in edges[(b, a)]]

    nbrs = _neighbours(edges)
    voted = {e: _voted_candidate(e[0], e[1], rot, nbrs, support) for e in edges}
    trust = {
        e: 0
        if e in uncalibrated
        else min(support.get(e, 0), closing)
        if _ambiguous(R, edges[e])
        else support.get(e, 0)
        for e, (R, closing) in voted.items()
    }
    ranked = sorted(edges, key=lambda e: (-trust[e], -support.get(e, 0), e))
    # spanning_tree takes the highest key first: the rank, reversed, is that key
    rank = {e: len(ranked) - i for i, e in enumerate(ranked)}
    return {e: voted[e][0] for e in spanning_tree(ranked, rank)}


def tree_inconsistent_pairs(
    rotations: Mapping[tuple[int, int], list[np.ndarray]],
    support: Mapping[tuple[int, int], int],
    base_deg: float = TREE_DEG,
    per_hop_deg: float = TREE_DEG_PER_HOP,
    uncalibrated: Set[tuple[int, int]] = frozenset(),
    trusted: Mapping[tuple[int, int], np.ndarray] | None = None,
) -> list[tuple[tuple[int, int], float, int]]:
    """The pairs of ``rotations`` {(i, j): candidate R_ij, i < j} that disagree with the tree of
    :func:`trusted_tree` (module docstring), each with its angle to the tree's rotation
    and the tree path length. Tree pairs are never returned, and an image keeps ``MIN_PAIRS``
    pairs (the most inconsistent go first). ``trusted``: that tree, where the caller has it."""
    edges = dict(rotations)

    def rot(a: int, b: int) -> list[np.ndarray]:
        return edges[(a, b)] if a < b else [R.T for R in edges[(b, a)]]

    nbrs = _neighbours(edges)
    tree: dict[int, list[tuple[int, np.ndarray]]] = {}
    if trusted is None:
        trusted = trusted_tree(edges, support, uncalibrated)
    for (a, b), R in trusted.items():
        tree.setdefault(a, []).append((b, R))
        tree.setdefault(b, []).append((a, R.T))
    absolute: dict[int, np.ndarray] = {}
    depth: dict[int, int] = {}
    up: dict[int, int] = {}
    for start in sorted(tree):
        if start in absolute:
            continue
        absolute[start], depth[start], up[start] = np.eye(3), 0, start
        stack = [start]
        while stack:
            x = stack.pop()
            for y, R_xy in tree[x]:
                if y not in absolute:
                    absolute[y], depth[y], up[y] = R_xy @ absolute[x], depth[x] + 1, x
                    stack.append(y)

    def hops(a: int, b: int) -> int:
        n = 0
        while a != b:
            if depth[a] < depth[b]:
                a, b = b, a
            a, n = up[a], n + 1
        return n

    judged: list[tuple[tuple[int, int], float, int]] = []
    for a, b in sorted(edges):
        if any(y == b for y, _ in tree.get(a, [])):
            continue
        h = hops(a, b)
        chained = absolute[b] @ absolute[a].T
        err = min(rotation_angle(c.T @ chained) for c in edges[(a, b)])
        if err > base_deg + per_hop_deg * h:
            judged.append(((a, b), err, h))
    # the worst first, and an image keeps MIN_PAIRS pairs, as in the loop check: with one pair
    # left an image registers only if that pair's points are seen by a third view
    out: list[tuple[tuple[int, int], float, int]] = []
    for (a, b), err, h in sorted(judged, key=lambda j: -j[1]):
        if len(nbrs[a]) <= MIN_PAIRS or len(nbrs[b]) <= MIN_PAIRS:
            continue
        nbrs[a].discard(b)
        nbrs[b].discard(a)
        out.append(((a, b), err, h))
    return sorted(out)


def _neighbours(pairs: Iterable[tuple[int, int]]) -> dict[int, set[int]]:
    nbrs: dict[int, set[int]] = {}
    for a, b in pairs:
        nbrs.setdefault(a, set()).add(b)
        nbrs.setdefault(b, set()).add(a)
    return nbrs


def _voted_candidate(
    a: int,
    b: int,
    rot: Callable[[int, int], list[np.ndarray]],
    nbrs: Mapping[int, set[int]],
    support: Mapping[tuple[int, int], int],
) -> tuple[np.ndarray, int]:
    """The candidate rotation of pair (a, b) whose closed triangles carry the most support, the
    least closing error among ties (each triangle's error weighted like its vote), and the support
    of the strongest triangle it closes (0: none).
    A flat or distant scene's pair admits several rotations (essential matrix, COLMAP's pose,
    homography decompositions), and so do its neighbours, so wrong candidates can close as many
    triangles as the right one; they close them less tightly. A triangle counts with the inliers
    of its weaker other pair, so a wrong candidate closing triangles through weak wrong pairs does
    not outvote the right one closing them through strong right pairs (counted alike, the error
    tie-break can pick the wrong one and turn every image behind it). A homography's second
    decomposition can close the same triangles as the right rotation, through its neighbours' own
    second decompositions, and then the tie-break decides: summed unweighted, a weak wrong
    triangle's error decided it for a strong ground pair's wrong rotation (docs/benchmarks.md,
    "`geomatch run` over many seeds")."""
    cands = np.stack(rot(a, b))
    votes = np.zeros(len(cands))
    error = np.zeros(len(cands))
    strongest = np.zeros(len(cands))
    for k in sorted(nbrs[a] & nbrs[b]):
        weight = min(support.get(_key(a, k), 0), support.get(_key(b, k), 0))
        e = _closing_errors(cands, np.stack(rot(b, k)), np.stack(rot(a, k)))
        closes = e <= LOOP_DEG
        votes += weight * closes
        error += weight * np.minimum(e, 4 * LOOP_DEG)
        strongest = np.maximum(strongest, weight * closes)
    best = min(range(len(cands)), key=lambda i: (-votes[i], error[i], i))
    return cands[best], int(strongest[best])


def _ambiguous(chosen: np.ndarray, cands: list[np.ndarray]) -> bool:
    """Whether a pair admits a rotation more than LOOP_DEG from the one the vote chose: then the
    vote, not the pair, decided the rotation."""
    return any(rotation_angle(chosen.T @ R) > LOOP_DEG for R in cands)


def _closing_errors(ab: np.ndarray, bk: np.ndarray, ak: np.ndarray) -> np.ndarray:
    """Per candidate of ``ab``: :func:`loop_error` of the triangle with ``bk`` and ``ak`` (stacked
    candidates), all at once: the tree ranks every pair by it, so it runs per triangle and pair."""
    chained = np.einsum("mij,njk->nmik", bk, ab)  # R_bk R_ab
    trace = np.einsum("pik,nmik->nmp", ak, chained)  # trace(R_ak^T R_bk R_ab)
    angles = np.degrees(np.arccos(np.clip((trace - 1) / 2, -1.0, 1.0)))
    return angles.reshape(len(ab), -1).min(axis=1)


def _key(a: int, b: int) -> tuple[int, int]:
    return (a, b) if a < b else (b, a)


def _weakest_in_broken(
    a: int,
    b: int,
    loops: list[tuple[int, int, int]],
    broken: Mapping[tuple[int, int, int], bool],
    support: Mapping[tuple[int, int], int],
) -> bool:
    """Whether (a, b) has the fewest inliers of a broken loop it is in."""
    own = support.get((a, b), 0)
    for t in loops:
        if broken[t]:
            i, j, k = t
            if own <= min(support.get(e, 0) for e in ((i, j), (j, k), (i, k))):
                return True
    return False


def judge(
    rotations: Mapping[tuple[int, int], list[np.ndarray]],
    inliers: Mapping[tuple[int, int], int],
    loop_deg: float = LOOP_DEG,
    loops: bool = True,
    tree: bool = True,
    uncalibrated: Set[tuple[int, int]] = frozenset(),
) -> tuple[list[tuple[tuple[int, int], float, int]], list[tuple[tuple[int, int], int, int]], int]:
    """The pairs the tree check drops (pair, degrees, hops), then those the loop check drops
    (pair, broken loops, loops), and the number of loops it saw. The loop check judges the pairs
    the tree check kept, and counts a loop through a pair the tree check dropped only against
    pairs weaker than that one (:func:`inconsistent_pairs`). It never drops a pair of the spanning
    tree: where repeated structure makes many pairs wrong, the loops through right neighbour
    pairs break too, and the loop check alone can drop a strong right pair and leave cameras
    attached by wrong pairs only (docs/pipeline.md, "The view-graph checks"). An image keeps
    ``MIN_PAIRS`` pairs over both checks. ``uncalibrated``: :func:`trusted_tree`'s."""
    pairs_of = Counter(i for pair in rotations for i in pair)
    # the tree votes on every pair: built once for both checks
    trusted = trusted_tree(rotations, inliers, uncalibrated) if tree else {}
    tree_drop = tree_inconsistent_pairs(rotations, inliers, trusted=trusted) if tree else []
    gone = {pair for pair, _, _ in tree_drop}
    pairs_of.subtract(i for pair in gone for i in pair)
    loop_drop: list[tuple[tuple[int, int], int, int]] = []
    seen = 0
    if loops:
        keep = set(trusted)
        drop, seen = inconsistent_pairs(rotations, loop_deg, inliers, keep, judged=gone)
        for (a, b), bad, n in drop:
            if min(pairs_of[a], pairs_of[b]) <= MIN_PAIRS:
                continue
            loop_drop.append(((a, b), bad, n))
            pairs_of.subtract((a, b))
    return tree_drop, loop_drop, seen
