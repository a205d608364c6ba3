"""A project's COLMAP database as the pipeline's stages fill it: its images registered, the
planned pairs not matched yet, and a matched pair (:class:`PairMatches`) written: consolidated,
verified, one transaction."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..epipolar.geometry import fundamental_from_matches
from ..imagefolder import PhotoScale
from ..imageio import snap_radius
from ..matching.config import MatchResult
from ..matching.tiling import TiledMatches
from ..metadata import ImageMeta
from ..sfm.colmapdb import ColmapDatabase, PairWrite, PreparedPair, seeded_verification
from .pair_sources import Pair


@dataclass
class PairMatches:
    """One pair's matches, in each image's original pixels (pixel centres at integers): what the
    match step hands the write."""

    keypoints0: np.ndarray
    keypoints1: np.ndarray
    scores: np.ndarray
    sizes: tuple[tuple[int, int], tuple[int, int]]  # (width, height) of image0 and image1
    tiled: bool = False
    # None: an image was matched turned (the source's F is in the turned frames), or the matches
    # were read back from where a caller stored them
    source: MatchResult | TiledMatches | None = None
    crops: int = 0  # aerial crops matched (tiled pairs; 0 when the matches were read back)

    def __len__(self) -> int:
        return int(self.keypoints0.shape[0])

    def in_photo_pixels(self, photo0: PhotoScale | None, photo1: PhotoScale | None) -> PairMatches:
        """The matches of images read at a working size (imagefolder.Images.to_photo: x and y
        scale to the photo, its size; None: read as stored) in the photos' own pixels, which
        the database and the mapper speak. The source goes: its F is in working pixels."""
        if photo0 is None and photo1 is None:
            return self
        k0, k1 = self.keypoints0, self.keypoints1
        sizes = list(self.sizes)
        if photo0 is not None:
            k0, sizes[0] = _to_photo(k0, photo0[:2]), photo0[2]
        if photo1 is not None:
            k1, sizes[1] = _to_photo(k1, photo1[:2]), photo1[2]
        return PairMatches(k0, k1, self.scores, (sizes[0], sizes[1]), self.tiled, None, self.crops)

    @property
    def F(self) -> np.ndarray:
        """x1^T F x0 = 0 in original pixels: the matcher's (a tiled pair's is fitted over its
        merged matches on first use); without a source, fitted over the matches."""
        if self.source is None:
            return fundamental_from_matches(self.keypoints0, self.keypoints1)
        return self.source.F


def _to_photo(points: np.ndarray, scale: tuple[float, float]) -> np.ndarray:
    """Working pixels to photo pixels, pixel centres at integers on both."""
    s = np.asarray(scale, np.float64)
    return ((np.asarray(points, np.float64) + 0.5) * s - 0.5).astype(points.dtype, copy=False)


def register(
    db: ColmapDatabase, names: Sequence[str], metas: Mapping[str, ImageMeta], share_camera: bool | None
) -> dict[str, int]:
    """Every image in the COLMAP database (a no-op for those there); their ids by name."""
    return {n: db.add_image(n, metas[n], share_camera) for n in names}


def unmatched(db: ColmapDatabase, ids: Mapping[str, int], planned: Sequence[Pair]) -> list[Pair]:
    """The planned pairs not in the database yet (a pair stored with zero matches is matched)."""
    return [p for p in planned if not db.has_pair(ids[p.name0], ids[p.name1])]


# a tiled pair verified with fewer inliers is written without a geometry (matches kept, nothing
# for the mapper): an aerial image's crops against a street photo find a few dozen coherent wrong
# matches where the two share nothing, while right tiled pairs verify with more (the counts behind
# the bound: docs/benchmarks.md). COLMAP's own floor, 15, is for detector matches of plain pairs
TILED_MIN_INLIERS = 60


# COLMAP verifies with a 4 photo-pixel RANSAC threshold, made for SIFT found at the photo's own size.
# Our matches are found at the network's input size and are as precise as its pixel: every set this
# project was tuned on (photos up to 2000 px at the default 640) met that threshold at up to 3.1 photo
# pixels per network pixel, i.e. at 1.28 network pixels. On larger photos (a drone's 4000 px
# originals: 6.25 photo px per network px) 4 photo pixels are 0.64 network pixels and reject right
# matches wholesale (what brighton_beach's originals lost to it: docs/benchmarks.md, "Drone surveys
# beside COLMAP SIFT"), so from there the threshold follows the network's pixel.
VERIFY_NETWORK_PX = 1.28


def verification_error(resize: int | None, long0: int, long1: int, photo_px: float = 4.0) -> float:
    """The verification's RANSAC threshold in photo pixels for a pair found at ``resize`` (None:
    full size) on photos whose longer sides are ``long0`` and ``long1``."""
    if not resize:
        return photo_px
    return max(photo_px, VERIFY_NETWORK_PX * max(long0, long1) / resize)


def prepare(
    db: ColmapDatabase, id0: int, id1: int, m: PairMatches, radius: float, resize: int | None
) -> PreparedPair:
    """The pair snapped and verified against the database as it is now (no writer lock needed):
    what :func:`commit` writes."""
    options = seeded_verification()
    # a tiled pair's aerial side was matched by crops of half its size, each at ``resize``
    found_at = resize * 2 if resize and m.tiled else resize
    options.ransac.max_error = verification_error(
        found_at, max(m.sizes[0]), max(m.sizes[1]), options.ransac.max_error
    )
    if m.tiled:
        options.min_num_inliers = TILED_MIN_INLIERS
    return db.prepare_pair(
        id0,
        id1,
        m.keypoints0,
        m.keypoints1,
        m.scores,
        snap_radius(radius, resize, max(m.sizes[0])),
        snap_radius(radius, resize, max(m.sizes[1])),
        options,
    )


def commit(db: ColmapDatabase, prepared: PreparedPair) -> PairWrite:
    """A prepared pair into the database (under the writer lock), one transaction; a no-op when
    the pair is there."""
    return db.commit_pair(prepared)


def write(
    db: ColmapDatabase, id0: int, id1: int, m: PairMatches, radius: float, resize: int | None
) -> PairWrite:
    """The pair into the COLMAP database (snapped within ``radius`` network pixels, verified,
    one transaction); a no-op when it is there."""
    return commit(db, prepare(db, id0, id1, m, radius, resize))
