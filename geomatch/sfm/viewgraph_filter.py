"""The view graph's checks (viewgraph.py) applied to a COLMAP database: the verified pairs' candidate
rotations read from it, the pairs the checks drop marked DEGENERATE in the mapper's private copy,
and what was kept and dropped, by image name, for the mapping's report and the model's agreement
check (modelagree.py)."""

from __future__ import annotations

import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from .pairrotations import verified_rotations
from .sqlitecopy import snapshot_sqlite
from .upright import upright_candidates
from .viewgraph import LOOP_DEG, MIN_INLIERS, judge


@dataclass
class ViewGraphReport:
    pairs: int = 0  # verified pairs with a relative rotation
    loops: int = 0  # triangles of verified pairs
    dropped: list[tuple[str, str, int, int]] = field(default_factory=list)  # (name0, name1, bad, loops)
    # the tree check's drops: (name0, name1, degrees off the tree's rotation, tree path length)
    tree_dropped: list[tuple[str, str, float, int]] = field(default_factory=list)
    # the pairs both checks kept, by image names (a, b): their candidate rotations (x_b ~ R x_a)
    # and inliers, which a finished model is held to (modelagree.py); not in the summary
    kept_rotations: dict[tuple[str, str], list[np.ndarray]] = field(default_factory=dict, repr=False)
    kept_inliers: dict[tuple[str, str], int] = field(default_factory=dict, repr=False)

    def as_dict(self) -> dict[str, object]:
        return {
            "pairs": self.pairs,
            "loops": self.loops,
            "dropped": [{"pair": [a, b], "broken_loops": bad, "loops": n} for a, b, bad, n in self.dropped],
            "tree_dropped": [
                {"pair": [a, b], "degrees": round(deg, 2), "hops": hops}
                for a, b, deg, hops in self.tree_dropped
            ],
        }


def filter_database(
    database: str,
    min_inliers: int = MIN_INLIERS,
    loop_deg: float = LOOP_DEG,
    loops: bool = True,
    tree: bool = True,
    up: Mapping[str, np.ndarray] | None = None,
) -> ViewGraphReport:
    """Mark the pairs :func:`judge` drops as DEGENERATE (no inliers) in ``database``, which must
    be the mapper's private copy: the project's database keeps every verified pair, so a later
    reconstruct with more images judges them again. ``up``: each photo's up in its camera frame
    where known (upright.image_up); a pair of two such photos is judged by the candidate rotations
    that carry one's up onto the other's (upright.py)."""
    db = pycolmap.Database.open(database)
    try:
        report, gone = _judged(db, min_inliers, loop_deg, loops, tree, up)
        for a, b in gone:
            _degenerate(db, a, b)
    finally:
        db.close()
    return report


def kept_pairs(database: str, up: Mapping[str, np.ndarray] | None = None) -> ViewGraphReport:
    """What :func:`filter_database` would report for ``database``, which is left as it is: the
    pairs a finished model was held to (modelagree.py), for a reader of a project's database that
    must not change it (localization)."""
    # read from a snapshot: COLMAP opens a database read-write, and closing it checkpoints and
    # removes the -wal and -shm files of a project the reader must leave as it found it (and a
    # read-only connection still writes the -shm index: sqlitecopy's ``untouched``)
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "database.db"
        snapshot_sqlite(database, copy, untouched=True)
        db = pycolmap.Database.open(str(copy))
        try:
            report, _ = _judged(db, MIN_INLIERS, LOOP_DEG, True, True, up)
        finally:
            db.close()
    return report


def _judged(
    db: pycolmap.Database,
    min_inliers: int,
    loop_deg: float,
    loops: bool,
    tree: bool,
    up: Mapping[str, np.ndarray] | None,
) -> tuple[ViewGraphReport, list[tuple[int, int]]]:
    """The report of :func:`filter_database` and the image id pairs it drops."""
    rotations, inliers = verified_rotations(db, min_inliers)
    names = {im.image_id: im.name for im in db.read_all_images()}
    if up:
        rotations = upright_candidates(rotations, names, up)
    tree_drop, loop_drop, seen = judge(
        rotations, inliers, loop_deg, loops, tree, uncalibrated=_uncalibrated_pairs(db)
    )
    report = ViewGraphReport(pairs=len(rotations), loops=seen)
    for (a, b), deg, hops in tree_drop:
        report.tree_dropped.append((names[a], names[b], deg, hops))
    for (a, b), bad, n in loop_drop:
        report.dropped.append((names[a], names[b], bad, n))
    gone = [pair for pair, _, _ in tree_drop] + [pair for pair, _, _ in loop_drop]
    dropped = set(gone)
    for (a, b), cands in rotations.items():
        if (a, b) not in dropped:
            report.kept_rotations[(names[a], names[b])] = cands
            report.kept_inliers[(names[a], names[b])] = inliers[(a, b)]
    return report, gone


def _uncalibrated_pairs(db: pycolmap.Database) -> set[tuple[int, int]]:
    """The verified pairs COLMAP's verification left UNCALIBRATED, keyed (i, j) with i < j."""
    pair_ids, geometries = db.read_two_view_geometries()
    out = set()
    for pid, g in zip(pair_ids, geometries, strict=True):
        if g.config == pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED:
            a, b = pycolmap.pair_id_to_image_pair(pid)
            out.add((min(a, b), max(a, b)))
    return out


def _degenerate(db: pycolmap.Database, a: int, b: int) -> None:
    g = pycolmap.TwoViewGeometry()
    g.config = pycolmap.TwoViewGeometryConfiguration.DEGENERATE
    db.delete_two_view_geometry(a, b)
    db.write_two_view_geometry(a, b, g)
