"""How well a model's cameras agree with the relative rotations of the pairs it was built from.

Why: on the air-to-ground scenes the incremental mapper sometimes places a block of cameras
tens of degrees off though every pair it used is right; which block, and whether at all, depends
on its random seed (RANSAC samples, the order images are tried). Such a model contradicts its
strongest pairs: an aerial image and a street photo sharing many inliers, placed tens of degrees
from that pair's two-view rotation, while a right model holds each right pair within a degree or
two and disagrees only with the few weak wrong pairs the view-graph checks let through. The
inliers of the pairs it contradicts, against those it holds, say which of several attempts to
keep without any ground truth (docs/benchmarks.md, "`geomatch run` over many seeds").
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pycolmap
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from .pairrotations import rotation_angle

# a model's relative rotation within this angle of one of a pair's candidate rotations holds the
# pair: the view-graph loops hold at 5 deg, and a right pair's rotation is good to about a degree
AGREE_DEG = 5.0
# a model that contradicts at most this share of its pairs' inliers is taken as it is: right
# models of the synthetic seeds contradict only the weak wrong pairs kept, misplaced ones far more
CLEAN_SHARE = 0.1
# another rotation a camera's pairs hold as well as its own is a second place for it only this far
# from its own: the estimators of one right pair give candidates a few degrees apart (on the
# service tests' scene two such rotations held every pair alike: docs/benchmarks.md, "Subsets of
# the scenes: photos left out"), a homography's other decomposition tens of degrees
TIE_DEG = 2 * AGREE_DEG
# ...and only for a camera its own rotation holds by fewer inliers than this: the twins seen were
# held by weaker near-flat pairs, while a right camera hung on one strong pair (the demo scene's
# ground_03 with ground_02) has its essential matrix pinned by points off the plane, and the
# homography's other decomposition, listed among its candidates, explains few (the counts:
# docs/benchmarks.md, "Subsets of the scenes: photos left out")
TIE_MAX_INLIERS = 400


@dataclass(frozen=True)
class Agreement:
    held: int  # inliers of the pairs between registered images that the model holds
    contradicted: int  # ...and of those it contradicts
    off: tuple[tuple[str, str, float], ...]  # the contradicted pairs, degrees off

    @property
    def score(self) -> int:
        """More cameras held right adds inliers held; a misplaced block moves its strong pairs to
        the other side, which counts twice."""
        return self.held - self.contradicted

    @property
    def clean(self) -> bool:
        total = self.held + self.contradicted
        return total == 0 or self.contradicted <= CLEAN_SHARE * total

    def as_dict(self) -> dict[str, object]:
        return {
            "held": self.held,
            "contradicted": self.contradicted,
            "off": [{"pair": [a, b], "degrees": round(d, 1)} for a, b, d in self.off],
        }


# an image is misplaced where the model contradicts at least this many inliers of its own pairs
# and holds at most MISPLACED_HELD_SHARE of that: the mapper's wrong PnP or structure-less pose
# for one image, its right pairs all turned against it; an image bent with a misplaced block
# still holds some of its pairs and is left to the attempts (mapping.py)
MISPLACED_MIN_INLIERS = 100
MISPLACED_HELD_SHARE = 0.1


def misplaced(
    rec: pycolmap.Reconstruction,
    rotations: Mapping[tuple[str, str], list[np.ndarray]],
    inliers: Mapping[tuple[str, str], int],
) -> list[str]:
    """The registered images the model places against their own pairs, by name."""
    held: dict[str, int] = {}
    contradicted: dict[str, int] = {}
    for a, b, err in _pair_errors(rec, rotations):
        side = held if err <= AGREE_DEG else contradicted
        for name in (a, b):
            side[name] = side.get(name, 0) + inliers[(a, b)]
    return sorted(
        n
        for n, c in contradicted.items()
        if c >= MISPLACED_MIN_INLIERS and held.get(n, 0) <= MISPLACED_HELD_SHARE * c
    )


def misplaced_blocks(
    rec: pycolmap.Reconstruction,
    rotations: Mapping[tuple[str, str], list[np.ndarray]],
    inliers: Mapping[tuple[str, str], int],
) -> list[set[str]]:
    """Groups of registered images that hold their pairs with each other but contradict every pair
    with the rest of the model, at least MISPLACED_MIN_INLIERS of them: a block the mapper turned
    as one, after a wrong PnP pose of one image on a few dozen points that the next images then
    registered against (one image of such a block holds most of its pairs, so :func:`misplaced`
    passes it). The rest is the group holding the most inliers; the blocks are the others, largest
    first. Empty when the model's held pairs tie all its images together."""
    errors = _pair_errors(rec, rotations)
    groups = _held_groups(errors, inliers)
    if len(groups) < 2:
        return []
    against: dict[int, int] = {}
    where = {n: g for g, group in enumerate(groups) for n in group}
    for a, b, err in errors:
        ga, gb = where[a], where[b]
        if err > AGREE_DEG and 0 in (ga, gb) and ga != gb:
            other = gb if ga == 0 else ga
            against[other] = against.get(other, 0) + inliers[(a, b)]
    blocks = [groups[g] for g in range(1, len(groups)) if against.get(g, 0) >= MISPLACED_MIN_INLIERS]
    return sorted(blocks, key=lambda b: (-len(b), min(b)))


def unvouched(
    rec: pycolmap.Reconstruction,
    rotations: Mapping[tuple[str, str], list[np.ndarray]],
    inliers: Mapping[tuple[str, str], int],
    ties: bool = True,
) -> list[str]:
    """The registered images whose place the model's own pairs do not vouch for, by name: those
    :func:`misplaced` and :func:`outvoted` find, with ``ties`` those :func:`undecided` finds, and
    every image outside the group that the held pairs tie to the most inliers (a block held only
    within itself, however few inliers it contradicts: whether the mapper placed it right no pair
    says). A user's model should rather lack such a camera than hold it wrong, and a photo
    localized against it alone is placed wherever it is."""
    groups = _held_groups(_pair_errors(rec, rotations), inliers)
    apart = {n for group in groups[1:] for n in group}
    doubted = undecided if ties else outvoted
    return sorted(apart | set(misplaced(rec, rotations, inliers)) | set(doubted(rec, rotations, inliers)))


def unvouched_in_steps(
    rec: pycolmap.Reconstruction,
    rotations: Mapping[tuple[str, str], list[np.ndarray]],
    inliers: Mapping[tuple[str, str], int],
) -> list[str]:
    """:func:`unvouched` as the mapping leaves cameras out (leftovers.leave_out_unvouched): those
    the pairs speak against, then the tied ones among the rest, judged without the first. Why: a
    block held wrong leaves its right neighbours holding only their pairs with the rest, which a
    rotation through the block can nearly match; without the block they hold all they have."""
    strong = set(unvouched(rec, rotations, inliers, ties=False))
    rest = pycolmap.Reconstruction(rec)
    for im in list(rest.images.values()):
        if im.name in strong and im.has_pose:
            rest.deregister_frame(im.frame_id)
    return sorted(strong | set(unvouched(rest, rotations, inliers, ties=True)))


def outvoted(
    rec: pycolmap.Reconstruction,
    rotations: Mapping[tuple[str, str], list[np.ndarray]],
    inliers: Mapping[tuple[str, str], int],
) -> list[str]:
    """The registered images that another rotation would hold more of their own pairs' inliers
    than the model's does, by name (the other cameras as the model has them). Why: a pair of a
    near-flat view admits a homography's other decomposition besides its true rotation, and the
    mapper can register an image on it: 2+6 tuning seed 300 without ground_04 and ground_05 wrote
    ground_03 far off, held by its stronger pair, with ground_02, through a candidate far from the
    truth while its weaker pair, with aerial_01, was contradicted; the true rotation holds both.
    :func:`misplaced` passes it (it holds more than a tenth), and so does the agreement (a small
    share of the model's inliers contradicted)."""
    return sorted(n for n, (own, other) in _rotation_votes(rec, rotations, inliers).items() if other > own)


def most_outvoted(
    rec: pycolmap.Reconstruction,
    rotations: Mapping[tuple[str, str], list[np.ndarray]],
    inliers: Mapping[tuple[str, str], int],
) -> str | None:
    """The outvoted image (:func:`outvoted`) whose pairs another rotation would hold by the most
    inliers more than its own, or None. Why: one camera held wrong turns its neighbours' pairs with
    it against them too, so in a small model the outvoted can be half of it; the worst is the
    cause, and the others hold their pairs again once it is gone."""
    margins = {n: other - own for n, (own, other) in _rotation_votes(rec, rotations, inliers).items()}
    worst = max(sorted(margins), key=lambda n: margins[n], default=None)
    return worst if worst is not None and margins[worst] > 0 else None


def weakest_tied(
    rec: pycolmap.Reconstruction,
    rotations: Mapping[tuple[str, str], list[np.ndarray]],
    inliers: Mapping[tuple[str, str], int],
) -> str | None:
    """Of the images tied between two rotations (:func:`undecided` without the outvoted), the one
    its own pairs hold by the fewest inliers, or None: where the ties are half of a small model,
    the one least held goes first, and the rest may hold again without it."""
    tied = _tied(rec, rotations, inliers)
    return min(sorted(tied), key=lambda n: tied[n], default=None)


def undecided(
    rec: pycolmap.Reconstruction,
    rotations: Mapping[tuple[str, str], list[np.ndarray]],
    inliers: Mapping[tuple[str, str], int],
) -> list[str]:
    """The registered images whose own pairs hold another rotation, over TIE_DEG from the model's,
    as well as the model's, by name, and :func:`outvoted`'s. Why: an image tied to the model by
    one near-flat pair (or by pairs that all admit one other rotation) is placed by whichever
    decomposition the mapper's PnP or two-view step took, and nothing in the model says which; the
    2+6 test scene 403 without two ground photos wrote ground_04 and ground_05 far off so, each
    held by its one pair with ground_01 through a candidate other than the true one
    (docs/benchmarks.md, "Subsets of the scenes: photos left out"). A rotation a few degrees off
    holds what the model's holds through the neighbouring candidates that one pair's estimators
    give: no second place, so not a tie."""
    return sorted(set(_tied(rec, rotations, inliers)) | set(outvoted(rec, rotations, inliers)))


def _tied(
    rec: pycolmap.Reconstruction,
    rotations: Mapping[tuple[str, str], list[np.ndarray]],
    inliers: Mapping[tuple[str, str], int],
) -> dict[str, int]:
    """The images tied between two rotations (over TIE_DEG apart, under TIE_MAX_INLIERS held),
    with the inliers their own rotation holds."""
    votes = _rotation_votes(rec, rotations, inliers, TIE_DEG)
    return {n: own for n, (own, other) in votes.items() if own < TIE_MAX_INLIERS and other >= own}


def _rotation_votes(
    rec: pycolmap.Reconstruction,
    rotations: Mapping[tuple[str, str], list[np.ndarray]],
    inliers: Mapping[tuple[str, str], int],
    apart_deg: float = AGREE_DEG,
) -> dict[str, tuple[int, int]]:
    """For each registered image with pairs in the model: the inliers of its pairs that its pose
    holds, and the most that another rotation its pairs' candidates give (over ``apart_deg`` from
    it) would hold (0 when there is none)."""
    poses = {im.name: im.cam_from_world().rotation.matrix() for im in rec.images.values() if im.has_pose}
    implied: dict[str, list[np.ndarray]] = {}  # each image's rotations its pairs' candidates give
    ties: dict[str, list[tuple[str, str]]] = {}
    for (a, b), cands in rotations.items():
        if a in poses and b in poses and cands:
            ties.setdefault(a, []).append((a, b))
            ties.setdefault(b, []).append((a, b))
            implied.setdefault(b, []).extend(C @ poses[a] for C in cands)
            implied.setdefault(a, []).extend(C.T @ poses[b] for C in cands)

    def held(name: str, R: np.ndarray) -> int:
        total = 0
        for a, b in ties[name]:
            Ra, Rb = (R, poses[b]) if name == a else (poses[a], R)
            rel = Rb @ Ra.T
            if min(rotation_angle(rel.T @ C) for C in rotations[(a, b)]) <= AGREE_DEG:
                total += inliers[(a, b)]
        return total

    out = {}
    for name, options in implied.items():
        others = [R for R in options if rotation_angle(R @ poses[name].T) > apart_deg]
        out[name] = (held(name, poses[name]), max((held(name, R) for R in others), default=0))
    return out


def _held_groups(
    errors: list[tuple[str, str, float]], inliers: Mapping[tuple[str, str], int]
) -> list[set[str]]:
    """The images of ``errors`` grouped by the pairs the model holds (connected components), the
    group holding the most inliers first (then the largest), the others in a fixed order."""
    names = sorted({n for a, b, _ in errors for n in (a, b)})
    index = {n: i for i, n in enumerate(names)}
    held_edges = [(index[a], index[b]) for a, b, err in errors if err <= AGREE_DEG]
    rows, cols = (list(x) for x in zip(*held_edges, strict=True)) if held_edges else ([], [])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(names), len(names)))
    count, label = connected_components(graph, directed=False)
    held = np.zeros(count, np.int64)
    for a, b, err in errors:
        if err <= AGREE_DEG:
            held[label[index[a]]] += inliers[(a, b)]
    sizes = np.bincount(label, minlength=count)
    order = sorted(range(count), key=lambda g: (-held[g], -sizes[g], g))
    return [{n for n in names if label[index[n]] == g} for g in order]


def _pair_errors(
    rec: pycolmap.Reconstruction, rotations: Mapping[tuple[str, str], list[np.ndarray]]
) -> list[tuple[str, str, float]]:
    """(a, b, degrees) for each pair between registered images: how far the model's relative
    rotation is from the nearest of the pair's candidates."""
    poses = {im.name: im.cam_from_world().rotation.matrix() for im in rec.images.values() if im.has_pose}
    out = []
    for (a, b), cands in rotations.items():
        if a in poses and b in poses and cands:
            rel = poses[b] @ poses[a].T
            out.append((a, b, min(rotation_angle(rel.T @ C) for C in cands)))
    return out


def agreement(
    rec: pycolmap.Reconstruction,
    rotations: Mapping[tuple[str, str], list[np.ndarray]],
    inliers: Mapping[tuple[str, str], int],
) -> Agreement:
    """``rotations``: each pair's candidate rotations R (x_b ~ R x_a + t) keyed by image names
    (a, b); ``inliers`` its inlier count. Pairs with an image the model lacks are not counted."""
    held = contradicted = 0
    off = []
    for a, b, err in _pair_errors(rec, rotations):
        if err <= AGREE_DEG:
            held += inliers[(a, b)]
        else:
            contradicted += inliers[(a, b)]
            off.append((a, b, err))
    return Agreement(held, contradicted, tuple(sorted(off, key=lambda o: -o[2])))
