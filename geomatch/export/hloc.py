"""hloc's ``features.h5``, ``matches.h5`` and ``pairs.txt``, so hloc's triangulation, localization
and reconstruction read our keypoints and verified matches as if hloc had made them.

Layout is hloc's (extract_features / match_features): one group per image name in features.h5
with ``keypoints`` (N, 2), ``scores`` (N,) and ``image_size`` (width, height); one group per pair
in matches.h5, named ``names_to_pair(name0, name1)`` (``/`` in a name becomes ``-``, the names
joined by ``_``), with ``matches0`` (one entry per keypoint of image 0: the index of its match
in image 1, or -1) and ``matching_scores0``.

Keypoints are in hloc's convention, the centre of the top-left pixel at (0, 0): hloc adds 0.5
when it imports features into COLMAP (whose pixel centres sit at +0.5), so these are the
database's keypoints minus 0.5, the same convention as colmapdb.ColmapDatabase.keypoints (not
used here: colmapdb pulls torch through its image reader, and the service's API builds exports).

The matches are the verified inliers of every pair in the database (its two-view geometries),
not the raw matches: a user who imports them into COLMAP with hloc skips geometric
verification and gets the pairs our mapper saw. The database keeps no per-keypoint or
per-match score, so ``scores`` and ``matching_scores0`` are 1 for what exists (0 for unmatched).
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pycolmap

from .source import Source

COLMAP_OFFSET = 0.5  # colmapdb.COLMAP_OFFSET: COLMAP's pixel centres at +0.5 of hloc's


def names_to_pair(name0: str, name1: str, separator: str = "_") -> str:
    """hloc's key of a pair in matches.h5 (hloc.utils.io.names_to_pair)."""
    return separator.join((name0.replace("/", "-"), name1.replace("/", "-")))


def matches0(inliers: np.ndarray, n0: int) -> np.ndarray:
    """hloc's ``matches0`` of image 0 from (M, 2) index pairs; a keypoint of image 0 matched
    twice (never written by colmapdb, which keeps matches one-to-one) keeps its first match."""
    out = np.full(n0, -1, dtype=np.int32)
    inliers = np.asarray(inliers, dtype=np.int64).reshape(-1, 2)
    first = np.unique(inliers[:, 0], return_index=True)[1]
    out[inliers[first, 0]] = inliers[first, 1]
    return out


def write(source: Source, dest: Path) -> list[Path]:
    assert source.database is not None  # checked by export()
    dest.mkdir(parents=True, exist_ok=True)
    features, matches, pairs = dest / "features.h5", dest / "matches.h5", dest / "pairs.txt"
    db = pycolmap.Database.open(str(source.database))
    try:
        names = {int(im.image_id): im.name for im in db.read_all_images()}
        counts: dict[int, int] = {}
        with h5py.File(features, "w") as f:
            for image_id, name in sorted(names.items(), key=lambda kv: kv[1]):
                kp = np.zeros((0, 2), np.float32)
                if db.exists_keypoints(image_id):
                    kp = (db.read_keypoints(image_id)[:, :2] - COLMAP_OFFSET).astype(np.float32)
                cam = db.read_camera(db.read_image(image_id).camera_id)
                g = f.create_group(name)
                g.create_dataset("keypoints", data=kp)
                g.create_dataset("scores", data=np.ones(len(kp), np.float32))
                g.create_dataset("image_size", data=np.array([cam.width, cam.height], np.int64))
                counts[image_id] = len(kp)
        pair_ids, geometries = db.read_two_view_geometries()
        lines = []
        with h5py.File(matches, "w") as f:
            for pair_id, tvg in sorted(zip(pair_ids, geometries, strict=True), key=lambda pg: pg[0]):
                a, b = (int(i) for i in pycolmap.pair_id_to_image_pair(pair_id))
                m0 = matches0(tvg.inlier_matches, counts[a])
                g = f.create_group(names_to_pair(names[a], names[b]))
                g.create_dataset("matches0", data=m0)
                g.create_dataset("matching_scores0", data=(m0 > -1).astype(np.float32))
                lines.append(f"{names[a]} {names[b]}\n")
    finally:
        db.close()
    pairs.write_text("".join(lines))
    return [features, matches, pairs]
