"""Leave-one-out localization (``geomatch localize``) beside a full re-run of ``geomatch run``.

    OMP_NUM_THREADS=1 .venv/bin/python bench/localize.py --strecha Herz-Jesus-P8,fountain-P11
    OMP_NUM_THREADS=1 .venv/bin/python bench/localize.py --strecha '' --seeds 0 --test-seeds 100

For each scene the project is run once with every photo (``geomatch run``, a fresh process, its
wall time measured: that is the "full re-run with the photo added", the same run for every photo
of the scene, since the project with the photo added is the whole scene). Then each registered
photo in turn is left out: the model without it is the full model with its frame deregistered
(geomatch/eval/leaveout.py says why that is a fair test: the photo's keypoints, tracks and pose
are gone, its matches to the model are made afresh) and the photo is localized against it with
the library's defaults. Its error is measured after aligning the model's OTHER cameras to the
ground truth; the full run's error for the same photo beside it (aligned the same way).

Synthetic air-to-ground scenes (``--seeds`` tuning, ``--test-seeds`` test): each ground photo is
localized against the aerial + ground model without it, and against the model without any ground
image (every ground frame deregistered: what the aerial images alone hold of the model). The full
runs are ``geomatch run`` with its default plan (every pair; a ground x aerial pair tiled), as a
user re-runs a project.

Success = localized (any confidence) with rotation error <= 1 deg and position error <= 1 % of
the scene extent. Every photo is localized cold, as a new ``geomatch localize`` process does it:
a new matcher (networks loaded, nothing in memory) reading the features the run kept in its
folder (``OUT/features``), from which the photo's own features are taken out first (a new photo
was never extracted). Python's imports (torch: a few seconds) are the only part of a process's
start not in the time.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
from real_sfm import DATA, ROOT, timed

from geomatch.eval.leaveout import pose_error, without_image
from geomatch.localize import LocalizeOptions, Project, localize_photos, project_matcher

OUT = ROOT / "bench" / "out" / "localize"
SPLITS = {"tuning": ["fountain-P11", "Herz-Jesus-P8", "castle-P19"], "test": ["entry-P10"]}


def full_run(images: Path, out: Path, extra: list[str]) -> float:
    """The project run with every photo, in a fresh process; its wall seconds (cached in the
    folder, so a second benchmark run re-times nothing)."""
    stamp = out / "bench_wall.json"
    if stamp.is_file() and (out / "sparse" / "0" / "images.bin").is_file():
        return float(json.loads(stamp.read_text())["wall_s"])
    shutil.rmtree(out, ignore_errors=True)
    cmd = [sys.executable, "-m", "geomatch.cli", "run", str(images), "--out", str(out), *extra]
    wall, _, rc = timed(cmd)
    if rc:
        raise SystemExit(f"geomatch run failed on {images}")
    stamp.write_text(json.dumps({"wall_s": wall}))
    return wall


def features_without(run: Path, images: Path, name: str, dest: Path) -> Path:
    """The run's feature store without the photo's own features (hard links: the store is only
    read). A photo's features are keyed by its pixels, plain or quarter-turned (the rotation
    probe's); crops are cut from aerial images, never from a ground photo."""
    from geomatch.imagefolder import Images
    from geomatch.imageio import image_key
    from geomatch.matching.rotation import quarter_turn

    image = Images(images)[name]
    own = {f"{image_key(quarter_turn(image, t))}.pt" for t in range(4)}
    shutil.rmtree(dest, ignore_errors=True)
    shutil.copytree(
        run / "features", dest, copy_function=os.link, ignore=lambda _d, files: [f for f in files if f in own]
    )
    return dest


def leave_one_out(
    run: Path, images: Path, gt: Path, names: list[str], model: Path | None = None
) -> list[dict[str, Any]]:
    """One row per photo of ``names``: localized against ``model`` (default the run's) without it."""
    model = model or run / "sparse" / "0"
    full = pycolmap.Reconstruction(str(run / "sparse" / "0"))
    truth = pycolmap.Reconstruction(str(gt))
    rows = []
    for name in names:
        work = run.parent / f"loo-{run.name}" / name
        reduced = without_image(model, name, work)
        features = features_without(run, images, name, work / "features")
        t0 = time.perf_counter()
        matcher = project_matcher(Project.find(run), features)
        [loc] = localize_photos(run, [images / name], LocalizeOptions(), matcher, model_dir=reduced)
        wall = time.perf_counter() - t0
        row: dict[str, Any] = {
            "name": name,
            "localized": loc.localized,
            "confidence": loc.confidence,
            "inliers": loc.inliers,
            "seconds": wall,
            "reason": loc.reason,
        }
        if loc.localized and loc.cam_from_world is not None and loc.center is not None:
            w, x, y, z = loc.cam_from_world["qvec"]
            R = pycolmap.Rotation3d(np.array([x, y, z, w])).matrix()
            # aligned by the full model's other cameras: every reduced model is in its frame, and
            # a model of two aerial images alone has too few cameras to be aligned by itself
            err = pose_error(full, truth, name, R, np.array(loc.center))
            if err is not None:
                row.update(rot=err[0], pos=err[1], pct=err[2])
        im = full.find_image_with_name(name)
        if im is not None and im.has_pose:
            R = im.cam_from_world().rotation.matrix()
            err = pose_error(full, truth, name, R, np.asarray(im.projection_center()))
            if err is not None:
                row.update(full_rot=err[0], full_pos=err[1], full_pct=err[2])
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


def summarise(
    split: str, scene: str, setting: str, rows: list[dict[str, Any]], run_wall: float
) -> dict[str, Any]:
    ok = [r for r in rows if r.get("rot", 99) <= 1.0 and r.get("pct", 99) <= 1.0 and r["localized"]]
    located = [r for r in rows if "rot" in r]
    full = [r for r in rows if "full_rot" in r]
    secs = [r["seconds"] for r in rows]

    def med(key: str, rs: list[dict[str, Any]]) -> float:
        return float(np.median([r[key] for r in rs])) if rs else float("nan")

    def top(key: str, rs: list[dict[str, Any]]) -> float:
        return float(np.max([r[key] for r in rs])) if rs else float("nan")

    return {
        "split": split,
        "scene": scene,
        "setting": setting,
        "success": f"{len(ok)}/{len(rows)}",
        "high": f"{sum(r['confidence'] == 'high' for r in rows)}/{len(rows)}",
        "pos": f"{med('pos', located):.3f} / {top('pos', located):.3f}",
        "pct": f"{med('pct', located):.2f} / {top('pct', located):.2f}",
        "rot": f"{med('rot', located):.2f} / {top('rot', located):.2f}",
        "full_pos": f"{med('full_pos', full):.3f} / {top('full_pos', full):.3f}",
        "full_rot": f"{med('full_rot', full):.2f} / {top('full_rot', full):.2f}",
        "sec": f"{np.median(secs):.1f} / {np.max(secs):.1f}",
        "run_s": f"{run_wall:.0f}",
        "ratio": f"{np.max(secs) / run_wall:.3f}",
        "median_ratio": f"{np.median(secs) / run_wall:.3f}",
    }


HEADER = (
    "| split | scene | model | success (<=1 deg, <=1 %) | high confidence | position error m (median / max) "
    "| % of extent (median / max) | rotation error deg (median / max) "
    "| full run: position m | full run: rotation deg "
    "| s per photo (median / max) | full re-run s | max photo s / re-run s | median photo s / re-run s "
    "| other-scene photos localized | their max inliers |"
)
KEYS = (
    "split",
    "scene",
    "setting",
    "success",
    "high",
    "pos",
    "pct",
    "rot",
    "full_pos",
    "full_rot",
    "sec",
    "run_s",
    "ratio",
    "median_ratio",
    "others_localized",
    "others_max_inliers",
)


def print_table(rows: list[dict[str, Any]]) -> None:
    print(HEADER)
    print("|---|---|---|" + "---:|" * (len(KEYS) - 3))
    for r in rows:
        print("| " + " | ".join(str(r.get(k, "-")) for k in KEYS) + " |")
    sys.stdout.flush()


def other_scene(run: Path, matcher: Any, photos: list[str]) -> dict[str, Any]:
    """Package photos of other things (scikit-image's) localized against the scene's model: how
    many come back localized, and the most inliers any of them got (the margin under
    ``min_inliers``)."""
    from PIL import Image

    from geomatch.synth.photos import photo

    folder = run.parent / "other-photos"
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name in photos:
        path = folder / f"{name}.png"
        if not path.is_file():
            Image.fromarray(photo(name)).save(path)
        paths.append(path)
    found = localize_photos(run, paths, LocalizeOptions(), matcher)
    for loc in found:
        print(
            json.dumps(
                {k: loc.to_json()[k] for k in ("name", "localized", "confidence", "inliers", "matches")}
            )
        )
    return {
        "others_localized": f"{sum(r.localized for r in found)}/{len(found)}",
        "others_max_inliers": max((r.inliers for r in found), default=0),
    }


def strecha(scene: str, split: str, others: list[str]) -> dict[str, Any]:
    base = DATA / "strecha" / scene
    run = OUT / scene / "full"
    wall = full_run(base / "images", run, [])
    names = sorted(json.loads((run / "summary.json").read_text())["registered_names"])
    rows = leave_one_out(run, base / "images", base / "gt", names)
    (OUT / scene / "rows.json").write_text(json.dumps(rows, indent=2))
    others_row = other_scene(run, project_matcher(Project.find(run)), others)
    return summarise(split, scene, "all other photos", rows, wall) | others_row


def aerial_only(run: Path, ground: list[str]) -> Path:
    """The run's model without its ground images (deregistered, as a left-out photo is: the
    points only they saw go with them). Mapping the database with the aerial images alone was
    tried first: COLMAP made no model of a scene's two aerial images (\"Failed to create any
    sparse model\", with the initial pair's angle lowered to 2 deg too)."""
    return without_image(run / "sparse" / "0", ground, run.parent / "aerial-model")


def synthetic(seed: int, split: str, args: argparse.Namespace) -> list[dict[str, Any]]:
    from geomatch.synth.aerial import write_scene

    root = OUT / f"synth_a{args.aerial}_g{args.ground}_s{seed}"
    scene = root / "scene"
    if not (scene / "gt" / "images.txt").is_file():
        write_scene(scene, args.aerial, args.ground, seed)
    aerial = (scene / "aerial.txt").read_text().split()
    run = root / "full"
    wall = full_run(scene / "images", run, ["--aerial-list", str(scene / "aerial.txt")])
    registered = json.loads((run / "summary.json").read_text())["registered_names"]
    ground = sorted(n for n in registered if n not in aerial)
    out = []
    rows = leave_one_out(run, scene / "images", scene / "gt", ground)
    out.append(summarise(split, f"synthetic seed {seed}", "aerial + other ground", rows, wall))
    model = aerial_only(run, ground)
    rows = leave_one_out(run, scene / "images", scene / "gt", ground, model)
    out.append(summarise(split, f"synthetic seed {seed}", "aerial only", rows, wall))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--strecha", default="Herz-Jesus-P8,fountain-P11", help="comma-separated scenes ('' none)"
    )
    ap.add_argument("--seeds", default="0", help="synthetic tuning seeds")
    ap.add_argument("--test-seeds", default="100", help="synthetic test seeds (never tune on them)")
    ap.add_argument("--aerial", type=int, default=2)
    ap.add_argument("--ground", type=int, default=4)
    ap.add_argument(
        "--others", default="coffee,astronaut,brick,grass", help="package photos of other scenes (Strecha)"
    )
    args = ap.parse_args()
    others = [o for o in args.others.split(",") if o]
    table = []
    for scene in filter(None, args.strecha.split(",")):
        split = "test" if scene in SPLITS["test"] else "tuning"
        table.append(strecha(scene, split, others))
        print_table(table[-1:])
    for split, seeds in (("tuning", args.seeds), ("test", args.test_seeds)):
        for seed in filter(None, seeds.split(",")):
            table += synthetic(int(seed), split, args)
            print_table(table[-2:])
    print()
    print_table(table)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "table.json").write_text(json.dumps(table, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
