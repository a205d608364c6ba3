"""A project's COLMAP database as the pipeline's stages write it: its images registered, the
planned pairs not matched yet, and a matched pair written (consolidated, verified, one
transaction)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

from .imageio import snap_radius
from .metadata import ImageMeta
from .sfm.colmapdb import ColmapDatabase, PairWrite, PreparedPair, seeded_verification
from .sfm.pairs import Pair

if TYPE_CHECKING:
    from .pairstep import PairMatches


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
# matches wholesale (brighton_beach's originals lost a quarter of their points to it), so from there
# the threshold follows the network's pixel.
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
