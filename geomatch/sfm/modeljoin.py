"""Join models that share an image: the mapper's second model placed into its first.

Why: an aerial image matched against ground photos through its tiling crops gets keypoints at the
crops' scale, and against other aerial images at its own; the two sets are different keypoints, so
no track runs through both. When ground photos reach the rest of the project only through such an
image, COLMAP's incremental mapper registers that image in its first model (from its aerial
partner) and starts a second model from the ground photos, which registers the same image again
from the crop keypoints. The two models share a camera but no 3D point, so COLMAP's own merge
(common observations) cannot align them, and nothing in either model fixes their relative scale.

The shared image does: its pose gives the rotation and translation between the models, and the
scale is the ratio of depths, in that image, of the two models' points seen at nearby pixels
(the same surfaces, reached through different keypoints). A join is kept only when enough such
neighbours agree on one scale, and only where the verified pairs between the placed cameras and
the first model's others hold the placed poses (joincheck.py: a block at a wrong scale keeps its
rotations and breaks those pairs); the joined cameras are then fixed in the first model, every
point is triangulated again from the database with the poses held, and a bundle adjustment refines
the whole. A join those pairs refuse leaves the second model as it was, and the summary says so.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pycolmap
from scipy.spatial import cKDTree

from .joincheck import CrossPairs, View, cross_pairs

# two observations, one per model, within this many pixels of each other in the shared image see
# the same surface: close enough that a facade edge between them is rare, far enough that the
# crop keypoints (at twice the aerial image's scale) find neighbours among the full-image ones
NEIGHBOUR_PX = 8.0
# a scale rests on at least this many neighbours, whose log depth ratios spread (median absolute
# deviation) less than MAX_SCALE_SPREAD: a join on a few or disagreeing ratios would place the
# second model's cameras at a wrong distance, worse than leaving them out. The right joins of the
# air-to-ground subsets spread well under the bound, and one far over it put its aerial camera off
# with no pair that could tell (docs/benchmarks.md, "Subsets of the scenes: photos left out")
MIN_NEIGHBOURS = 5
MAX_SCALE_SPREAD = 0.05


@dataclass(frozen=True)
class Join:
    """How a second model was placed into the first, for the run's summary."""

    via: str  # the shared image
    scale: float  # the second model's units in the first's
    neighbours: int  # depth ratios the scale rests on
    spread: float  # their median absolute deviation in log scale
    images: tuple[str, ...]  # the images the first model gained (or would have, when refused)
    # inliers of the verified pairs between those images and the first model's others (not the
    # shared image's) that the placed poses hold, and that they break
    pairs_held: int = 0
    pairs_contradicted: int = 0
    # no such pair either way, and the shared image is not one the project tiled: nothing but
    # that one image's pose in two models holds the join (join_models says why that is not enough)
    alone: bool = False

    @property
    def refused(self) -> bool:
        return self.alone or CrossPairs(self.pairs_held, self.pairs_contradicted).refuse

    @property
    def reason(self) -> str | None:
        """Why the join was refused, in words for the summary; None when it was not."""
        if self.alone:
            return f"only {self.via} ties these cameras to the rest, and no pair of theirs checks it"
        if self.refused:
            return "their pairs with the rest do not meet their epipolar lines at the joined poses"
        return None

    def as_dict(self) -> dict[str, object]:
        out: dict[str, object] = {
            "via": self.via,
            "scale": round(self.scale, 4),
            "neighbours": self.neighbours,
            "spread": round(self.spread, 4),
            "images": list(self.images),
            "pairs_held": self.pairs_held,
            "pairs_contradicted": self.pairs_contradicted,
        }
        if self.reason is not None:
            out["reason"] = self.reason
        return out


def _depths(rec: pycolmap.Reconstruction, image: pycolmap.Image) -> tuple[np.ndarray, np.ndarray]:
    """Pixels and camera-frame depths of the image's observations that have a 3D point."""
    pose = image.cam_from_world()
    uv, depth = [], []
    for p in image.points2D:
        if p.has_point3D():
            uv.append(p.xy)
            depth.append((pose * rec.points3D[p.point3D_id].xyz)[2])
    return np.asarray(uv, np.float64).reshape(-1, 2), np.asarray(depth, np.float64)


def depth_scale(
    first: pycolmap.Reconstruction, second: pycolmap.Reconstruction, name: str
) -> tuple[float, int, float] | None:
    """(scale, neighbours, spread) of ``second`` in ``first``'s units from the image ``name``
    registered in both: for each of the second model's observations in that image, the median
    depth of the first model's observations within NEIGHBOUR_PX over its own depth; the median of
    those ratios (in log). None when no observation has a neighbour."""
    uv0, d0 = _depths(first, first.find_image_with_name(name))
    uv1, d1 = _depths(second, second.find_image_with_name(name))
    if not len(uv0) or not len(uv1):
        return None
    tree = cKDTree(uv0)
    logs = []
    for near, d in zip(tree.query_ball_point(uv1, NEIGHBOUR_PX), d1, strict=True):
        if near and d > 0:
            ahead = d0[near][d0[near] > 0]
            if len(ahead):
                logs.append(np.log(np.median(ahead) / d))
    if not logs:
        return None
    r = np.asarray(logs)
    med = float(np.median(r))
    return float(np.exp(med)), len(r), float(np.median(np.abs(r - med)))


def similarity(
    first: pycolmap.Reconstruction, second: pycolmap.Reconstruction, name: str, scale: float
) -> pycolmap.Sim3d:
    """first_from_second: the transform that gives the image ``name`` the same pose in both."""
    p0 = first.find_image_with_name(name).cam_from_world()
    p1 = second.find_image_with_name(name).cam_from_world()
    r0, t0 = p0.rotation.matrix(), np.asarray(p0.translation)
    r1, t1 = p1.rotation.matrix(), np.asarray(p1.translation)
    # x_cam = R0 X0 + t0 = scale (R1 X1 + t1) with X0 = scale R X1 + t
    return pycolmap.Sim3d(scale, pycolmap.Rotation3d(r0.T @ r1), r0.T @ (scale * t1 - t0))


def _registered(rec: pycolmap.Reconstruction) -> set[str]:
    return {im.name for im in rec.images.values() if im.has_pose}


def place(first: pycolmap.Reconstruction, second: pycolmap.Reconstruction) -> Join | None:
    """Place ``second``'s cameras that ``first`` lacks into ``first`` (poses only, no points)
    through the shared image with the most neighbours, if its scale holds (module docstring)."""
    new = _registered(second) - _registered(first)
    if not new:
        return None
    best: tuple[str, float, int, float] | None = None
    for name in sorted(_registered(first) & _registered(second)):
        found = depth_scale(first, second, name)
        if found is None:
            continue
        scale, n, spread = found
        if n >= MIN_NEIGHBOURS and spread <= MAX_SCALE_SPREAD and (best is None or n > best[2]):
            best = (name, scale, n, spread)
    if best is None:
        return None
    via, scale, n, spread = best
    moved = pycolmap.Reconstruction(second)
    moved.transform(similarity(first, second, via, scale))
    for name in sorted(new):
        src = moved.find_image_with_name(name)
        if not first.exists_camera(src.camera_id):
            first.add_camera_with_trivial_rig(moved.cameras[src.camera_id])
        image = pycolmap.Image()
        image.name, image.image_id, image.camera_id = name, src.image_id, src.camera_id
        image.points2D = pycolmap.Point2DList([pycolmap.Point2D(p.xy) for p in src.points2D])
        first.add_image_with_trivial_frame(image, src.cam_from_world())
    return Join(via, scale, n, spread, tuple(sorted(new)))


def verify(
    rec: pycolmap.Reconstruction,
    join: Join,
    base: set[str],
    database: Path,
    bridges: Collection[str] | None = None,
) -> Join:
    """``join`` with the inliers of the verified pairs of ``database`` between the images it placed
    and the images of ``base`` (the first model's own, the shared image aside) that ``rec`` holds,
    and of those it breaks (joincheck.py); ``alone`` where there are none and the shared image is
    not among ``bridges`` (None: any image may bridge). Measured on the adjusted model: the
    placement alone carries the second model's error in the shared image's pose, which the
    adjustment takes out of a right join and cannot take out of a wrong one (its cross pairs have
    no points to pull by)."""

    def view(name: str) -> View:
        image = rec.find_image_with_name(name)
        return View(rec.cameras[image.camera_id], image.cam_from_world())

    held = _registered(rec)
    placed = {name: view(name) for name in join.images if name in held}
    others = {name: view(name) for name in sorted(base & held) if name != join.via}
    check = cross_pairs(database, placed, others)
    silent = check.held == 0 and check.contradicted == 0
    alone = silent and bridges is not None and join.via not in bridges
    return replace(join, pairs_held=check.held, pairs_contradicted=check.contradicted, alone=alone)


def join_models(
    models: list[pycolmap.Reconstruction],
    database: Path,
    image_dir: Path,
    work: Path,
    options: pycolmap.IncrementalPipelineOptions,
    bridges: Collection[str] | None = None,
) -> tuple[list[pycolmap.Reconstruction], list[Join]]:
    """``models`` (largest first) with every later model that shares an image with the first
    placed into it, its points triangulated again from ``database`` (the mapper's copy) with the
    poses held and the whole bundle-adjusted; the models that could not be joined follow as they
    were. A join whose cross pairs refuse it (:func:`verify`) is undone and the rest joined again
    without it, and so is one that no cross pair speaks for unless its shared image is among
    ``bridges``: the images the project tiled (None: any image), whose crop keypoints are why
    two right models can share such an image and nothing else. Through any other image, two
    models that meet only there are a block the mapper could not tie to the rest, and that one
    image's pose in each (a homography's other decomposition, a wrong pose chain) places it. The
    joins come back with the models, refused ones included (``Join.refused``), for the summary.
    ``work``: a scratch folder for the triangulation."""
    if len(models) < 2:
        return models, []
    base = _registered(models[0])
    refused: dict[int, Join] = {}
    while True:  # each pass refuses one join more or returns: at most len(models) passes
        first, rest, joins = pycolmap.Reconstruction(models[0]), [], {}
        for k, other in enumerate(models[1:], start=1):
            j = None if k in refused else place(first, other)
            if j is None:
                rest.append(other)
            else:
                joins[k] = j
        if not joins:
            return models, list(refused.values())
        into = work / f"pass_{len(refused)}"
        into.mkdir(parents=True, exist_ok=True)
        joined = pycolmap.triangulate_points(
            first, str(database), str(image_dir), str(into), clear_points=True, options=options
        )
        adjust(joined)
        checked = {k: verify(joined, j, base, database, bridges) for k, j in joins.items()}
        newly = {k: j for k, j in checked.items() if j.refused}
        if not newly:
            # a model whose images all went into the first adds nothing more
            kept = [m for m in rest if _registered(m) - _registered(joined)]
            return [joined, *kept], [*checked.values(), *refused.values()]
        refused.update(newly)


def adjust(rec: pycolmap.Reconstruction) -> None:
    """A global bundle adjustment of every registered image and point, through the adjuster
    itself: ``pycolmap.bundle_adjustment`` logs past the quiet level (colmaplog.py)."""
    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.THREE_POINTS)
    pycolmap.create_default_bundle_adjuster(options, config, rec).solve()
