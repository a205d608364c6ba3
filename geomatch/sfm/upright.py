"""The relative rotations a pair may have when both photos know where up is.

Why: a near-flat site (a survey's ground seen from above) admits two consistent families of
relative rotations: the essential matrix's and, from the homography's other decomposition, one
that tilts the cameras against each other. The second family closes the view graph's
triangles just as well, through the neighbours' own second decompositions, so the vote cannot
tell them apart. On caliterra (nadir photos, judged by COLMAP SIFT's model) the vote took the
second family for some of the pairs that admit both, the spanning tree chained rotations of it,
and the tree check dropped many right pairs. Where both photos know where up is (a DJI gimbal's
pitch and roll, or a survey's nadir camera) a right rotation carries one photo's up onto the
other's, to the gimbal's fraction of a degree or to a nadir camera's few degrees of sway; the
second family misses it by the tilt it adds. The pair keeps the candidates that carry up within
``SLACK_DEG`` of the best one: on caliterra the vote is then right for nearly all of them and
the tree check drops few right pairs (docs/benchmarks.md, "Drone surveys beside COLMAP SIFT",
what the view graph drops on caliterra).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from ..metadata import ImageMeta, up_in_camera

# a nadir camera without a gimbal sways a few degrees each way: the two photos' ups differ by up to
# about twice that, so candidates within this of the best carrying of up stay (the second
# decomposition of a survey pair tilts by tens of degrees)
SLACK_DEG = 10.0
# up in a nadir camera (x right, y down, z forward): against the optical axis
NADIR_UP = np.array([0.0, 0.0, -1.0])


def image_up(metas: Mapping[str, ImageMeta], survey: bool) -> dict[str, np.ndarray]:
    """Up in each camera's frame where a photo knows it: from its gimbal's pitch and roll
    (metadata.up_in_camera), and in a survey (every photo aerial) from the nadir camera a survey
    flies where the photo says nothing of its gimbal (a compact camera hung under the drone; the
    matcher treats such a survey as nadir too). A photo whose gimbal is pitched off nadir without a
    roll is left out: its up is not known well enough."""
    out: dict[str, np.ndarray] = {}
    for name, meta in metas.items():
        up = up_in_camera(meta)
        if up is not None and np.isfinite(up).all():
            out[name] = np.asarray(up, np.float64)
        elif survey and meta.gimbal_pitch_deg is None:
            out[name] = NADIR_UP
    return out


def up_error_deg(R: np.ndarray, up0: np.ndarray, up1: np.ndarray) -> float:
    """Degrees between image 1's up and image 0's up carried by R (x1 ~ R x0 + t)."""
    c = float(np.dot(R @ up0, up1) / (np.linalg.norm(up0) * np.linalg.norm(up1)))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def upright_candidates(
    rotations: Mapping[tuple[int, int], list[np.ndarray]],
    names: Mapping[int, str],
    up: Mapping[str, np.ndarray],
    slack_deg: float = SLACK_DEG,
) -> dict[tuple[int, int], list[np.ndarray]]:
    """``rotations`` {(i, j): candidates R_ij} with, for each pair both of whose photos are in
    ``up``, only the candidates that carry up within ``slack_deg`` of the best one (never none)."""
    out: dict[tuple[int, int], list[np.ndarray]] = {}
    for (a, b), cands in rotations.items():
        ua, ub = up.get(names.get(a, "")), up.get(names.get(b, ""))
        if ua is None or ub is None or len(cands) < 2:
            out[(a, b)] = list(cands)
            continue
        err = [up_error_deg(R, ua, ub) for R in cands]
        best = min(err)
        out[(a, b)] = [R for R, e in zip(cands, err, strict=True) if e <= best + slack_deg]
    return out
