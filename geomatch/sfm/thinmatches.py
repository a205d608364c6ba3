"""A large survey's matches thinned before the global mapper, so that its memory stops growing
with the photos' keypoints.

Why: the global mapper re-triangulates every verified match and bundle-adjusts all of the points,
and the GPS priors' adjustment (geo/priorba.py) does so again; the memory of each grows with the
observations, and a dense matcher gives every photo of a survey thousands, so over a large flight
they outgrow a worker's budget (docs/benchmarks.md, "A thousand photos"), while a photo's pose is
fixed by far fewer points. So each photo keeps the keypoints that most of its pairs matched
(per_image_budget: a total for the project, never under a floor per photo), and the verified
matches between two kept keypoints are all the mapper's private copy of the database keeps (the
project's database keeps every match). Projects whose photos have fewer keypoints than their
budget are not touched.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from .trackrefine import UNUSABLE, Tracks, read_tracks

# observations the mapper's adjustments are sized for, all photos together
OBSERVATIONS = 1_500_000
# ...but never fewer than this per photo: below it the poses, not the memory, are what suffers
OBSERVATIONS_PER_IMAGE_FLOOR = 1500


def per_image_budget(n_images: int) -> int:
    """Keypoints each photo may keep in a project of ``n_images``."""
    return max(OBSERVATIONS_PER_IMAGE_FLOOR, OBSERVATIONS // max(1, n_images))


def kept_keypoints(tracks: Tracks, per_image: int) -> np.ndarray:
    """Which nodes (keypoints) stay: each photo's ``per_image`` matched in the most pairs (ties:
    the lower index, so the choice is reproducible). A keypoint's pairs are the photos it is
    matched to, so it ranks as its scene point's track would, and the same point ranks high in
    each of its photos, so its matches survive at both ends; the connected components themselves
    are no guide, since a few wrong matches chain most of a survey's keypoints into one."""
    n = int(tracks.offsets[-1])
    degree = np.bincount(tracks.edges.ravel(), minlength=n)
    image = tracks.image_of(np.arange(n))
    order = np.lexsort((np.arange(n), -degree, image))
    first = np.searchsorted(image[order], image[order], side="left")  # each image's first slot
    keep = np.zeros(n, bool)
    keep[order] = (np.arange(n) - first < per_image) & (degree[order] > 0)
    return keep


def thin_matches(database: Path, per_image: int) -> dict[str, Any]:
    """Drop from ``database`` (in place: the mapper's copy) the verified matches that do not join
    two keypoints kept at ``per_image``; returns counts for the summary."""
    db = pycolmap.Database.open(str(database))
    try:
        tracks, _ = read_tracks(db)
        keep = kept_keypoints(tracks, per_image)
        start = dict(zip(tracks.image_ids, tracks.offsets[:-1], strict=False))
        before = after = 0
        pair_ids, geometries = db.read_two_view_geometries()
        with pycolmap.DatabaseTransaction(db):  # one commit, not one per pair
            for pair_id, g in zip(pair_ids, geometries, strict=True):
                m = np.asarray(g.inlier_matches, np.int64).reshape(-1, 2)
                if g.config in UNUSABLE or not len(m):
                    continue
                a, b = pycolmap.pair_id_to_image_pair(pair_id)
                ok = keep[m[:, 0] + start[a]] & keep[m[:, 1] + start[b]]
                before += len(m)
                after += int(ok.sum())
                if not ok.all():
                    g.inlier_matches = m[ok].astype(np.uint32)
                    db.update_two_view_geometry(a, b, g)
    finally:
        db.close()
    return {
        "per_image": per_image,
        "keypoints_kept": int(keep.sum()),
        "matches_before": before,
        "matches_after": after,
    }
