"""A consistent copy of a live SQLite file (a COLMAP database) by SQLite's online backup.

Why not a file copy: the file may be mid-transaction at any moment, and in WAL mode the latest
commits live in the ``-wal`` file beside it; a plain copy could tear the one or miss the other.
"""

from __future__ import annotations

import sqlite3
from contextlib import closing
from pathlib import Path


def snapshot_sqlite(src: str | Path, dst: str | Path, untouched: bool = False) -> None:
    """``untouched``: leave ``src``'s files exactly as they are (a reader of a finished project):
    a read-only connection to a WAL database still writes its ``-shm`` index, so where no commit
    waits in the ``-wal`` file the database is read as immutable (no locks, no index)."""
    wal = Path(f"{src}-wal")
    immutable = untouched and (not wal.exists() or wal.stat().st_size == 0)
    mode = "mode=ro&immutable=1" if immutable else "mode=ro"
    with (
        closing(sqlite3.connect(f"file:{src}?{mode}", uri=True, timeout=60)) as a,
        closing(sqlite3.connect(dst)) as b,
    ):
        a.backup(b)
