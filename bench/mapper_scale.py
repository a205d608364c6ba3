"""Which COLMAP mapper for a project of N photos: incremental against global, on surveys of 100 to
1000 photos whose matches are known, so that the mapper alone is measured.

A project's mapping time is the mapper's; the matching before it is measured in bench/scale.py.
Here each survey (bench/write_rate.survey: nadir cameras on serpentine lines over ground with
relief, each photo paired with its K nearest as ``gps:K``) gets its keypoints from the exact
projections of the scene points (0.3 px noise) and its matches from the points two photos share,
plus 10 % wrong ones, written straight into a COLMAP database and verified by COLMAP
(``pycolmap.verify_matches``). ``geomatch.sfm.mapping.reconstruct`` then maps a copy with each
mapper (the view-graph checks on, no track refinement: there are no pixels), and the model is
judged against the cameras the survey was built from (correct: <= 3 deg, <= 5 % of the extent).

    python bench/mapper_scale.py --sizes 100,300,1000
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
from common import print_table
from write_rate import ALT, META, H, W, plan, project, survey

from geomatch.eval.evaluate import evaluate_run
from geomatch.sfm.colmapdb import COLMAP_OFFSET, ColmapDatabase
from geomatch.synth.camera import rotmat_to_qvec

OUT = Path(__file__).parent / "out" / "mapper_scale"
R_NADIR = np.diag([1.0, -1.0, -1.0])  # camera x east, y south, z down (write_rate.project)


def build(n: int, k: int, folder: Path) -> int:
    """The survey's database and ground truth in ``folder``; returns the pairs written."""
    cams, X = survey(n)
    rng = np.random.default_rng(2)
    folder.mkdir(parents=True, exist_ok=True)
    db_path = folder / "database.db"
    db_path.unlink(missing_ok=True)
    names = [f"img_{i:05d}.jpg" for i in range(n)]
    seen: list[np.ndarray] = []
    with ColmapDatabase(db_path) as db:
        ids = [db.add_image(name, META, share_camera=True) for name in names]
        for i, c in enumerate(cams):
            idx, px = project(c, X)
            px = px + rng.normal(0, 0.3, px.shape).astype(np.float32)
            db.db.write_keypoints(ids[i], (px + COLMAP_OFFSET).astype(np.float32))
            seen.append(idx)
        pairs = plan(cams, k)
        with pycolmap.DatabaseTransaction(db.db):
            for i, j in pairs:
                _, a, b = np.intersect1d(seen[i], seen[j], return_indices=True)
                wrong = int(0.1 * len(a))
                a = np.r_[a, rng.integers(0, len(seen[i]), wrong)]
                b = np.r_[b, rng.integers(0, len(seen[j]), wrong)]
                db.db.write_matches(ids[i], ids[j], np.c_[a, b].astype(np.uint32))
    (folder / "pairs.txt").write_text("".join(f"{names[i]} {names[j]}\n" for i, j in pairs))
    pycolmap.verify_matches(str(db_path), str(folder / "pairs.txt"))
    gt = folder / "gt"
    gt.mkdir(exist_ok=True)
    f = float(META.focal_px or 0.0)
    (gt / "cameras.txt").write_text(f"1 PINHOLE {W} {H} {f} {f} {W / 2} {H / 2}\n")
    q = " ".join(f"{v:.12g}" for v in rotmat_to_qvec(R_NADIR))
    lines = []
    for i, c in enumerate(cams):
        t = " ".join(f"{v:.12g}" for v in -R_NADIR @ c)
        lines.append(f"{i + 1} {q} {t} 1 {names[i]}\n\n")
    (gt / "images.txt").write_text("".join(lines))
    (gt / "points3D.txt").write_text("")
    return len(pairs)


def map_once(folder: Path, mapper: str) -> dict[str, Any]:
    """One mapper on a copy of the survey's database, in a child process (its peak memory apart)."""
    out = folder / mapper
    shutil.rmtree(out, ignore_errors=True)
    (out / "images").mkdir(parents=True)  # COLMAP reads colours from it; there are no pixels
    shutil.copy(folder / "database.db", out / "database.db")
    code = (
        "import sys, json, time; from pathlib import Path; "
        "from geomatch.sfm.mapping import MappingSettings, reconstruct; "
        "import resource; t = time.perf_counter(); "
        "s = reconstruct(Path(sys.argv[1]) / 'database.db', Path(sys.argv[1]) / 'images', Path(sys.argv[1]), "
        "MappingSettings(mapper=sys.argv[2], track_refine=False)); "
        "print(json.dumps({'wall': time.perf_counter() - t, 'stages': s['mapping_seconds'], "
        "'rss_mib': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))"
    )
    r = subprocess.run(
        [sys.executable, "-c", code, str(out), mapper], capture_output=True, text=True, check=True
    )
    stats = json.loads(r.stdout.strip().splitlines()[-1])
    m = evaluate_run(out, folder / "gt").metrics
    return {
        "mapper": mapper,
        "mapper_s": stats["stages"]["mapper"],
        "view_graph_s": stats["stages"]["view_graph"],
        "rss": stats["rss_mib"],
        "registered": f"{m['registered']}/{m['images']}",
        "correct": f"{m['correct']}/{m['images']}",
        "auc10": m.get("auc@10", 0.0),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="100,300,1000")
    ap.add_argument("--k", type=int, default=12, help="pairs per photo, as gps:K (the default plan)")
    ap.add_argument("--mappers", default="incremental,global")
    args = ap.parse_args()
    rows = []
    for n in (int(s) for s in args.sizes.split(",")):
        folder = OUT / f"survey{n}"
        t = time.perf_counter()
        pairs = build(n, args.k, folder)
        built = time.perf_counter() - t
        for mapper in args.mappers.split(","):
            row = {"photos": n, "pairs": pairs, "build_s": built, **map_once(folder, mapper)}
            print(json.dumps(row), flush=True)
            rows.append(row)
    print_table(
        f"Mappers on nadir surveys with known matches (altitude {ALT:.0f} m, gps:{args.k} pairs)",
        [
            ("photos", "photos", "d"),
            ("pairs", "pairs", "d"),
            ("mapper", "mapper", "s"),
            ("mapper s", "mapper_s", ".1f"),
            ("view graph s", "view_graph_s", ".1f"),
            ("peak RSS MiB", "rss", ".0f"),
            ("registered", "registered", "s"),
            ("correct", "correct", "s"),
            ("AUC@10", "auc10", ".1f"),
        ],
        rows,
    )


if __name__ == "__main__":
    main()
