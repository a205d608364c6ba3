"""The whole pipeline on real photographs with surveyed cameras, beside COLMAP's SIFT pipeline.

    .venv/bin/python bench/real_sfm.py                                   # both splits, defaults + peer
    .venv/bin/python bench/real_sfm.py --split tuning --variants "geo;sparse"
    .venv/bin/python bench/real_sfm.py --scenes castle-P19 --variants "sparse lightglue_depth_confidence=-1"

Scenes: the Strecha scenes of ``../shared/data/real/strecha/`` (tuning split: fountain-P11,
Herz-Jesus-P8, castle-P19; test split: entry-P10) and sacre_coeur (10 photos without surveyed
cameras: its reference is the consensus of three COLMAP builds at full size with DSP-SIFT and affine
shapes, so on that scene the peer is judged against a close relative of itself and its errors there
are a floor, not a measurement; ``--repeats`` shows the runs' own spread). Each run is a fresh
process (``geomatch run`` through ``geomatch.pipeline.run``, or ``bench/peer_colmap.py``) so that
its wall time and peak RSS are its own; runs of one scene follow
each other on the same machine, so ratios against the peer's row of that scene are side by side.

A variant is ``METHOD [key=value ...]``: keys of ``RunOptions`` (``pairs=retrieval:8``,
``resize=1024``, ``loop_check=false`` ...) go to the run, any other key to the matcher config
(``max_keypoints=1024``, ``lightglue_depth_confidence=-1`` ...). ``default`` is ``geomatch run``
with no option at all.

Columns: correct / registered cameras (geomatch eval's rule), pose AUC@3/5/10 deg over all pairs,
median and max camera position error (metres) and median rotation error (deg) after alignment,
wrong verified pairs that reached the mapper (of all wrong verified pairs; judged by the ground
truth's epipolar geometry, geomatch/eval/pairtruth.py), wall seconds, the ratio to the peer's wall time
and peak RSS.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT.parent / "shared" / "data" / "real"
OUT = ROOT / "bench" / "out" / "real_sfm"
SPLITS = {
    "tuning": ["fountain-P11", "Herz-Jesus-P8", "castle-P19"],
    "test": ["entry-P10", "sacre_coeur"],
}
PEER = "colmap-sift"


def scene_paths(scene: str) -> tuple[Path, Path]:
    """(images, ground truth model) of a scene; sacre_coeur's truth is built on first use."""
    if scene == "sacre_coeur":
        images = DATA / "sacre_coeur"
        model = OUT / f"{images.name}_reference" / "model"
        if not (model / "images.bin").exists():
            # in a child: a process forked from this one starts with its resident memory, so a
            # reference built here (4.7 GiB) would be every later run's peak RSS
            subprocess.run(
                [sys.executable, "bench/real_sfm.py", "--reference", str(images)], cwd=ROOT, check=True
            )
        return images, model
    base = DATA / "strecha" / scene
    return base / "images", base / "gt"


# one build is one draw of COLMAP's RANSAC and mapping: builds with mapper seeds 0 and 1 put
# sacre_coeur's cameras 0.004 reference units apart (median; 0.035 max, scene extent 10)
REFERENCE_BUILDS = 3


def sift_build(images: Path, out: Path, seed: int) -> Path:
    """COLMAP at full size with the stronger SIFT variant (DSP, affine shapes, guided matching)."""
    import pycolmap

    from geomatch.sfm.colmapdb import seeded_verification
    from geomatch.sfm.colmaplog import colmap_log

    model = out / "model"
    if (model / "images.bin").exists():
        return model
    out.mkdir(parents=True, exist_ok=True)
    db = out / "database.db"
    db.unlink(missing_ok=True)
    ex = pycolmap.FeatureExtractionOptions()
    ex.sift.max_num_features = 16384
    ex.sift.estimate_affine_shape = True
    ex.sift.domain_size_pooling = True
    mo = pycolmap.FeatureMatchingOptions()
    mo.guided_matching = True
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.random_seed = seed
    with colmap_log(False):
        pycolmap.extract_features(db, images, extraction_options=ex)
        pycolmap.match_exhaustive(db, matching_options=mo, verification_options=seeded_verification())
        recs = pycolmap.incremental_mapping(db, images, out / "sparse", mapping)
    best = max(recs.values(), key=lambda r: r.num_reg_images())
    model.mkdir(exist_ok=True)
    best.write_binary(str(model))
    return model


def mean_rotation(rs: np.ndarray) -> np.ndarray:
    """The rotation nearest (chordal) to the mean of a stack of rotations (N, 3, 3)."""
    u, _, vt = np.linalg.svd(rs.sum(0))
    return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt


Poses = dict[str, tuple[np.ndarray, np.ndarray]]  # image name -> (cam_from_world rotation, centre)


def consensus(builds: list[Poses]) -> Poses:
    """Mean camera (cam_from_world rotation, centre) of the cameras every build registered, each
    build first aligned to the running mean by a similarity (frame and scale of the first build)."""
    from geomatch.geo.similarity import umeyama

    names = sorted(set.intersection(*(set(b) for b in builds)))
    mean = {n: builds[0][n] for n in names}
    for _ in range(3):
        aligned = []
        for b in builds:
            sim = umeyama(np.array([b[n][1] for n in names]), np.array([mean[n][1] for n in names]))
            aligned.append({n: (b[n][0] @ sim.R.T, sim.apply(b[n][1][None])[0]) for n in names})
        mean = {
            n: (mean_rotation(np.array([a[n][0] for a in aligned])), np.mean([a[n][1] for a in aligned], 0))
            for n in names
        }
    return mean


def sift_reference(images: Path) -> Path:
    """The reference of a scene that has no surveyed cameras: the consensus of REFERENCE_BUILDS
    COLMAP DSP-SIFT builds (mapper seeds 0, 1, ...), so that no single build's placement decides
    which run is closer. Each build's own distance to the consensus goes to spread.json."""
    import pycolmap

    from geomatch.eval.metrics import camera_errors

    ref = OUT / f"{images.name}_reference"
    model = ref / "model"
    if (model / "images.bin").exists():
        return model
    models = [sift_build(images, ref / f"build{s}", s) for s in range(REFERENCE_BUILDS)]
    recs = [pycolmap.Reconstruction(str(m)) for m in models]
    builds = [
        {
            im.name: (im.cam_from_world().rotation.matrix(), im.projection_center())
            for im in r.images.values()
            if im.has_pose
        }
        for r in recs
    ]
    mean = consensus(builds)
    out = pycolmap.Reconstruction(recs[0])
    for im in out.images.values():
        if im.name in mean:
            R, c = mean[im.name]
            out.frames[im.frame_id].set_cam_from_world(
                im.camera_id, pycolmap.Rigid3d(pycolmap.Rotation3d(R), (-R @ c).reshape(3, 1))
            )
        else:
            out.deregister_frame(im.frame_id)
    model.mkdir(parents=True, exist_ok=True)
    out.write_binary(str(model))
    spread = []
    for s, r in enumerate(recs):
        errs = camera_errors(r, out, 3.0, float("inf")) or {}
        pos = sorted(p for _, p in errs.values())
        spread.append({"build": s, "median": float(np.median(pos)), "max": float(pos[-1])})
    (ref / "spread.json").write_text(json.dumps(spread, indent=2) + "\n")
    return model


def parse_variant(spec: str) -> tuple[str, dict[str, Any], dict[str, Any]]:
    """(method or 'default', RunOptions fields, matcher fields)."""
    from dataclasses import fields

    from common import parse_value

    from geomatch.pipeline import RunOptions

    method, *kvs = spec.split()
    run_keys = {f.name for f in fields(RunOptions)}
    run: dict[str, Any] = {}
    matcher: dict[str, Any] = {}
    for kv in kvs:
        k, v = kv.split("=", 1)
        (run if k in run_keys else matcher)[k] = parse_value(v)
    return method, run, matcher


def run_one(images: Path, out: Path, spec: str, match_cache: str | None) -> None:
    """The child process of one geomatch run."""
    import shutil

    import matchcache

    from geomatch.pipeline import RunOptions, run

    method, run_kw, matcher_kw = parse_variant(spec)
    shutil.rmtree(out, ignore_errors=True)
    opts = RunOptions(progress=False, matcher=matcher_kw, **run_kw)
    if method != "default":
        opts.method = method
    run(images, out, opts, match=matchcache.cached(match_cache))


def timed(cmd: list[str]) -> tuple[float, float, int]:
    """(wall seconds, peak RSS MiB, exit status) of a child process."""
    # stderr into a file, not a pipe: a pipe nobody reads until the child exits blocks the child
    # once its buffer (64 KiB) is full, and a long run's log fills it
    with tempfile.TemporaryFile() as log:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=log)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        log.seek(0)
        err = log.read().decode(errors="replace")
    if proc.returncode:
        print(err[-3000:], file=sys.stderr)
    return wall, usage.ru_maxrss / 1024, proc.returncode


def judge(out: Path, gt: Path) -> dict[str, Any]:
    """geomatch eval's metrics plus the wrong verified pairs (geomatch.eval.pairtruth)."""
    from geomatch.eval.evaluate import evaluate_run

    return evaluate_run(out, gt).metrics


def row(scene: str, label: str, m: dict[str, Any], wall: float, rss: float, peer_wall: float | None) -> dict:
    pairs = m.get("pairs") or {}
    return {
        "scene": scene,
        "run": label,
        "correct": f"{m['correct']}/{m['registered']}/{m['images']}",
        "auc": f"{m['auc@3']:.1f} / {m['auc@5']:.1f} / {m['auc@10']:.1f}",
        "median_m": m.get("median_position_error", float("nan")),
        "max_m": m.get("max_position_error", float("nan")),
        "rot_deg": m.get("median_rotation_error_deg", float("nan")),
        "wrong": f"{pairs['wrong_pairs_admitted']}/{pairs['wrong_pairs']}" if pairs else "-",
        "wall": wall,
        "ratio": wall / peer_wall if peer_wall else float("nan"),
        "rss": rss,
        "models": len(m.get("other_models", [])) + 1,
    }


def print_rows(rows: list[dict[str, Any]]) -> None:
    print(
        "| scene | run | correct / registered / images | AUC@3/5/10 deg "
        "| median / max position error m | median rotation error deg "
        "| wrong pairs admitted / verified wrong | wall s | x peer | peak RSS MiB |"
    )
    print("|---|---|---|---|---|---:|---|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['scene']} | {r['run']} | {r['correct']} | {r['auc']} "
            f"| {r['median_m']:.3f} / {r['max_m']:.3f} | {r['rot_deg']:.2f} | {r['wrong']} "
            f"| {r['wall']:.0f} | {r['ratio']:.2f} | {r['rss']:.0f} |"
        )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--split", choices=("tuning", "test", "both"), default="both")
    ap.add_argument("--scenes", default=None, help="comma-separated scene names (overrides --split)")
    ap.add_argument("--variants", default="default", help="';'-separated METHOD [key=value ...]")
    ap.add_argument("--no-peer", action="store_true", help="skip COLMAP SIFT (no ratio column)")
    ap.add_argument("--match-cache", default=None, help="raw pair matches shared by runs (variants)")
    ap.add_argument("--repeats", type=int, default=1, help="run the peer and each variant N times")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--one", nargs=3, metavar=("IMAGES", "OUT", "VARIANT"), help=argparse.SUPPRESS)
    ap.add_argument("--reference", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.reference:
        sift_reference(args.reference)
        return 0
    if args.one:
        run_one(Path(args.one[0]), Path(args.one[1]), args.one[2], args.match_cache)
        return 0
    if args.scenes:
        scenes = args.scenes.split(",")
    else:
        scenes = SPLITS["tuning"] + SPLITS["test"] if args.split == "both" else SPLITS[args.split]
    variants = [v.strip() for v in args.variants.split(";") if v.strip()]
    rows: list[dict[str, Any]] = []
    for scene in scenes:
        images, gt = scene_paths(scene)
        for k in range(args.repeats):
            # repeats show the runs' own spread: matching and COLMAP's threaded mapping are not
            # reproducible to the millimetre
            tag = f" #{k + 1}" if args.repeats > 1 else ""
            base = args.out / scene / (f"repeat{k + 1}" if args.repeats > 1 else "")
            peer_wall = None
            if not args.no_peer:
                out = base / PEER
                wall, rss, rc = timed([sys.executable, "bench/peer_colmap.py", str(images), str(out)])
                if rc == 0:
                    peer_wall = wall
                    rows.append(row(scene, f"COLMAP SIFT (peer){tag}", judge(out, gt), wall, rss, peer_wall))
                    print_rows(rows[-1:])
            for spec in variants:
                out = base / spec.replace(" ", "_").replace("/", "-")
                cmd = [sys.executable, "bench/real_sfm.py", "--one", str(images), str(out), spec]
                if args.match_cache:
                    cmd += ["--match-cache", args.match_cache]
                wall, rss, rc = timed(cmd)
                if rc:
                    print(f"{scene} {spec}: failed (exit {rc})", file=sys.stderr)
                    continue
                rows.append(row(scene, spec + tag, judge(out, gt), wall, rss, peer_wall))
                print_rows(rows[-1:])
            sys.stdout.flush()
    print()
    print_rows(rows)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
