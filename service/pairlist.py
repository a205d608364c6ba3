"""The matched pairs of a project's COLMAP database with their counts, read in plain SQL.

A read-only SQLite connection sees one consistent state of the file (a read transaction), so the
writer lock is not needed; COLMAP's schema (``images``, ``matches``, ``two_view_geometries``) and
its pair id (``id0 * 2147483647 + id1``, the smaller id first) are public and stable.
"""

from __future__ import annotations

import sqlite3
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path

MAX_IMAGE_ID = 2147483647  # COLMAP's kMaxNumImages: the pair id's base


@dataclass(frozen=True)
class PairView:
    name0: str
    name1: str
    matches: int  # raw matches written by the matcher
    inliers: int  # matches verified by the two-view geometry (0 when none fitted)


def pair_ids(pair_id: int) -> tuple[int, int]:
    return pair_id // MAX_IMAGE_ID, pair_id % MAX_IMAGE_ID


def read_pairs(database: Path) -> list[PairView]:
    """Every pair written to the database (zero-match pairs too), most inliers first."""
    if not database.is_file():
        return []
    uri = f"{database.resolve().as_uri()}?mode=ro"
    with closing(sqlite3.connect(uri, uri=True, timeout=30)) as con:
        names = dict(con.execute("SELECT image_id, name FROM images"))
        raw = dict(con.execute("SELECT pair_id, rows FROM matches"))
        verified = dict(con.execute("SELECT pair_id, rows FROM two_view_geometries"))
    out = []
    for pid, n in raw.items():
        a, b = pair_ids(int(pid))
        if a in names and b in names:
            out.append(PairView(names[a], names[b], int(n or 0), int(verified.get(pid) or 0)))
    return sorted(out, key=lambda p: (-p.inliers, -p.matches, p.name0, p.name1))
