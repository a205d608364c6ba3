"""Localize new photos against a project's model, without mapping the project again.

For each photo: choose the model images to match it with (:func:`candidates`: VLAD retrieval over
the project's own features, the nearest cameras to its GPS fix when the model is georeferenced,
and the most similar aerial images when the photo is a ground view of a project flown from
above, those pairs tiled as ``geomatch run`` tiles them), match each pair with the project's
matcher (``pairstep.match``, so tiling, the quarter-turn probe and ``auto``'s choice of method are
the pipeline's), lift the matches to 2D-3D correspondences through the model images'
observations and estimate the pose with pycolmap's absolute pose (sfm/absolute.py). The answer
says how sure it is (:func:`judge`): a photo of another scene must come back not localized, never
as a confident wrong pose.

Two layouts of a project are read: a ``geomatch run --out OUT`` folder (``database.db``,
``sparse/0``, ``summary.json`` naming the images folder, the options and the aerial images) and
a project stored by the service (``database.db``, ``images/``, ``model/sparse/0``,
``model/summary.json``); explicit ``model_dir`` / ``images_dir`` override either.
"""

from __future__ import annotations

import copy
import json
import shutil
import time
from collections.abc import Callable, Collection, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .options import DEFAULTS

if TYPE_CHECKING:  # the API process reads the options and answers without torch or pycolmap
    from .metadata import ImageMeta
    from .sfm.absolute import Correspondences, Pose


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


# -- the project --------------------------------------------------------------------------------
class LocalizeError(ValueError):
    """The project cannot be localized against: no model, no database, no images."""


@dataclass(frozen=True)
class Project:
    """Where a project's parts are and what its run recorded."""

    database: Path
    model_dir: Path
    images_dir: Path
    summary: dict[str, Any]

    @classmethod
    def find(cls, root: Path, model_dir: Path | None = None, images_dir: Path | None = None) -> Project:
        root = Path(root)
        if model_dir is None:
            model_dir = next(
                (
                    d
                    for d in (root / "sparse" / "0", root / "model" / "sparse" / "0")
                    if (d / "images.bin").is_file()
                ),
                None,
            )
        if model_dir is None or not (Path(model_dir) / "images.bin").is_file():
            raise LocalizeError(
                f"{root}: no model (sparse/0 or model/sparse/0): reconstruct the project first"
            )
        model_dir = Path(model_dir)
        summary_path = next(
            (p for p in (model_dir.parent.parent / "summary.json", root / "summary.json") if p.is_file()),
            None,
        )
        summary = json.loads(summary_path.read_text()) if summary_path is not None else {}
        if images_dir is None:
            recorded = summary.get("image_dir")
            images_dir = Path(recorded) if recorded else root / "images"
        if not Path(images_dir).is_dir():
            raise LocalizeError(f"{images_dir}: the project's images are not there (pass images_dir)")
        database = root / "database.db"
        if not database.is_file():
            raise LocalizeError(f"{root}: no COLMAP database (database.db)")
        return cls(database, model_dir, Path(images_dir), summary)

    @property
    def run_options(self) -> dict[str, Any]:
        """The options ``geomatch run`` recorded (empty for a service project: its caller knows)."""
        options = self.summary.get("options")
        return dict(options) if isinstance(options, dict) else {}

    def frame(self) -> Any:
        """The ENU frame the model is in, or None when it is not georeferenced."""
        from .geo.geodesy import EnuFrame

        origin = self.summary.get("origin")
        if not self.summary.get("georeferenced") or not isinstance(origin, dict):
            return None
        return EnuFrame(float(origin["lat"]), float(origin["lon"]), float(origin["alt"]))


def project_matcher(project: Project, features: Path | None = None) -> Any:
    """The matcher the project ran with (method, resize and matcher options of its summary), or
    the defaults for a project that recorded none; it reads the features in ``features`` (default:
    the run folder's own ``features/``) and writes none."""
    from .features.store import run_feature_store
    from .matching.matcher import config_from_options
    from .matching.stored import stored
    from .options import cache_budget

    recorded = project.run_options
    budget = cache_budget()
    options = {
        "method": recorded.get("method", DEFAULTS["method"]),
        "resize": recorded.get("resize", DEFAULTS["resize"]),
        "device": recorded.get("device", DEFAULTS["device"]),
        "cache_features_mb": budget.features_mb,
        "cache_anchors_mb": budget.anchors_mb,
        **dict(recorded.get("matcher") or {}),  # the run's further matcher and optimizer options
    }
    config = config_from_options(**options)
    # a run's folder keeps its features: the model images are read, not extracted again (and
    # the folder is left as it is: a photo's own features are not written into it)
    folder = Path(features) if features is not None else project.database.parent / "features"
    store = run_feature_store(folder, writable=False) if folder.is_dir() else None
    return stored(config, store)


# -- one photo ----------------------------------------------------------------------------------
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

        from .imagefolder import Images
        from .sfm.absolute import Observations

        self.project, self.options = project, options
        self.matcher = matcher if matcher is not None else project_matcher(project)
        self.rec = pycolmap.Reconstruction(str(project.model_dir))
        self.observations = {im.name: Observations.of(im) for im in self.rec.images.values() if im.has_pose}
        # images with too few observed points cannot lift enough matches to help
        self.names = sorted(n for n, o in self.observations.items() if len(o.point3D_ids) >= 10)
        from .metadata import read_metadata

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
            from .matching.variants import for_pair

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
        from .sfm.retrieval import vlad

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
        from .imageio import snap_radius
        from .pairstep import match
        from .sfm import pairs as pairing
        from .sfm.absolute import lift, merge

        aerial = set(self.aerial) | ({QUERY} if aerial_photo else set())
        tiling = str(self.project.run_options.get("tiling", DEFAULTS["tiling"]))
        planned = pairing.finalize([(QUERY, n) for n in chosen], aerial, tiling)
        resize = self.matcher.config.resize
        pairs = dict(into.pairs) if into is not None else {}
        parts = list(into.parts) if into is not None else []
        for pair in planned:
            name = pair.name1
            model_image = self.images[name]
            m = match(self.matcher, pair, image, model_image, aerial_project=bool(aerial))
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

        from .sfm.colmapdb import CAMERA_MODEL, default_focal

        if meta.has_device:
            for n in self.names:
                if self.metas[n].device == meta.device:
                    calibrated = self.rec.cameras[self.rec.find_image_with_name(n).camera_id]
                    return copy.copy(calibrated), "model"
        focal = meta.focal_px or default_focal(meta.width, meta.height)
        cam = pycolmap.Camera.create_from_model_name(0, CAMERA_MODEL, focal, meta.width, meta.height)
        return cam, "exif" if meta.focal_px else "estimated"

    def localize(self, photo: Path) -> tuple[Localization, Evidence | None]:
        from .imageio import read_image, snap_radius
        from .metadata import read_metadata
        from .sfm.absolute import Correspondences

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
            out = judge(photo.name, pose, ev.correspondences, self.options, matched, support)
        if out is None:  # a model with no image to match
            out = judge(photo.name, None, Correspondences.empty(), self.options, [])
        out.focal_source = focal_source
        if pose is not None and out.localized:
            out.cam_from_world, out.center, out.camera = describe(pose)
            if self.frame is not None:
                from .geo.placement import wgs84

                R = pose.cam_from_world.rotation.matrix().T
                out.wgs84 = wgs84(self.frame, pose.centre, R)
        out.seconds = time.perf_counter() - t0
        return out, ev

    def support_of(self, ev: Evidence, pose: Pose, camera: Any, threshold: float) -> dict[str, int]:
        """Per model image, how many of its own 2D-3D correspondences the pose reprojects within
        ``threshold``: the images that independently agree with it (a wrong pose fitted to one
        image's coherent but wrong matches, a facade's repeated windows say, finds no second)."""
        from .sfm.absolute import reprojection_errors

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
        from .sfm.absolute import estimate_pose

        if len(corr) < 4:
            return None
        xyz = np.array([self.rec.points3D[int(i)].xyz for i in corr.point3D_ids], np.float64)
        return estimate_pose(corr.points2D, xyz, camera, threshold, estimate_focal)


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
) -> Localization:
    """Localized or not, and how confident, from the pose's evidence (thresholds: LocalizeOptions).

    ``high``: enough inliers, with at least ``high_min_images`` model images each agreeing on
    the pose with a quarter of ``min_inliers`` of their own matches; ``low``: localized on less
    (one image's matches, or few inliers): usable, but a user should check it. ``support``: each
    model image's own correspondences that agree with the pose (:func:`support_of`); without it
    the merged correspondences' images count, which credit a point seen by several model images
    to the first only."""
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
    if inliers < opts.min_inliers:
        reason = f"only {inliers} of {tried} matches to the model agree on a pose (needs {opts.min_inliers})"
    elif ratio < opts.min_inlier_ratio:
        reason = (
            f"only {100 * ratio:.0f}% of its {tried} matches to the model agree on a pose "
            f"(needs {100 * opts.min_inlier_ratio:.0f}%)"
        )
    strong = [n for n in supporting if support[n] >= opts.min_inliers // 4]
    if reason is not None:
        confidence = "none"
    elif inliers >= opts.high_min_inliers and len(strong) >= opts.high_min_images:
        confidence = "high"
    else:
        confidence = "low"
    return Localization(
        localized=reason is None,
        reason=None if reason is None else reason + ": the photo does not seem to show this scene",
        inliers=inliers,
        reprojection_error_px=pose.reprojection_error_px,
        confidence=confidence,
        supporting_images=supporting,
        inlier_ratio=ratio,
        **base,
    )


# -- adding a photo to the project ---------------------------------------------------------------
def add_to_project(project: Project, photo: Path, evidence: Evidence, matcher: Any, snap: float) -> int:
    """The photo into the project's COLMAP database (its image row, keypoints and its verified
    matches to the model images it was matched with) and into its images folder, so a later
    reconstruct maps it (the mapper reads the photos: track refinement). Idempotent: an image and
    a pair already there are left as they are. Returns the photo's image id."""
    from .dbwrite import write
    from .metadata import read_metadata
    from .sfm.colmapdb import ColmapDatabase

    photo = Path(photo)
    dest = project.images_dir / photo.name
    if not dest.exists():
        shutil.copyfile(photo, dest)
    elif dest.read_bytes() != photo.read_bytes():
        raise LocalizeError(f"{photo.name}: the project has another image of that name")
    meta = read_metadata(dest)
    share = project.run_options.get("share_camera")
    with ColmapDatabase(project.database) as db:
        photo_id = db.add_image(photo.name, meta, share if isinstance(share, bool) else None)
        for name, m in evidence.pairs.items():
            image = db.db.read_image_with_name(name) if db.db.exists_image(name) else None
            if image is None or name == photo.name:
                continue
            other = int(image.image_id)
            write(db, photo_id, other, m, snap, matcher.config.resize)
    return photo_id


# -- the API --------------------------------------------------------------------------------------
def localize_photos(
    project_dir: Path,
    photos: Sequence[Path],
    options: LocalizeOptions | None = None,
    matcher: Any = None,
    add: bool = False,
    progress: Callable[[int, int], None] | None = None,
    *,
    model_dir: Path | None = None,
    images_dir: Path | None = None,
    aerial: Collection[str] | None = None,
) -> list[Localization]:
    """Each photo's pose in the project's model (one :class:`Localization` per photo, in order).

    ``matcher``: the project's (a service passes its own, with its feature store); default: the
    one the run recorded. ``add``: also put the photos into the project (:func:`add_to_project`).
    ``progress(done, total)`` is called after each photo. ``model_dir`` / ``images_dir``: where
    the model and the images are when the project's layout does not say (see the module's
    docstring); ``aerial``: the model's aerial images, when neither the summary nor their
    metadata says."""
    project = Project.find(Path(project_dir), model_dir, images_dir)
    localizer = Localizer(project, options or LocalizeOptions(), matcher, aerial)
    snap = float(project.run_options.get("snap_radius", DEFAULTS["snap_radius"]))
    results = []
    for k, photo in enumerate(photos):
        result, evidence = localizer.localize(Path(photo))
        if add and evidence is not None:
            add_to_project(project, Path(photo), evidence, localizer.matcher, snap)
        results.append(result)
        if progress is not None:
            progress(k + 1, len(photos))
    return results


def localizations_json(results: Sequence[Localization]) -> dict[str, Any]:
    """The one JSON document of ``geomatch localize --json``."""
    return {
        "photos": [r.to_json() for r in results],
        "localized": sum(r.localized for r in results),
        "total": len(results),
    }
