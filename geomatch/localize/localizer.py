"""One photo localized against an open project: candidates, matching, 2D-3D lifting, pose.

For each photo: choose the model images to match it with (:meth:`Localizer.candidates`: VLAD
retrieval over the project's own features, the nearest cameras to its GPS fix when the model is
georeferenced, and the most similar aerial images when the photo is a ground view of a project
flown from above, those pairs tiled as ``geomatch run`` tiles them), match each pair with the
project's matcher (``pairstep.match``, so tiling, the quarter-turn probe and ``auto``'s choice of
method are the pipeline's), lift the matches to 2D-3D correspondences through the model images'
observations and estimate the pose with pycolmap's absolute pose (sfm/absolute.py); the answer is
judged by :func:`.answer.judge`.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..options import DEFAULTS
from .answer import Localization, LocalizeOptions, describe, judge
from .project import Project, project_matcher

if TYPE_CHECKING:
    from ..metadata import ImageMeta
    from .absolute import Correspondences, Pose


QUERY = "\x00query"  # the photo's name in a planned pair: never a model image's name


@dataclass
class Evidence:
    """What one photo's matching left: the pairs (for ``add``) and the 2D-3D correspondences
    (merged, and per pair)."""

    pairs: dict[str, Any]  # model image name -> pairstep.PairMatches
    correspondences: Correspondences
    parts: list[Correspondences]


class Localizer:
    """A project opened for localization: its model, observations, images and matcher, kept for
    every photo of one call (the model images' features are computed once)."""

    def __init__(
        self,
        project: Project,
        options: LocalizeOptions,
        matcher: Any = None,
        aerial: Collection[str] | None = None,
    ) -> None:
        import pycolmap

        from ..imagefolder import Images
        from .absolute import Observations

        self.project, self.options = project, options
        self.matcher = matcher if matcher is not None else project_matcher(project)
        self.rec = pycolmap.Reconstruction(str(project.model_dir))
        self.observations = {im.name: Observations.of(im) for im in self.rec.images.values() if im.has_pose}
        # images with too few observed points cannot lift enough matches to help
        self.names = sorted(n for n, o in self.observations.items() if len(o.point3D_ids) >= 10)
        from ..metadata import read_metadata

        self.images = Images(project.images_dir)
        self.metas = {
            n: read_metadata(project.images_dir / n) for n in self.names if (project.images_dir / n).is_file()
        }
        self.names = [n for n in self.names if n in self.metas]
        if aerial is None:
            recorded = project.summary.get("aerial")
            aerial = (
                recorded
                if isinstance(recorded, list)
                else [n for n in self.names if self.metas[n].aerial_hint]
            )
        self.aerial = set(aerial) & set(self.names)
        from ..sfm.upright import image_up

        self.unvouched = (
            unvouched_cameras(project, self.rec, image_up(self.metas, survey=False))
            if self.aerial and len(self.aerial) < len(self.names)
            else frozenset()
        )
        self.frame = project.frame()
        self._descriptors: list[np.ndarray] | None = None
        self._sparse: Any = None

    # -- candidates
    def model_descriptors(self) -> list[np.ndarray]:
        if self._descriptors is None:
            self._descriptors = [self.local_descriptors(self.images[n]) for n in self.names]
        return self._descriptors

    def local_descriptors(self, image: np.ndarray) -> np.ndarray:
        if self._sparse is None:
            from ..matching.variants import for_pair

            # the plain pairs' own sparse matcher when they are matched by anchors alone (``auto``
            # on a ground project: fewer keypoints), so the photo's and the model images'
            # features serve retrieval and matching both, each extracted once
            plain = for_pair(self.matcher, False, bool(self.aerial))
            self._sparse = plain if plain.config.method == "sparse" else self.matcher.derive(method="sparse")
        sparse = self._sparse
        feats = sparse.features(image)[sparse.config.sparse].sparse
        assert feats is not None
        return np.asarray(feats.descriptors.float().cpu().numpy())

    def candidates(
        self, image: np.ndarray, meta: ImageMeta, aerial_photo: bool
    ) -> tuple[list[str], list[str]]:
        """The model images to match the photo with, best first, in two stages: the plain pairs
        (retrieval's top ``max_candidates`` of the images on the photo's side, air or ground,
        then the nearest cameras to its GPS fix) and the tiled ones (for a ground photo of a
        project with aerial images, the ``aerial_candidates`` most similar aerial images, or
        the nearest to its fix). A tiled pair costs several matchings (five crops at most), so
        the second stage runs only when the first does not localize the photo confidently."""
        from ..pipeline.retrieval import vlad

        opts = self.options
        vectors = vlad([*self.model_descriptors(), self.local_descriptors(image)])
        scores = vectors[:-1] @ vectors[-1]
        ranked = [self.names[i] for i in np.argsort(-scores, kind="stable")]
        tiles = not aerial_photo and bool(self.aerial)  # ground photo x aerial image: a tiled pair
        same_side = [n for n in ranked if not tiles or n not in self.aerial]
        other_side = [n for n in ranked if tiles and n in self.aerial]
        plain = same_side[: opts.max_candidates]
        tiled = other_side[: opts.aerial_candidates]
        if self.frame is not None and meta.lat_lon is not None and opts.gps_candidates > 0:
            lat, lon = meta.lat_lon
            here = self.frame.from_geodetic(lat, lon, meta.altitude_m if meta.altitude_m is not None else 0.0)
            centres = {
                n: np.asarray(self.rec.find_image_with_name(n).projection_center(), np.float64)
                for n in self.names
            }

            def near(names: list[str]) -> list[str]:
                return sorted(names, key=lambda n: float(np.linalg.norm(centres[n][:2] - here[:2])))

            plain += [n for n in near(same_side) if n not in plain][: opts.gps_candidates]
            tiled += [n for n in near(other_side) if n not in tiled][: opts.aerial_candidates]
        return plain, tiled

    # -- matching and pose
    def evidence(
        self, image: np.ndarray, chosen: Sequence[str], aerial_photo: bool, into: Evidence | None = None
    ) -> Evidence:
        """The photo matched with ``chosen`` (pairs planned and tiled as ``geomatch run`` plans
        them), the matches lifted to 2D-3D; added to ``into``'s when given."""
        from ..imageio import snap_radius
        from ..pipeline import pair_sources as pairing
        from ..pipeline.match_pairs import match
        from .absolute import lift, merge

        aerial = set(self.aerial) | ({QUERY} if aerial_photo else set())
        tiling = str(self.project.run_options.get("tiling", DEFAULTS["tiling"]))
        planned = pairing.finalize([(QUERY, n) for n in chosen], aerial, tiling)
        resize = self.matcher.config.resize
        pairs = dict(into.pairs) if into is not None else {}
        parts = list(into.parts) if into is not None else []
        for pair in planned:
            name = pair.name1
            model_image = self.images[name]
            m = match(self.matcher, pair, image, model_image)
            pairs[name] = m
            order = np.argsort(-np.asarray(m.scores), kind="stable")
            radius = snap_radius(self.options.lift_radius, resize, max(model_image.shape[:2]))
            parts.append(lift(m.keypoints0[order], m.keypoints1[order], self.observations[name], radius))
        query_radius = snap_radius(1.0, resize, max(image.shape[:2]))
        return Evidence(pairs, merge(parts, query_radius), parts)

    def camera_for(self, meta: ImageMeta) -> tuple[Any, str]:
        """The photo's intrinsics: a model camera calibrated on an image of the same device when
        there is one (the mapper refined it), else its EXIF focal length, else a guess that the
        pose estimation refines."""
        import pycolmap

        from ..sfm.colmapdb import CAMERA_MODEL, default_focal

        if meta.has_device:
            for n in self.names:
                if self.metas[n].device == meta.device:
                    calibrated = self.rec.cameras[self.rec.find_image_with_name(n).camera_id]
                    return copy.copy(calibrated), "model"
        focal = meta.focal_px or default_focal(meta.width, meta.height)
        cam = pycolmap.Camera.create_from_model_name(0, CAMERA_MODEL, focal, meta.width, meta.height)
        return cam, "exif" if meta.focal_px else "estimated"

    def localize(self, photo: Path) -> tuple[Localization, Evidence | None]:
        from ..imageio import read_image, snap_radius
        from ..metadata import read_metadata
        from .absolute import Correspondences

        t0 = time.perf_counter()
        photo = Path(photo)
        image = read_image(photo)
        meta = read_metadata(photo)
        aerial_photo = bool(meta.aerial_hint)
        plain, tiled = self.candidates(image, meta, aerial_photo)
        camera, focal_source = self.camera_for(meta)
        threshold = max(
            snap_radius(self.options.max_error, self.matcher.config.resize, max(image.shape[:2])), 1.0
        )
        ev: Evidence | None = None
        out: Localization | None = None
        pose = None
        matched: list[str] = []
        first = max(1, self.options.first_candidates)
        for stage in (plain[:first], plain[first:], tiled):
            if not stage or (out is not None and out.confidence == "high"):
                continue
            ev = self.evidence(image, stage, aerial_photo, ev)
            matched += stage
            pose = self.pose(ev.correspondences, camera, threshold, focal_source == "estimated")
            support = self.support_of(ev, pose, camera, threshold) if pose is not None else None
            out = judge(photo.name, pose, ev.correspondences, self.options, matched, support, self.unvouched)
        if out is None:  # a model with no image to match
            out = judge(photo.name, None, Correspondences.empty(), self.options, [])
        out.focal_source = focal_source
        if pose is not None and out.localized:
            out.cam_from_world, out.center, out.camera = describe(pose)
            if self.frame is not None:
                from ..geo.placement import wgs84

                R = pose.cam_from_world.rotation.matrix().T
                out.wgs84 = wgs84(self.frame, pose.centre, R)
        out.seconds = time.perf_counter() - t0
        return out, ev

    def support_of(self, ev: Evidence, pose: Pose, camera: Any, threshold: float) -> dict[str, int]:
        """Per model image, how many of its own 2D-3D correspondences the pose reprojects within
        ``threshold``: the images that independently agree with it (a wrong pose fitted to one
        image's coherent but wrong matches, a facade's repeated windows say, finds no second)."""
        from .absolute import reprojection_errors

        out: dict[str, int] = {}
        for part in ev.parts:
            if not len(part):
                continue
            xyz = np.array([self.rec.points3D[int(i)].xyz for i in part.point3D_ids], np.float64)
            errors = reprojection_errors(pose.cam_from_world, pose.camera, part.points2D, xyz)
            name = part.images[0]
            out[name] = out.get(name, 0) + int((errors <= threshold).sum())
        return out

    def pose(self, corr: Correspondences, camera: Any, threshold: float, estimate_focal: bool) -> Pose | None:
        from .absolute import estimate_pose

        if len(corr) < 4:
            return None
        xyz = np.array([self.rec.points3D[int(i)].xyz for i in corr.point3D_ids], np.float64)
        return estimate_pose(corr.points2D, xyz, camera, threshold, estimate_focal)


def unvouched_cameras(
    project: Project, rec: Any, up: Mapping[str, np.ndarray] | None = None
) -> frozenset[str]:
    """The model's cameras that their own pairs in the project's database do not vouch for
    (modelagree.unvouched_in_steps, over the pairs the view-graph checks keep): a photo placed against them
    alone is not localized (:func:`.answer.judge`). Asked only of projects with aerial images,
    whose mapping is held to its pairs: an air-to-ground model can hold a block of cameras turned
    tens of degrees on right pairs, and a photo localized against that block is as far off.
    ``up``: the photos' up where they know it, as the run's view graph had it (upright.py)."""
    from ..sfm.modelagree import unvouched_in_steps
    from ..sfm.viewgraph_filter import kept_pairs

    report = kept_pairs(str(project.database), up)
    return frozenset(unvouched_in_steps(rec, report.kept_rotations, report.kept_inliers))
