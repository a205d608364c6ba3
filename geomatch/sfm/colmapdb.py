"""The COLMAP database writer: the only code that writes ``database.db``.

Layout is COLMAP's own (pycolmap.Database), so COLMAP's GUI and command line read it: one camera
per device (EXIF focal length as a prior, else COLMAP's 1.2 x max(width, height) guess), a
trivial rig and a frame per image (what COLMAP's own importer writes since rigs exist),
keypoints in COLMAP's convention (pixel centre at +0.5), raw matches and the verified two-view
geometry of each pair.

A pair is written in one transaction: both images' keypoint lists (append-only, see tracks.py),
the matches and the two-view geometry. A pair already present is left untouched, so replaying
a write after a crash is harmless.
"""

from __future__ import annotations

import sqlite3
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path
from typing import SupportsInt

import numpy as np
import pycolmap

from ..metadata import ImageMeta
from .tracks import snap, unique_matches

CAMERA_MODEL = "SIMPLE_RADIAL"
_DEVICES_TABLE = (
    "CREATE TABLE IF NOT EXISTS geomatch_devices (device TEXT PRIMARY KEY, camera_id INTEGER NOT NULL)"
)
COLMAP_OFFSET = 0.5  # COLMAP pixel centres sit at +0.5 of ours (OpenCV's)


@dataclass(frozen=True)
class PairWrite:
    name0: str
    name1: str
    matches: int  # written, after snapping and de-duplication
    inliers: int  # of the verified two-view geometry
    config: str  # COLMAP's two-view configuration name
    skipped: bool = False  # already in the database: nothing written


@dataclass
class PreparedPair:
    """A pair as :meth:`ColmapDatabase.prepare_pair` leaves it for :meth:`ColmapDatabase.commit_pair`:
    keypoints in COLMAP's convention, ids in COLMAP's order (smaller first), the matches indexing
    each image's list as it was read (``base`` keypoints) followed by the pair's ``new`` ones."""

    image_id0: int
    image_id1: int
    name0: str
    name1: str
    base0: int
    base1: int
    new0: np.ndarray
    new1: np.ndarray
    matches: np.ndarray  # (M, 2) uint32
    tvg: pycolmap.TwoViewGeometry
    radius0: float
    radius1: float
    present: bool = False  # the pair was in the database when it was prepared


def default_focal(width: int, height: int) -> float:
    return 1.2 * max(width, height)  # COLMAP's guess without EXIF


VERIFICATION_SEED = 0


def seeded_verification() -> pycolmap.TwoViewGeometryOptions:
    """COLMAP's verification options with a fixed RANSAC seed (COLMAP draws a new one per call):
    the same matches give the same inliers, so a pair written again (a retried job, a re-run, two
    methods that answer a pair alike) is written identically, and two runs differ only where
    their matches do."""
    options = pycolmap.TwoViewGeometryOptions()
    options.ransac.random_seed = VERIFICATION_SEED
    return options


class ColmapDatabase:
    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.db = pycolmap.Database.open(str(self.path))
        self._devices: dict[tuple[object, ...], int] = {}

    def close(self) -> None:
        self.db.close()

    def __enter__(self) -> ColmapDatabase:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- cameras and images -------------------------------------------------------------------
    def _camera_for(self, meta: ImageMeta, shared: bool) -> int:
        """A device's images share one camera; without a device in EXIF each image gets its own
        (COLMAP's default), since unrelated photos of one size need not share intrinsics."""
        focal = meta.focal_px or default_focal(meta.width, meta.height)
        if shared:
            key: tuple[object, ...] = meta.device
            if key in self._devices:
                return self._devices[key]
            known = self._stored_devices().get(repr(key))  # a camera written by an earlier run
            if known is not None and self.db.exists_camera(known):
                self._devices[key] = known
                return known
        cam = pycolmap.Camera.create_from_model_name(0, CAMERA_MODEL, focal, meta.width, meta.height)
        cam.has_prior_focal_length = meta.focal_px is not None
        with pycolmap.DatabaseTransaction(self.db):
            cam_id = self.db.write_camera(cam)
            cam.camera_id = cam_id
            rig = pycolmap.Rig()
            rig.add_ref_sensor(cam.sensor_id)
            self.db.write_rig(rig)
        if shared:
            self._devices[meta.device] = cam_id
            with closing(sqlite3.connect(self.path)) as con, con:
                con.execute(_DEVICES_TABLE)
                con.execute(
                    "INSERT OR REPLACE INTO geomatch_devices VALUES (?, ?)", (repr(meta.device), cam_id)
                )
        return cam_id

    def _stored_devices(self) -> dict[str, int]:
        """Device -> camera id, kept in a table of our own (COLMAP ignores tables it does not know)
        so that images added by a later run join their device's camera."""
        with closing(sqlite3.connect(self.path)) as con, con:
            con.execute(_DEVICES_TABLE)
            return {d: int(c) for d, c in con.execute("SELECT device, camera_id FROM geomatch_devices")}

    def add_image(self, name: str, meta: ImageMeta, share_camera: bool | None = None) -> int:
        """Idempotent by name. ``share_camera`` None: share when EXIF names the device."""
        existing = self.db.read_image_with_name(name) if self.db.exists_image(name) else None
        if existing is not None:
            return int(existing.image_id)
        shared = meta.has_device if share_camera is None else share_camera
        cam_id = self._camera_for(meta, shared)
        rig_id = next(r.rig_id for r in self.db.read_all_rigs() if r.ref_sensor_id.id == cam_id)
        with pycolmap.DatabaseTransaction(self.db):
            image_id = self.db.write_image(pycolmap.Image(name=name, camera_id=cam_id))
            image = self.db.read_image(image_id)
            frame = pycolmap.Frame()
            frame.rig_id = rig_id
            frame.add_data_id(image.data_id)
            self.db.write_frame(frame)
        return int(image_id)

    def image_id(self, name: str) -> int | None:
        """The id of the image called ``name``; None when the database does not hold it."""
        image = self.db.read_image_with_name(name) if self.db.exists_image(name) else None
        return int(image.image_id) if image is not None else None

    def image_names(self) -> list[str]:
        """The names of the images the database holds, in its order."""
        return [im.name for im in self.db.read_all_images()]

    def pose_priors(self) -> int:
        """How many images carry a pose prior (their GPS fix)."""
        return int(self.db.num_pose_priors())

    def camera(self, image_id: int) -> pycolmap.Camera:
        return self.db.read_camera(self.db.read_image(image_id).camera_id)

    def keypoints(self, image_id: int) -> np.ndarray:
        """(N, 2) keypoints in OUR convention (pixel centres at integers)."""
        if not self.db.exists_keypoints(image_id):
            return np.zeros((0, 2), np.float32)
        return self.db.read_keypoints(image_id)[:, :2] - COLMAP_OFFSET

    # -- pairs -------------------------------------------------------------------------------
    def has_pair(self, image_id0: int, image_id1: int) -> bool:
        """Whether the pair is written, either order; a pair written with zero matches is (a
        matcher that found nothing is an answer too, not a reason to match again)."""
        return bool(self.db.exists_matches(image_id0, image_id1))

    def matches(self, image_id0: int, image_id1: int) -> np.ndarray:
        """(N, 2) keypoint indices of the pair's matches (image0's, image1's)."""
        return np.asarray(self.db.read_matches(image_id0, image_id1)).reshape(-1, 2)

    def inlier_matches(self, image_id0: int, image_id1: int) -> np.ndarray:
        """(N, 2) keypoint indices of the pair's matches its verified geometry keeps."""
        return np.asarray(self.db.read_two_view_geometry(image_id0, image_id1).inlier_matches).reshape(-1, 2)

    def write_pair(
        self,
        image_id0: int,
        image_id1: int,
        keypoints0: np.ndarray,
        keypoints1: np.ndarray,
        scores: np.ndarray,
        radius0: float,
        radius1: float,
        options: pycolmap.TwoViewGeometryOptions | None = None,
    ) -> PairWrite:
        """Snap, de-duplicate, verify and write one pair, all or nothing; a no-op when present.

        Points are in our convention (pixel centres at integers), best first is not required:
        they are ordered by score here so the best match of a snapped cluster is the one kept.
        """
        prepared = self.prepare_pair(
            image_id0, image_id1, keypoints0, keypoints1, scores, radius0, radius1, options
        )
        return self.commit_pair(prepared)

    def prepare_pair(
        self,
        image_id0: int,
        image_id1: int,
        keypoints0: np.ndarray,
        keypoints1: np.ndarray,
        scores: np.ndarray,
        radius0: float,
        radius1: float,
        options: pycolmap.TwoViewGeometryOptions | None = None,
    ) -> PreparedPair:
        """The pair snapped onto its images' keypoints as they are now and verified, written by
        nothing: a database opened without the writer lock can prepare, so that COLMAP's
        verification (most of a write) runs beside other workers' writes, and only
        :meth:`commit_pair` needs the lock."""
        if not (len(keypoints0) == len(keypoints1) == len(scores)):
            raise ValueError(
                f"pair ({image_id0}, {image_id1}): {len(keypoints0)}, {len(keypoints1)} keypoints and "
                f"{len(scores)} scores; one of each per match"
            )
        name0 = self.db.read_image(image_id0).name
        name1 = self.db.read_image(image_id1).name
        if image_id0 > image_id1:  # COLMAP stores pairs with the smaller id first
            image_id0, image_id1 = image_id1, image_id0
            keypoints0, keypoints1 = keypoints1, keypoints0
            radius0, radius1 = radius1, radius0
            name0, name1 = name1, name0
        if self.has_pair(image_id0, image_id1):
            empty = np.zeros((0, 2), np.float32)
            return PreparedPair(
                image_id0, image_id1, name0, name1, 0, 0, empty, empty, np.zeros((0, 2), np.uint32),
                pycolmap.TwoViewGeometry(), radius0, radius1, present=True,
            )  # fmt: skip
        order = np.argsort(-np.asarray(scores), kind="stable")
        p0 = np.asarray(keypoints0, np.float32)[order] + COLMAP_OFFSET
        p1 = np.asarray(keypoints1, np.float32)[order] + COLMAP_OFFSET
        kp0 = self.keypoints(image_id0) + COLMAP_OFFSET
        kp1 = self.keypoints(image_id1) + COLMAP_OFFSET
        i0, kp0_new = snap(kp0, p0, radius0)
        i1, kp1_new = snap(kp1, p1, radius1)
        keep = unique_matches(i0, i1)
        matches = np.stack([i0[keep], i1[keep]], 1).astype(np.uint32)
        # the new keypoints no match of this pair uses are dropped again (they would be orphans)
        kp0_new, matches[:, 0] = _drop_unused(kp0_new, len(kp0), matches[:, 0])
        kp1_new, matches[:, 1] = _drop_unused(kp1_new, len(kp1), matches[:, 1])
        tvg = self._verify(image_id0, image_id1, kp0_new, kp1_new, matches, options)
        return PreparedPair(
            image_id0, image_id1, name0, name1, len(kp0), len(kp1),
            kp0_new[len(kp0):], kp1_new[len(kp1):], matches, tvg, radius0, radius1,
        )  # fmt: skip

    def commit_pair(self, p: PreparedPair) -> PairWrite:
        """A prepared pair written in one transaction; a no-op when the pair is there. Where other
        writers appended keypoints to its images since it was prepared, its new keypoints are
        snapped onto theirs first (:func:`rebase`), so that tracks through those images join as
        if the pairs had been written one after the other."""
        if p.present or self.has_pair(p.image_id0, p.image_id1):
            return PairWrite(p.name0, p.name1, 0, 0, "", skipped=True)
        kp0 = self.keypoints(p.image_id0) + COLMAP_OFFSET
        kp1 = self.keypoints(p.image_id1) + COLMAP_OFFSET
        new0, new1, matches, inliers = p.new0, p.new1, p.matches, p.tvg.inlier_matches
        if len(kp0) != p.base0 or len(kp1) != p.base1:
            new0, new1, matches, inliers = rebase(p, kp0, kp1)
        tvg = p.tvg
        tvg.inlier_matches = inliers
        with pycolmap.DatabaseTransaction(self.db):
            for image_id, old, new in ((p.image_id0, kp0, new0), (p.image_id1, kp1, new1)):
                full = np.concatenate([old, new]).astype(np.float32)
                if not self.db.exists_keypoints(image_id):
                    self.db.write_keypoints(image_id, full)
                elif len(new):  # append-only: a longer list is the only possible change
                    self.db.update_keypoints(image_id, full)
            self.db.write_matches(p.image_id0, p.image_id1, matches)
            self.db.write_two_view_geometry(p.image_id0, p.image_id1, tvg)
        return PairWrite(p.name0, p.name1, len(matches), len(inliers), _config_name(tvg.config))

    def _verify(
        self,
        image_id0: int,
        image_id1: int,
        kp0: np.ndarray,
        kp1: np.ndarray,
        matches: np.ndarray,
        options: pycolmap.TwoViewGeometryOptions | None,
    ) -> pycolmap.TwoViewGeometry:
        if len(matches) < 8:
            tvg = pycolmap.TwoViewGeometry()
            tvg.config = pycolmap.TwoViewGeometryConfiguration.DEGENERATE
            return tvg
        return pycolmap.estimate_two_view_geometry(
            self.camera(image_id0),
            kp0.astype(np.float64),
            self.camera(image_id1),
            kp1.astype(np.float64),
            matches,
            options or seeded_verification(),
        )

    def stats(self) -> dict[str, int]:
        return {
            "images": int(self.db.num_images()),
            "cameras": int(self.db.num_cameras()),
            "keypoints": int(self.db.num_keypoints()),
            "matched_pairs": int(self.db.num_matched_image_pairs()),
            "verified_pairs": int(self.db.num_verified_image_pairs()),
            "matches": int(self.db.num_matches()),
            "inlier_matches": int(self.db.num_inlier_matches()),
        }


def _drop_unused(points: np.ndarray, n_old: int, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keep the old keypoints and only the new ones ``idx`` uses; renumber ``idx`` accordingly."""
    used_new = np.unique(idx[idx >= n_old])
    remap = np.arange(len(points))
    remap[used_new] = n_old + np.arange(len(used_new))
    return np.concatenate([points[:n_old], points[used_new]]), remap[idx].astype(np.uint32)


def _config_name(config: SupportsInt) -> str:
    try:
        return pycolmap.TwoViewGeometryConfiguration(int(config)).name
    except (TypeError, ValueError):
        return str(config)


def _rebase_side(
    current: np.ndarray, base: int, new: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Where a prepared pair's new keypoints of one image land in its list as it is now: an
    index per new keypoint, and the keypoints still new (appended after the current list)."""
    others = current[base:]
    idx, out = snap(others, new, radius)
    fresh = idx >= len(others)
    where = np.where(fresh, len(current) + idx - len(others), base + idx)
    return where, out[len(others) :]


def rebase(p: PreparedPair, kp0: np.ndarray, kp1: np.ndarray) -> tuple[np.ndarray, ...]:
    """(new0, new1, matches, inliers) of a prepared pair against the current keypoint lists
    ``kp0``/``kp1`` (COLMAP convention), which other writers lengthened since it was prepared:
    its new keypoints within the snap radius of theirs become theirs, the rest are appended
    after them; matches that now fall on one keypoint keep the first (the best), and the
    verified inliers follow their matches. The lists are append-only, so the first ``base``
    keypoints are the ones the pair was prepared against."""
    where0, fresh0 = _rebase_side(kp0, p.base0, p.new0, p.radius0)
    where1, fresh1 = _rebase_side(kp1, p.base1, p.new1, p.radius1)

    def remap(idx: np.ndarray, base: int, where: np.ndarray) -> np.ndarray:
        idx = idx.astype(np.int64)
        out = idx.copy()
        new = idx >= base
        out[new] = where[idx[new] - base]
        return out

    m0 = remap(p.matches[:, 0], p.base0, where0)
    m1 = remap(p.matches[:, 1], p.base1, where1)
    keep = unique_matches(m0, m1)
    matches = np.stack([m0[keep], m1[keep]], 1).astype(np.uint32)
    fresh0, matches[:, 0] = _drop_unused(np.concatenate([kp0, fresh0]), len(kp0), matches[:, 0])
    fresh1, matches[:, 1] = _drop_unused(np.concatenate([kp1, fresh1]), len(kp1), matches[:, 1])
    inl = np.asarray(p.tvg.inlier_matches, np.int64).reshape(-1, 2)
    i0 = remap(inl[:, 0], p.base0, where0)
    i1 = remap(inl[:, 1], p.base1, where1)
    # an inlier is the row of its match (renumbered with the matches by _drop_unused); one whose
    # match fell onto an earlier match's keypoints went with it
    row = {k: i for i, k in enumerate(zip(m0[keep].tolist(), m1[keep].tolist(), strict=True))}
    rows = [row[k] for k in zip(i0.tolist(), i1.tolist(), strict=True) if k in row]
    inliers = matches[np.unique(np.asarray(rows, np.int64))] if rows else np.zeros((0, 2), np.uint32)
    return fresh0[len(kp0) :], fresh1[len(kp1) :], matches, inliers
