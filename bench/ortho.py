"""The map (geomatch.ortho): time, peak memory and position accuracy of the orthophoto.

Three parts, each printing a table:

- ``--sizes 100,300``: synthetic survey flights (``geomatch synth --kind flight``: rolling terrain,
  buildings, GPS with 1.5 m noise, 640x480 photos) rendered once and cached under
  ``bench/out/ortho/flight-N``, ``geomatch run`` on them (its matching and mapping seconds, its
  peak RSS), then the map of that run in a child process of its own (seconds per step, peak RSS by
  ``os.wait4``), and the orthophoto against the truth: the ground's texture rendered at each map
  pixel's position, shifts of 64 px patches by phase correlation, in GSD, patches that touch a
  building's footprint (grown by 3 m) left out. ``absolute`` includes the model's own
  georeferencing error (GPS); ``relative`` is after taking out the median shift (what seams and
  the sparse DSM do to the map on their own).
- ``--exact``: flights whose model is the true cameras with points on the true surface (some
  thrown metres off): the map step alone on flat ground and on 17 % slopes (tests/ortho_scene.py).
- ``--real RUN``: the map of a real run folder (``geomatch run IMAGES --out RUN`` first), its
  picture and crops across seams for the docs (``--pictures DIR``).

    .venv/bin/python bench/ortho.py --exact
    .venv/bin/python bench/ortho.py --sizes 100,300
    .venv/bin/python bench/ortho.py --real RUN --pictures docs/img --name brighton_beach_full
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # tests/ortho_scene.py: the exact-model scenes

from common import print_table  # noqa: E402

from geomatch.ortho.accuracy import patch_offsets  # noqa: E402

OUT = ROOT / "bench" / "out" / "ortho"
PY = sys.executable


def child(argv: list[str]) -> tuple[float, float, int, str]:
    """Run ``argv`` (a fresh interpreter): wall seconds, peak RSS MiB, exit code, stdout."""
    t = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, cwd=ROOT, text=True)
    out = proc.stdout.read() if proc.stdout else ""
    _, status, usage = os.wait4(proc.pid, 0)
    return time.perf_counter() - t, usage.ru_maxrss / 1024, os.waitstatus_to_exitcode(status), out


MAP_CODE = """
import json, sys
from geomatch.ortho import make_map
print(json.dumps(make_map(sys.argv[1]).record))
"""


def run_map(run: Path) -> dict[str, Any]:
    wall, rss, rc, out = child([PY, "-c", MAP_CODE, str(run)])
    if rc != 0:
        raise SystemExit(f"the map of {run} failed ({rc})")
    rec: dict[str, Any] = json.loads(out.strip().splitlines()[-1])
    rec["wall_s"], rec["peak_rss_mib"] = wall, rss
    return rec


def truth_offsets(ortho: Path, world: Any, building_margin: float = 3.0) -> dict[str, Any]:
    """Patch shifts of the orthophoto against the world's ground texture (buildings masked)."""
    import pyproj
    import rasterio

    from geomatch.synth.sensors import GPS_ORIGIN

    with rasterio.open(ortho) as src:
        data = np.moveaxis(src.read(), 0, -1)
        t, crs = src.transform, pyproj.CRS.from_user_input(src.crs.to_wkt())
    h, w = data.shape[:2]
    cols, rows = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    e, n = t.c + cols * t.a, t.f + rows * t.e
    lon, lat = pyproj.Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(e.ravel(), n.ravel())
    enu = GPS_ORIGIN.from_geodetic(np.asarray(lat), np.asarray(lon), np.zeros(lat.size))
    x, y = enu[:, 0], enu[:, 1]
    truth = np.clip(world.ground.sample(x, y) + 0.5, 0, 255).astype(np.uint8).reshape(h, w, 3)
    skip = np.zeros(x.size, bool)
    m = building_margin
    for b in world.buildings_near(x.min(), x.max(), y.min(), y.max()):
        skip |= (x > b.lo[0] - m) & (x < b.hi[0] + m) & (y > b.lo[1] - m) & (y < b.hi[1] + m)
    off = patch_offsets(data, truth, skip=skip.reshape(h, w))
    out: dict[str, Any] = {"absolute": off.summary()}
    if len(off.shifts):
        rel = off.shifts - np.median(off.shifts, axis=0)
        err = np.hypot(rel[:, 0], rel[:, 1])
        out["relative"] = {"median_gsd": float(np.median(err)), "p95_gsd": float(np.percentile(err, 95))}
    return out


# -- synthetic flights through the whole pipeline --------------------------------------------------
def flight(size: int, seed: int) -> dict[str, Any]:
    folder = OUT / f"flight-{size}"
    run = folder / "run"
    if not (folder / "gt" / "flight.json").is_file():
        subprocess.run(
            [
                PY,
                "-m",
                "geomatch_app",
                "synth",
                str(folder),
                "--kind",
                "flight",
                "--photos",
                str(size),
                "--seed",
                str(seed),
            ],
            check=True,
            cwd=ROOT,
        )
    row_path = folder / "run_row.json"
    if row_path.is_file():
        run_row = json.loads(row_path.read_text())
    else:
        wall, rss, rc, _ = child([PY, "-m", "geomatch_app", "run", str(folder / "images"), "--out", str(run)])
        if rc != 0:
            raise SystemExit(f"geomatch run on the {size}-photo flight failed ({rc})")
        run_row = {"run_wall_s": wall, "run_peak_rss_mib": rss}
        row_path.write_text(json.dumps(run_row))
    summary = json.loads((run / "summary.json").read_text())
    t = summary.get("timings", {})
    rec = run_map(run)
    from geomatch.synth.flightplan import FOCAL_PER_WIDTH
    from geomatch.synth.world import World

    plan = json.loads((folder / "gt" / "flight.json").read_text())
    world = World(seed, texel_m=plan["altitude"] / (FOCAL_PER_WIDTH * plan["width"]) / 2)
    acc = truth_offsets(run / "odm_orthophoto" / "odm_orthophoto.tif", world)
    return row(f"flight {size}", size, summary.get("registered"), t, run_row, rec, acc)


def row(
    label: str,
    photos: int,
    registered: Any,
    t: dict[str, Any],
    run_row: dict[str, Any],
    rec: dict[str, Any],
    acc: dict[str, Any],
) -> dict[str, Any]:
    a, r = acc.get("absolute", {}), acc.get("relative", {})
    sec = rec["seconds"]
    match_map = (t.get("matching") or 0) + (t.get("mapping") or 0) if t else None
    return {
        "label": label,
        "photos": photos,
        "registered": registered,
        "match_s": t.get("matching"),
        "mapping_s": t.get("mapping"),
        "run_rss": run_row.get("run_peak_rss_mib"),
        "dsm_s": sec["dsm"],
        "gains_s": sec["gains"],
        "mosaic_s": sec["orthophoto"],
        "map_s": rec["wall_s"],
        "ratio": rec["wall_s"] / match_map if match_map else None,
        "map_rss": rec["peak_rss_mib"],
        "gsd_cm": 100 * rec["gsd_m"],
        "size": f"{rec['size_px'][0]} x {rec['size_px'][1]}",
        "patches": a.get("patches"),
        "absolute": pair(a),
        "relative": pair(r),
    }


def pair(a: dict[str, Any]) -> str | None:
    if a.get("median_gsd") is None:
        return None
    return f"{a['median_gsd']:.2f} / {a['p95_gsd']:.2f}"


COLUMNS = [
    ("set", "label", "s"),
    ("photos", "photos", "d"),
    ("registered", "registered", ""),
    ("matching s", "match_s", ".0f"),
    ("mapping s", "mapping_s", ".0f"),
    ("run peak MiB", "run_rss", ".0f"),
    ("DSM s", "dsm_s", ".1f"),
    ("gains s", "gains_s", ".1f"),
    ("mosaic s", "mosaic_s", ".1f"),
    ("map s (process)", "map_s", ".1f"),
    ("map / (matching + mapping)", "ratio", ".2f"),
    ("map peak MiB", "map_rss", ".0f"),
    ("GSD cm", "gsd_cm", ".1f"),
    ("pixels", "size", "s"),
    ("patches", "patches", ""),
    ("error median / p95, GSD", "absolute", "s"),
    ("less the median shift, GSD", "relative", "s"),
]


# -- exact models ------------------------------------------------------------------------------------
def exact(photos: int) -> list[dict[str, Any]]:
    from tests.ortho_scene import make_scene

    rows = []
    for label, kw in (("exact, flat", {}), ("exact, 17 % slopes", {"relief": (150.0, 4.0)})):
        folder = OUT / f"exact-{photos}-{'flat' if not kw else 'slope'}"
        scene = make_scene(folder, photos=photos, width=640, height=480, altitude=80.0, **kw)
        rec = run_map(scene.run)
        acc = truth_offsets(scene.run / "odm_orthophoto" / "odm_orthophoto.tif", scene.world)
        rows.append(row(label, photos, photos, {}, {}, rec, acc))
    return rows


# -- time and memory against photo count, without rendering ---------------------------------------
def scale_scene(folder: Path, photos: int, seed: int = 1, width: int = 640, height: int = 480) -> Path:
    """A survey of ``photos`` photos whose model is exact (the flight plan's cameras, points where
    rays of random pixels meet the rolling terrain) and whose photos are smoothed noise, not
    renders: the map's cost depends on the pixels and the geometry, not on what the photos show,
    and rendering a thousand photos would take an hour here. For time and memory only."""
    import cv2
    import pycolmap

    from geomatch.synth.flightplan import FlightPlan, aerial_cameras
    from geomatch.synth.groundtruth import write_gt
    from geomatch.synth.sensors import GPS_ORIGIN
    from geomatch.synth.world import Terrain

    run = folder / "run"
    if (run / "summary.json").is_file():
        return run
    plan = FlightPlan.make(photos, width, height, 80.0)
    cams, _ = aerial_cameras(plan, seed)
    terrain = Terrain(seed)
    rng = np.random.default_rng(seed)
    images = folder / "images"
    images.mkdir(parents=True, exist_ok=True)
    lines = []
    for cam in cams:
        noise = rng.integers(0, 256, (height // 4, width // 4, 3), dtype=np.uint8)
        img = cv2.GaussianBlur(cv2.resize(noise, (width, height), interpolation=cv2.INTER_CUBIC), (0, 0), 1.0)
        cv2.imwrite(str(images / cam.name), img, [cv2.IMWRITE_JPEG_QUALITY, 90])
        uv = np.column_stack([rng.uniform(0, width, 300), rng.uniform(0, height, 300), np.ones(300)])
        d = (uv @ np.linalg.inv(cam.K).T) @ cam.R  # world directions
        o = cam.centre
        t = o[2] / -d[:, 2]
        for _ in range(8):
            t = (o[2] - terrain.height(o[0] + t * d[:, 0], o[1] + t * d[:, 1])) / -d[:, 2]
        for x, y, z in o + t[:, None] * d:
            lines.append(f"{len(lines) + 1} {x:.4f} {y:.4f} {z:.4f} 128 128 128 0.5\n")
    text = folder / "model_text"
    write_gt(cams, text)
    (text / "points3D.txt").write_text("# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]\n" + "".join(lines))
    (run / "sparse" / "0").mkdir(parents=True, exist_ok=True)
    pycolmap.Reconstruction(str(text)).write(str(run / "sparse" / "0"))
    summary = {
        "image_dir": str(images),
        "georeferenced": True,
        "frame": "ENU",
        "origin": GPS_ORIGIN.as_dict(),
    }
    (run / "summary.json").write_text(json.dumps({**summary, "registered": len(cams), "images": len(cams)}))
    return run


def scale(photos: int) -> dict[str, Any]:
    rec = run_map(scale_scene(OUT / f"scale-{photos}", photos))
    return row(f"noise photos, exact model {photos}", photos, photos, {}, {}, rec, {})


# -- a real run: the picture and the seams -------------------------------------------------------------
def real(run: Path, pictures: Path | None, name: str) -> dict[str, Any]:
    rec = run_map(run)
    targets = rec.get("gcp_targets")
    if targets:  # a GCP model: its targets found on the orthophoto (geomatch/ortho/targets.py)
        rows = targets["points"]
        found = [r for r in rows if r["found"]]
        print_table(
            f"GCP targets located in the orthophoto ({len(found)} of {len(rows)} found)",
            [
                ("point", "name", "s"),
                ("role", "role", "s"),
                ("map vs model m", "map_vs_model_m", ".3f"),
                ("map vs survey m", "map_vs_survey_m", ".3f"),
            ],
            found,
        )
        print(
            f"\ncheck points: map RMSE {targets.get('check_rmse_horizontal_m')} m against the model's "
            f"{targets.get('model_check_rmse_horizontal_m')} m"
        )
    if pictures is not None:
        pictures.mkdir(parents=True, exist_ok=True)
        seam_pictures(run, pictures, name)
    return rec


def seam_pictures(run: Path, pictures: Path, name: str, crop: int = 320, count: int = 3) -> None:
    """The map at 1200 px with the seams drawn, and ``count`` full-resolution crops centred on
    seams well inside the map (where three or more photos meet, the most telling)."""
    import cv2
    import rasterio
    from PIL import Image

    from geomatch.ortho.make import MapOptions, prepare
    from geomatch.ortho.mosaic import labels

    prep = prepare(run, None, MapOptions())
    step = 16
    lab = labels(prep.mosaic, step)
    edge = np.zeros(lab.shape, bool)
    edge[:, 1:] |= lab[:, 1:] != lab[:, :-1]
    edge[1:, :] |= lab[1:, :] != lab[:-1, :]
    edge &= lab >= 0
    edge[:, 1:] &= lab[:, :-1] >= 0  # not the map's own border
    edge[1:, :] &= lab[:-1, :] >= 0
    with rasterio.open(run / "odm_orthophoto" / "odm_orthophoto.tif") as src:
        f = min(1.0, 900 / max(src.width, src.height))
        small = np.moveaxis(
            src.read(
                out_shape=(4, round(src.height * f), round(src.width * f)),
                resampling=rasterio.enums.Resampling.average,
            ),
            0,
            -1,
        ).copy()
        # seam nodes far from the edge of the map and of each other
        inside = cv2.erode((lab >= 0).astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
        rr, cc = np.nonzero(edge & inside)
        picked: list[tuple[int, int]] = []
        order = np.random.default_rng(0).permutation(len(rr))
        for i in order:
            r, c = int(rr[i]) * step, int(cc[i]) * step
            if all(abs(r - a) + abs(c - b) > 4 * crop for a, b in picked):
                picked.append((r, c))
            if len(picked) == count:
                break
        crops = []
        for k, (r, c) in enumerate(picked):
            r0, c0 = max(0, r - crop // 2), max(0, c - crop // 2)
            win = rasterio.windows.Window(c0, r0, crop, crop)
            tile = np.moveaxis(src.read(window=win, boundless=True), 0, -1)
            crops.append(tile[..., :3])
            sr, sc = round(r * f), round(c * f)
            cv2.rectangle(small, (sc - 12, sr - 12), (sc + 12, sr + 12), (255, 255, 0, 255), 2)
            cv2.putText(
                small, str(k + 1), (sc + 14, sr), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 0, 255), 2
            )
    ys, xs = np.nonzero(edge)
    for y, x in zip(ys, xs, strict=True):
        cv2.circle(small, (round(x * step * f), round(y * step * f)), 1, (255, 0, 0, 255), -1)
    # docs pictures as JPEG (photographs: a fraction of a PNG's bytes), the transparent part white
    rgb = np.where(small[..., 3:4] > 0, small[..., :3], 255).astype(np.uint8)
    Image.fromarray(rgb).save(pictures / f"ortho_{name}.jpg", quality=85, optimize=True)
    if crops:
        strip = Image.fromarray(np.concatenate(crops, axis=1))
        strip.save(pictures / f"ortho_{name}_seams.jpg", quality=90, optimize=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="", help="synthetic flights through geomatch run, e.g. 100,300")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument(
        "--exact", type=int, nargs="?", const=30, default=0, help="exact-model scenes of N photos"
    )
    ap.add_argument(
        "--scale", default="", help="time and memory on exact models of N noise photos, e.g. 100,1000"
    )
    ap.add_argument("--real", type=Path, help="a real run folder to map")
    ap.add_argument("--pictures", type=Path, help="with --real: where the pictures go")
    ap.add_argument("--name", default="real")
    args = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    rows = []
    if args.exact:
        rows += exact(args.exact)
    for size in [int(s) for s in args.sizes.split(",") if s]:
        rows.append(flight(size, args.seed))
    for size in [int(s) for s in args.scale.split(",") if s]:
        rows.append(scale(size))
    if rows:
        print_table("Orthophoto: time, memory and position error against the truth", COLUMNS, rows)
        (OUT / "rows.json").write_text(json.dumps(rows, indent=1))
    if args.real:
        rec = real(args.real, args.pictures, args.name)
        keep = (
            "photos",
            "gsd_m",
            "dsm_cell_m",
            "size_px",
            "extent_m",
            "crs",
            "seconds",
            "wall_s",
            "peak_rss_mib",
        )
        print(json.dumps({k: rec[k] for k in keep}, indent=1))


if __name__ == "__main__":
    main()
