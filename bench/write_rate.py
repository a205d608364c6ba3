"""How fast one project's COLMAP database takes pairs, against how fast workers match them.

Every worker writes a project's pairs into one SQLite database under the project's writer lock,
so the lock's rate is a ceiling on the whole fleet's, however many workers match. A write is
snapping onto the images' keypoints, COLMAP's verification, and the transaction. Prepared outside
the lock (``ColmapDatabase.prepare_pair`` on a reader, as the workers' pair steps do), only the
transaction (``commit_pair``) holds it; written whole (``write_pair``), the lock is held for all.

The project is a synthetic survey (nadir cameras on serpentine lines over ground with relief),
each image paired with its K nearest (as ``gps:K``), each pair's matches the scene points both
images see (with pixel noise and outliers), so keypoint lists grow and get snapped onto as in a
real project. Per size: seconds a pair for prepare and commit, the lock's ceiling in pairs/s
both ways, and how the commit grows as the project fills. Then W worker processes writing one
database under a file lock, both ways: pairs/s of the fleet (the machine's cores bound it).

    python bench/write_rate.py --sizes 100,300,1000 --workers 1,2
"""

from __future__ import annotations

import argparse
import fcntl
import multiprocessing as mp
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
from common import print_table
from scipy.spatial import cKDTree

from geomatch.metadata import ImageMeta
from geomatch.sfm.colmapdb import ColmapDatabase

OUT = Path(__file__).parent / "out" / "write_rate"
W, H, F = 640, 480, 500.0
ALT = 30.0
META = ImageMeta(W, H, "synth", "drone", F, ALT, -90.0)
RADIUS = 1.5  # the snap radius at the default working size, in pixels


def survey(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres on serpentine lines (75 % forward, 65 % side overlap) and ground points."""
    foot_w, foot_h = W / F * ALT, H / F * ALT
    along, across = 0.25 * foot_h, 0.35 * foot_w
    per_line = max(int(np.sqrt(n * across / along)), 2)
    lines = int(np.ceil(n / per_line))
    centres = []
    for line in range(lines):
        ys = np.arange(per_line) * along
        ys = ys if line % 2 == 0 else ys[::-1]
        centres += [(line * across, y) for y in ys]
    c = np.array(centres[:n], np.float64)
    rng = np.random.default_rng(seed)
    lo, hi = c.min(0) - foot_w, c.max(0) + foot_w
    area = float(np.prod(hi - lo))
    pts = rng.uniform(lo, hi, (int(4.0 * area), 2))
    z = 1.5 * np.sin(pts[:, 0] / 7.0) * np.cos(pts[:, 1] / 5.0) + rng.uniform(0, 0.5, len(pts))
    return np.c_[c, np.full(len(c), ALT)], np.c_[pts, z]


def project(centre: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of the ground points a nadir camera at ``centre`` sees (x east, y south)."""
    d = X - centre
    u = F * d[:, 0] / -d[:, 2] + W / 2
    v = F * -d[:, 1] / -d[:, 2] + H / 2
    seen = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    return np.flatnonzero(seen), np.c_[u[seen], v[seen]].astype(np.float32)


def pair_matches(
    i: int, j: int, cams: np.ndarray, X: np.ndarray, rng: np.random.Generator, cap: int = 1500
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ia, pa = project(cams[i], X)
    ib, pb = project(cams[j], X)
    common, ka, kb = np.intersect1d(ia, ib, return_indices=True)
    take = rng.permutation(len(common))[:cap]
    a, b = pa[ka[take]], pb[kb[take]]
    a = a + rng.normal(0, 0.4, a.shape).astype(np.float32)
    b = b + rng.normal(0, 0.4, b.shape).astype(np.float32)
    bad = rng.random(len(a)) < 0.15  # wrong matches: somewhere else in the image
    b[bad] = rng.uniform((0, 0), (W, H), (int(bad.sum()), 2)).astype(np.float32)
    return a, b, rng.random(len(a))


def plan(cams: np.ndarray, k: int) -> list[tuple[int, int]]:
    _, nn = cKDTree(cams[:, :2]).query(cams[:, :2], k=k + 1)
    return sorted({(min(i, int(j)), max(i, int(j))) for i in range(len(cams)) for j in nn[i, 1:]})


def setup(path: Path, n: int) -> list[int]:
    path.unlink(missing_ok=True)
    with ColmapDatabase(path) as db:
        return [db.add_image(f"img_{i:05d}.jpg", META) for i in range(n)]


def one_process(n: int, k: int) -> dict[str, Any]:
    cams, X = survey(n)
    pairs = plan(cams, k)
    path = OUT / f"single_{n}.db"
    ids = setup(path, n)
    rng = np.random.default_rng(1)
    prep, comm = [], []
    with ColmapDatabase(path) as db:
        for i, j in pairs:
            a, b, s = pair_matches(i, j, cams, X, rng)
            t0 = time.perf_counter()
            p = db.prepare_pair(ids[i], ids[j], a, b, s, RADIUS, RADIUS)
            t1 = time.perf_counter()
            db.commit_pair(p)
            prep.append(t1 - t0)
            comm.append(time.perf_counter() - t1)
        kp = db.stats()["keypoints"]
    pr, cm = np.array(prep), np.array(comm)
    tenth = max(len(cm) // 10, 1)
    return {
        "photos": n,
        "pairs": len(pairs),
        "keypoints_per_image": kp / n,
        "prepare_ms": 1e3 * pr.mean(),
        "commit_ms": 1e3 * cm.mean(),
        "commit_first_ms": 1e3 * cm[:tenth].mean(),
        "commit_last_ms": 1e3 * cm[-tenth:].mean(),
        "ceiling_whole": 1.0 / (pr.mean() + cm.mean()),
        "ceiling_split": 1.0 / cm.mean(),
    }


def _worker(
    path: str, lock: str, jobs: list[tuple[int, int, int, int]], n: int, split: bool, out: Any
) -> None:
    cams, X = survey(n)
    count = 0
    for seed, i, j, id_pair in jobs:
        rng = np.random.default_rng(seed)
        a, b, s = pair_matches(i, j, cams, X, rng)
        id0, id1 = divmod(id_pair, 1 << 20)
        if split:  # opened and closed under the lock, read beside the writers (workers/jobs._readable)
            with open(lock, "w") as fh:
                fcntl.flock(fh, fcntl.LOCK_EX)
                reader = ColmapDatabase(path)
            p = reader.prepare_pair(id0, id1, a, b, s, RADIUS, RADIUS)
            with open(lock, "w") as fh:
                fcntl.flock(fh, fcntl.LOCK_EX)
                reader.close()
            with open(lock, "w") as fh:
                fcntl.flock(fh, fcntl.LOCK_EX)
                with ColmapDatabase(path) as db:
                    db.commit_pair(p)
        else:
            with open(lock, "w") as fh:
                fcntl.flock(fh, fcntl.LOCK_EX)
                with ColmapDatabase(path) as db:
                    db.write_pair(id0, id1, a, b, s, RADIUS, RADIUS)
        count += 1
    out.put(count)


def fleet(n: int, k: int, workers: int, split: bool) -> dict[str, Any]:
    """W processes writing one database, each pair's matches made beforehand in the process
    (the matching itself is not timed: this is the database's side of the fleet)."""
    cams, _ = survey(n)
    pairs = plan(cams, k)
    path = OUT / f"fleet_{n}_{workers}_{int(split)}.db"
    ids = setup(path, n)
    jobs = [(s, i, j, (ids[i] << 20) + ids[j]) for s, (i, j) in enumerate(pairs)]
    out: Any = mp.Queue()
    procs = [
        mp.Process(target=_worker, args=(str(path), str(path) + ".lock", jobs[w::workers], n, split, out))
        for w in range(workers)
    ]
    t0 = time.perf_counter()
    for p in procs:
        p.start()
    done = sum(out.get() for _ in procs)
    for p in procs:
        p.join()
    wall = time.perf_counter() - t0
    with ColmapDatabase(path) as db:
        st = db.stats()
    return {
        "photos": n,
        "workers": workers,
        "mode": "prepare unlocked, commit locked" if split else "whole write locked",
        "pairs": done,
        "rate": done / wall,
        "verified": st["verified_pairs"],
        "keypoints_per_image": st["keypoints"] / n,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="100,300,1000")
    ap.add_argument("--k", type=int, default=10, help="pairs per photo, as gps:K")
    ap.add_argument("--workers", default="1,2", help="fleet sizes for the multi-process rows")
    ap.add_argument("--fleet-size", type=int, default=300, help="photos in the multi-process rows")
    args = ap.parse_args()
    shutil.rmtree(OUT, ignore_errors=True)
    OUT.mkdir(parents=True)
    rows = [one_process(int(s), args.k) for s in args.sizes.split(",")]
    print_table(
        "One process: a pair's write, split into the unlocked and the locked part",
        [
            ("photos", "photos", "d"),
            ("pairs", "pairs", "d"),
            ("keypoints / image at the end", "keypoints_per_image", ".0f"),
            ("prepare ms / pair (snap + verify)", "prepare_ms", ".1f"),
            ("commit ms / pair (transaction)", "commit_ms", ".1f"),
            ("commit ms, first tenth", "commit_first_ms", ".1f"),
            ("commit ms, last tenth", "commit_last_ms", ".1f"),
            ("lock ceiling pairs/s, whole write", "ceiling_whole", ".1f"),
            ("lock ceiling pairs/s, commit only", "ceiling_split", ".1f"),
        ],
        rows,
    )
    ctx_rows = []
    for w in (int(x) for x in args.workers.split(",")):
        for split in (False, True):
            ctx_rows.append(fleet(args.fleet_size, args.k, w, split))
    print_table(
        f"Worker processes writing one {args.fleet_size}-photo project's database",
        [
            ("photos", "photos", "d"),
            ("workers", "workers", "d"),
            ("mode", "mode", "s"),
            ("pairs", "pairs", "d"),
            ("pairs/s", "rate", ".1f"),
            ("verified pairs", "verified", "d"),
            ("keypoints / image", "keypoints_per_image", ".0f"),
        ],
        ctx_rows,
    )


if __name__ == "__main__":
    mp.set_start_method("fork")
    main()
