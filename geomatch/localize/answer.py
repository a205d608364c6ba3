"""A localization's answer: the options that decide it, what it says, and how sure it is.

:func:`judge` turns a pose and its evidence into a :class:`Localization` with the thresholds of
:class:`LocalizeOptions`; a photo of another scene must come back not localized, never as a
confident wrong pose. Nothing here imports torch or pycolmap: the API process reads the options and
the answers.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ..options import DEFAULTS

if TYPE_CHECKING:
    from .absolute import Correspondences, Pose


@dataclass
class LocalizeOptions:
    """How a photo is localized. The defaults are tuned on the Strecha tuning scenes and the
    synthetic air-to-ground tuning seed (bench/localize.py; docs/benchmarks.md, "Localization")."""

    # model images matched per photo by retrieval (the plain pairs): 4 localize the tuning scenes'
    # photos with inliers to spare, and each further pair costs one more matching
    max_candidates: int = 4
    # the plain candidates are matched best first: this many, then the others only when those
    # did not localize the photo confidently (two model images are what "high" needs, and a
    # photo that two of its best matches place confidently is rarely moved by more)
    first_candidates: int = 2
    # added when the photo has a GPS fix and the model is georeferenced: its nearest cameras
    gps_candidates: int = 2
    # for a ground photo of a project with aerial images: the most similar aerial images, matched
    # tiled, and only when the plain pairs did not localize the photo confidently (a tiled pair
    # is several matchings, many times a plain pair's cost)
    aerial_candidates: int = 1
    # PnP inliers below which a photo is not localized: COLMAP's own bar for registering an image
    # (the mapper's default, options.MIN_POSE_INLIERS): photos of other scenes stay well below it,
    # true photos reach it even against a model's aerial images alone (docs/benchmarks.md,
    # "Localization")
    min_inliers: int = 30
    # inliers over the correspondences tried: another scene's matches scatter over the model, a
    # true photo's nearly all fit the pose
    min_inlier_ratio: float = 0.25
    # a confident answer ("high") needs this many inliers, with at least ``high_min_images``
    # model images agreeing with the pose through their own matches (one image's coherent but
    # wrong matches, repeated windows say, can fit a wrong pose; two images' rarely do)
    high_min_inliers: int = 100
    high_min_images: int = 2
    # RANSAC's reprojection threshold in network pixels (the matcher's working size, as
    # ``snap_radius``): scaled to the photo's pixels, since a match is no more precise than the
    # resolution it was found at
    max_error: float = 4.0
    # a match counts as seeing a model point when it lands this close to the point's observation
    # in the model image, network pixels (the pipeline's default snap radius)
    lift_radius: float = DEFAULTS["snap_radius"]


@dataclass
class Localization:
    name: str  # the photo's file name
    localized: bool
    reason: str | None  # why not localized (for a user), None when localized
    cam_from_world: dict[str, list[float]] | None  # {"qvec": [w, x, y, z], "tvec": [x, y, z]}, COLMAP's
    center: list[float] | None  # camera centre in the model frame
    wgs84: dict[str, float] | None  # {"lat", "lon", "alt", "heading_deg"} when the model is georeferenced
    inliers: int
    matches: int  # 2D-3D correspondences tried
    reprojection_error_px: float | None
    confidence: str  # "high" | "low" | "none"
    supporting_images: list[str]  # model images whose matches gave inliers
    camera: dict[str, Any] | None  # {"model", "width", "height", "params"}
    seconds: float
    candidates: list[str] = field(default_factory=list)  # model images the photo was matched with
    inlier_ratio: float = 0.0
    focal_source: str = ""  # "model" (a model camera of the same device), "exif", "estimated"

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def describe(pose: Any) -> tuple[dict[str, list[float]], list[float], dict[str, Any]]:
    """(cam_from_world as COLMAP writes it, centre, camera) of a pose."""
    x, y, z, w = (float(v) for v in pose.cam_from_world.rotation.quat)
    t = [float(v) for v in np.asarray(pose.cam_from_world.translation).reshape(3)]
    cam = pose.camera
    camera = {
        "model": cam.model.name,
        "width": int(cam.width),
        "height": int(cam.height),
        "params": [float(p) for p in cam.params],
    }
    return {"qvec": [w, x, y, z], "tvec": t}, [float(v) for v in pose.centre], camera


def judge(
    name: str,
    pose: Pose | None,
    corr: Correspondences,
    opts: LocalizeOptions,
    chosen: Sequence[str],
    support: dict[str, int] | None = None,
    unvouched: Collection[str] = (),
) -> Localization:
    """Localized or not, and how confident, from the pose's evidence (thresholds: LocalizeOptions).

    ``high``: enough inliers, with at least ``high_min_images`` model images each agreeing on
    the pose with a quarter of ``min_inliers`` of their own matches; ``low``: localized on less
    (one image's matches, or few inliers): usable, but a user should check it. ``support``: each
    model image's own correspondences that agree with the pose (``Localizer.support_of``); without
    it the merged correspondences' images count, which credit a point seen by several model
    images to the first only.

    ``unvouched``: model images whose own pairs do not vouch for their place in the model
    (modelagree.unvouched): a photo placed against them is placed where they are, right or
    not, so their support does not count, and a photo that the other images do not place on
    their own (``min_inliers``) is not localized. A model camera turned 31 deg off its true pose
    with its neighbour placed two held-back photos 9-10 % of the scene off, confidently."""
    tried = len(corr)
    base: dict[str, Any] = dict(
        name=name,
        cam_from_world=None,
        center=None,
        wgs84=None,
        matches=tried,
        camera=None,
        seconds=0.0,
        candidates=list(chosen),
    )
    if pose is None:
        why = (
            "no match with the model's 3D points"
            if tried < 4
            else f"no camera pose agrees with its {tried} matches to the model's 3D points"
        )
        return Localization(
            localized=False,
            reason=why + ": the photo does not seem to show this scene",
            inliers=0,
            reprojection_error_px=None,
            confidence="none",
            supporting_images=[],
            **base,
        )
    inliers = pose.num_inliers
    ratio = inliers / tried if tried else 0.0
    if support is None:
        support = {}
        for n, ok in zip(corr.images, pose.inliers, strict=True):
            if ok:
                support[n] = support.get(n, 0) + 1
    support = {n: k for n, k in support.items() if k > 0}
    supporting = sorted(support, key=lambda n: -support[n])
    reason: str | None = None
    other_scene = ": the photo does not seem to show this scene"
    if inliers < opts.min_inliers:
        reason = (
            f"only {inliers} of {tried} matches to the model agree on a pose (needs {opts.min_inliers})"
            + other_scene
        )
    elif ratio < opts.min_inlier_ratio:
        reason = (
            f"only {100 * ratio:.0f}% of its {tried} matches to the model agree on a pose "
            f"(needs {100 * opts.min_inlier_ratio:.0f}%)" + other_scene
        )
    vouched = {n: k for n, k in support.items() if n not in unvouched}
    if reason is None and sum(vouched.values()) < opts.min_inliers and len(vouched) < len(support):
        doubtful = sorted(n for n in support if n in unvouched)
        reason = (
            f"its pose rests on model cameras whose own pairs do not vouch for their place in the "
            f"model ({', '.join(doubtful)}); the others give it {sum(vouched.values())} inliers "
            f"(needs {opts.min_inliers}): the model cannot say where this photo is"
        )
    strong = [n for n in supporting if vouched.get(n, 0) >= opts.min_inliers // 4]
    if reason is not None:
        confidence = "none"
    elif inliers >= opts.high_min_inliers and len(strong) >= opts.high_min_images:
        confidence = "high"
    else:
        confidence = "low"
    return Localization(
        localized=reason is None,
        reason=reason,
        inliers=inliers,
        reprojection_error_px=pose.reprojection_error_px,
        confidence=confidence,
        supporting_images=supporting,
        inlier_ratio=ratio,
        **base,
    )
