"""A consistent copy of a live SQLite file (a COLMAP database) by SQLite's online backup.

Why not a file copy: the file may be mid-transaction at any moment, and in WAL mode the latest
commits live in the ``-wal`` file beside it; a plain copy could tear the one or miss the other.
"""

from __future__ import annotations

import sqlite3
from contextlib import closing
from pathlib import Path


def snapshot_sqlite(src: str | Path, dst: str | Path) -> None:
    with (
        closing(sqlite3.connect(f"file:{src}?mode=ro", uri=True, timeout=60)) as a,
        closing(sqlite3.connect(dst)) as b,
    ):
        a.backup(b)
