"""The run writes its pairs on a thread of its own while the next pair is matched: the database
ends as a sequential run leaves it, and a failed write stops the run without losing the pairs
written before it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from geomatch.metadata import ImageMeta
from geomatch.pipeline.database import PairMatches, write
from geomatch.pipeline.runner import PairWriter
from geomatch.sfm.colmapdb import ColmapDatabase

pytestmark = pytest.mark.unit

META = ImageMeta(640, 480, "DJI", "FC6310", 500.0, 60.0, -90.0)


def _matches(seed: int, n: int = 120) -> PairMatches:
    """A plane seen by two views a few pixels apart: verified by COLMAP as a homography."""
    rng = np.random.default_rng(seed)
    k0 = rng.uniform([10, 10], [630, 470], (n, 2)).astype(np.float32)
    k1 = (k0 * 0.98 + np.float32([7.0, -4.0])).astype(np.float32)
    return PairMatches(k0, k1, rng.uniform(0.5, 1, n), ((640, 480), (640, 480)))


def _database(path: Path, n: int = 4) -> list[int]:
    with ColmapDatabase(path) as db:
        return [db.add_image(f"{i}.jpg", META) for i in range(n)]


def _contents(path: Path) -> tuple[list[bytes], list[tuple[int, int, int]]]:
    with ColmapDatabase(path) as db:
        kps = [db.keypoints(i).tobytes() for i in range(1, 5)]
        pairs = [
            (i, j, len(db.db.read_matches(i, j)))
            for i in range(1, 5)
            for j in range(i + 1, 5)
            if db.has_pair(i, j)
        ]
    return kps, pairs


def test_writes_behind_the_matching_leave_the_database_a_sequential_run_leaves(tmp_path: Path) -> None:
    plan = [(0, 1), (1, 2), (0, 2), (2, 3), (1, 3)]
    ids = _database(tmp_path / "threaded.db")
    with PairWriter(tmp_path / "threaded.db", 1.5, 640) as writer:
        for k, (a, b) in enumerate(plan):
            writer.put(ids[a], ids[b], _matches(k))
    assert writer.seconds > 0 and writer.last is not None
    ids = _database(tmp_path / "sequential.db")
    with ColmapDatabase(tmp_path / "sequential.db") as db:
        for k, (a, b) in enumerate(plan):
            write(db, ids[a], ids[b], _matches(k), 1.5, 640)
    threaded, sequential = _contents(tmp_path / "threaded.db"), _contents(tmp_path / "sequential.db")
    assert threaded == sequential and len(threaded[1]) == len(plan)


def test_a_failed_write_stops_the_run_and_keeps_the_pairs_written_before_it(tmp_path: Path) -> None:
    ids = _database(tmp_path / "d.db")
    good = _matches(0)
    bad = PairMatches(good.keypoints0, good.keypoints1[:10], good.scores, good.sizes)  # lengths disagree
    with pytest.raises(ValueError, match="keypoints"), PairWriter(tmp_path / "d.db", 1.5, 640) as writer:
        writer.put(ids[0], ids[1], good)
        writer.put(ids[1], ids[2], bad)
        for _ in range(20):  # the matching goes on until the writer's error reaches it
            writer.put(ids[2], ids[3], _matches(1))
    with ColmapDatabase(tmp_path / "d.db") as db:
        assert db.has_pair(ids[0], ids[1])
        assert not db.has_pair(ids[1], ids[2])
        assert not db.has_pair(ids[2], ids[3])  # queued behind the failure: dropped, matched again on resume
