"""The peer: COLMAP's own SIFT pipeline through pycolmap, on the same images and machine.

A user who does not pick geomatch runs this (``extract_features`` with 8192 SIFT features at up to
1600 px, ``match_exhaustive``, ``incremental_mapping``, COLMAP's default options). Its output has
geomatch's layout (``OUT/sparse/0`` the largest model, ``OUT/summary.json`` with ``timings``), so
``geomatch eval OUT --gt GT`` judges it exactly as it judges a ``geomatch run``, and every table in
docs/benchmarks.md can put it beside geomatch's rows from the same run.

    .venv/bin/python bench/peer_colmap.py IMAGES OUT [--gt GT]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from geomatch.sfm.colmapdb import COLMAP_OFFSET
from geomatch.sfm.colmaplog import colmap_log
from geomatch.sfm.mapping import sfm_stats

MAX_FEATURES = 8192
MAX_IMAGE_SIZE = 1600


def run_peer(
    images: Path, out: Path, threads: int = -1, matcher: str = "exhaustive", mapper: str = "incremental"
) -> dict[str, Any]:
    """SIFT extraction, exhaustive (or ``spatial``: COLMAP's GPS neighbours, its defaults of 50
    neighbours within 100 m, from the pose priors extraction reads from EXIF GPS) matching and
    incremental (or ``global``, as geomatch maps large projects) mapping; returns the summary."""
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    db = out / "database.db"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = MAX_IMAGE_SIZE
    extraction.num_threads = threads
    extraction.sift.max_num_features = MAX_FEATURES
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    with colmap_log(False):
        pycolmap.extract_features(db, images, extraction_options=extraction)
        t1 = time.perf_counter()
        if matcher == "spatial":
            pycolmap.match_spatial(db)
        else:
            pycolmap.match_exhaustive(db)
        t2 = time.perf_counter()
        work = out / ".mapping"
        work.mkdir()
        if mapper == "global":
            models = pycolmap.global_mapping(db, images, work, pycolmap.GlobalPipelineOptions())
        else:
            models = pycolmap.incremental_mapping(db, images, work)
    t3 = time.perf_counter()
    timings.update(extraction=t1 - t0, matching=t2 - t1, mapping=t3 - t2, total=t3 - t0)
    ranked = sorted(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()), reverse=True)
    for i, rec in enumerate(ranked):
        d = out / "sparse" / str(i)
        d.mkdir(parents=True)
        rec.write_binary(str(d))
    shutil.rmtree(work, ignore_errors=True)
    n_images = sum(1 for p in images.iterdir() if p.is_file())
    summary: dict[str, Any] = {
        "method": "colmap-sift",
        "matcher": matcher,
        "mapper": mapper,
        "models": len(ranked),
        "timings": timings,
    }
    if ranked:
        summary.update(sfm_stats(ranked[0], n_images))
    else:
        summary.update(registered=0, images=n_images, points3D=0)
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def sift_pair(
    image0: np.ndarray, image1: np.ndarray, threads: int = -1
) -> tuple[np.ndarray, np.ndarray, float]:
    """The peer on one pair, as a user's COLMAP project would match it: SIFT on both images,
    ``match_exhaustive`` with its geometric verification; returns the verified matches (pixel
    coordinates, top-left pixel's centre at 0.5 as in COLMAP) and the seconds it took (writing the
    two images to a scratch folder excluded)."""
    import cv2

    with tempfile.TemporaryDirectory() as tmp:
        images = Path(tmp) / "images"
        images.mkdir()
        for name, im in (("0.png", image0), ("1.png", image1)):
            cv2.imwrite(str(images / name), np.ascontiguousarray(im[:, :, ::-1]))
        db_path = Path(tmp) / "database.db"
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.max_image_size = MAX_IMAGE_SIZE
        extraction.num_threads = threads
        extraction.sift.max_num_features = MAX_FEATURES
        t0 = time.perf_counter()
        with colmap_log(False):
            pycolmap.extract_features(db_path, images, extraction_options=extraction)
            pycolmap.match_exhaustive(db_path)
        seconds = time.perf_counter() - t0
        db = pycolmap.Database.open(str(db_path))
        try:
            ids = {im.name: im.image_id for im in db.read_all_images()}
            a, b = ids["0.png"], ids["1.png"]
            if not db.exists_two_view_geometry(a, b):
                return np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32), seconds
            m = db.read_two_view_geometry(a, b).inlier_matches
            k0, k1 = db.read_keypoints(a)[:, :2], db.read_keypoints(b)[:, :2]
        finally:
            db.close()
    p0, p1 = k0[m[:, 0]] - COLMAP_OFFSET, k1[m[:, 1]] - COLMAP_OFFSET
    return p0.astype(np.float32), p1.astype(np.float32), seconds


PEER = "COLMAP SIFT (peer)"


@dataclass
class PeerMatch:
    """The peer's answer for a pair, shaped like geomatch's MatchResult where the benchmarks read it."""

    keypoints0: np.ndarray
    keypoints1: np.ndarray
    seconds: float

    def __len__(self) -> int:
        return len(self.keypoints0)


class SiftPeer:
    """:func:`sift_pair` with a Matcher's ``match``, so a benchmark's loop over variants runs the
    peer as one more row."""

    def match(self, image0: np.ndarray, image1: np.ndarray) -> PeerMatch:
        return PeerMatch(*sift_pair(image0, image1))


def with_peer(variants: list[tuple[str, Any]], peer: bool = True) -> list[tuple[str, Any]]:
    """(label, matcher) rows with the peer's first, unless ``peer`` is False."""
    return [(PEER, SiftPeer()), *variants] if peer else variants


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("images", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--gt", type=Path, help="ground-truth COLMAP model: print geomatch eval's table")
    ap.add_argument("--threads", type=int, default=-1, help="SIFT threads (-1: all cores)")
    ap.add_argument("--matcher", choices=("exhaustive", "spatial"), default="exhaustive")
    ap.add_argument("--mapper", choices=("incremental", "global"), default="incremental")
    args = ap.parse_args(argv)
    s = run_peer(args.images, args.out, args.threads, args.matcher, args.mapper)
    t = s["timings"]
    print(
        f"COLMAP SIFT: {s['registered']}/{s['images']} registered, {s['points3D']} points; "
        f"{t['total']:.1f} s (extraction {t['extraction']:.1f}, matching {t['matching']:.1f}, "
        f"mapping {t['mapping']:.1f})"
    )
    if args.gt:
        from geomatch.eval.evaluate import evaluate_run

        print(evaluate_run(args.out, args.gt).table())
    return 0


if __name__ == "__main__":
    sys.exit(main())
