"""Fixed-wing surveys: a field circled many times, return legs flown the other way with sparser
photos, banked turns photographed, near-infrared farmland, EXIF GPS only; ``geomatch run`` with
its defaults beside COLMAP's SIFT pipeline.

Each seed is a flight rendered once by ``geomatch synth --kind fixedwing`` (geomatch/synth/
fixedwing.py and farmtex.py; 640x480, 2.5 m GPS noise, 3 % of triggers failing, return legs 1.75x
the outbound legs' 30 m spacing) and cached under ``bench/out/fixedwing``. Seeds: tuning 1, 2, 3
(what defaults may be tuned on); test 101-105 (held out: report, never tune). The runs, each
a child process (wall time, peak RSS):

- ``geomatch run IMAGES --out OUT``, the defaults a user gets (its own GPS georeferencing);
- the peer, COLMAP SIFT through pycolmap (bench/peer_colmap.py: its spatial matcher on the EXIF
  GPS, incremental mapping, as a COLMAP user runs a georeferenced survey), georeferenced as
  COLMAP's ``model_aligner`` would: a robust similarity (geo/georef.robust_similarity, 10 m) from
  its cameras to the EXIF fixes.

Judged on the largest model (``sparse/0``): photos registered, photos left out, models, and
cameras placed wrong: more than 3x the GPS noise (7.5 m) from their true position, (a) in the
run's own georeferenced frame (what a user measures) and (b) after a robust similarity to the
truth (RANSAC at 3x the noise: the model's own shape). ``correct`` is geomatch eval's rule (3 deg,
5 % of the flight's extent). Each wrong or left-out photo is listed with where in the flight it
was taken (outbound, return, the turns; the loop), from the flight's ``gt/flight.json``, and
drawn on a map of the flight (``geomatch.png``, ``peer.png`` in the flight's folder).

    .venv/bin/python bench/fixedwing.py --seeds 1              # one tuning flight, both runs
    .venv/bin/python bench/fixedwing.py --split test
    .venv/bin/python bench/fixedwing.py --seeds 1 --runs peer  # one run only
    .venv/bin/python bench/fixedwing.py --seeds 1,2 --report   # the saved rows again
    .venv/bin/python bench/fixedwing.py --seeds 1 --judge      # judge run folders as they are
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
from common import print_table
from scale import judge, timed

from geomatch.geo.geodesy import EnuFrame
from geomatch.geo.georef import camera_centres, robust_similarity
from geomatch.synth.sensors import GPS_ORIGIN

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "out" / "fixedwing"
SPLITS = {"tuning": (1, 2, 3), "test": (101, 102, 103, 104, 105)}
PHOTOS = 160
WRONG_FACTOR = 3.0  # a camera farther than this many GPS sigmas from the truth is misplaced

COLUMNS = [
    ("seed", "seed", "d"),
    ("split", "split", "s"),
    ("run", "run", "s"),
    ("wall s", "wall", ".0f"),
    ("peak RSS MiB", "rss_mib", ".0f"),
    ("registered", "registered", "s"),
    ("left out", "left_out", "d"),
    ("models", "models", "d"),
    ("wrong, own georeference (> 3 sigma)", "wrong_georef_n", "d"),
    ("wrong, similarity to truth (> 3 sigma)", "wrong_similar_n", "d"),
    ("error m, own georeference (median / max)", "georef_error", "s"),
    ("correct (eval)", "correct", "s"),
]


def split_of(seed: int) -> str:
    return next((name for name, seeds in SPLITS.items() if seed in seeds), "other")


def scene_dir(seed: int, photos: int) -> Path:
    return OUT / f"fixedwing{photos}_s{seed}"


def render(seed: int, photos: int) -> dict[str, Any]:
    """The flight rendered once (a finished folder is reused) by ``geomatch synth``, timed."""
    scene = scene_dir(seed, photos)
    done = scene / "render.json"
    if done.is_file():
        return dict(json.loads(done.read_text()))
    scene.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "geomatch.cli", "synth", str(scene), "--kind", "fixedwing"]
    cmd += ["--photos", str(photos), "--seed", str(seed)]
    wall, rss, rc = timed(cmd, scene / "render.log")
    if rc:
        sys.exit(f"rendering seed {seed} failed (log: {scene / 'render.log'})")
    info = {"seconds": wall, "per_photo": wall / photos, "rss_mib": rss}
    done.write_text(json.dumps(info) + "\n")
    return info


def where(scene: Path) -> dict[str, str]:
    """Each photo's place in the flight: its part (outbound, return, a turn), loop and trigger."""
    flight = json.loads((scene / "gt" / "flight.json").read_text())
    return {
        t["name"]: f"{t['part']}, loop {t['loop']}, roll {t['roll_deg']:+.0f} deg"
        for t in flight["triggers"]
        if t["name"]
    }


def georeferenced_centres(out: Path, model: Path, truth_frame: EnuFrame) -> dict[str, np.ndarray] | None:
    """geomatch's cameras in the truth's ENU frame, as its own georeferencing put them (the run's
    frame is ENU at its first fix: moved through WGS84); None when it did not georeference."""
    s = json.loads((out / "summary.json").read_text())
    if not s.get("georeferenced") or "origin" not in s:
        return None
    o = s["origin"]
    frame = EnuFrame(float(o["lat"]), float(o["lon"]), float(o["alt"]))
    centres = camera_centres(pycolmap.Reconstruction(str(model)))
    return {n: truth_frame.from_geodetic(*frame.to_geodetic(c)) for n, c in centres.items()}


def placement(out: Path, scene: Path, own_georef: bool) -> dict[str, Any]:
    """Cameras of ``sparse/0`` against the true positions: in the run's own georeferenced frame
    (``own_georef``), else moved to the EXIF fixes by a robust similarity (the peer's
    model_aligner step); and after a robust similarity to the truth itself."""
    truth = json.loads((scene / "gt" / "gps.json").read_text())
    sigma = float(truth["sigma_m"])
    limit = WRONG_FACTOR * sigma
    true = {n: np.asarray(v) for n, v in truth["true_enu"].items()}
    model = out / "sparse" / "0"
    if not model.is_dir():
        return {"wrong_georef": {}, "wrong_similar": {}, "georef_error": "-", "limit_m": limit}
    centres = camera_centres(pycolmap.Reconstruction(str(model)))
    names = sorted(n for n in centres if n in true)
    src = np.stack([centres[n] for n in names])
    dst = np.stack([true[n] for n in names])
    placed: np.ndarray | None = None
    if own_georef:
        geo = georeferenced_centres(out, model, GPS_ORIGIN)
        if geo is not None:
            placed = np.stack([geo[n] for n in names])
    else:
        fixes = np.stack([np.asarray(truth["gps_enu"][n]) for n in names])
        fit = robust_similarity(src, fixes, threshold=10.0)
        if fit is not None:
            placed = fit.sim.apply(src)
    georef_err = np.linalg.norm(placed - dst, axis=1) if placed is not None else np.full(len(names), np.inf)
    to_truth = robust_similarity(src, dst, threshold=limit)
    sim_err = (
        np.linalg.norm(to_truth.sim.apply(src) - dst, axis=1)
        if to_truth is not None
        else np.full(len(names), np.inf)
    )
    return {
        "limit_m": limit,
        "wrong_georef": {n: float(e) for n, e in zip(names, georef_err, strict=True) if e > limit},
        "wrong_similar": {n: float(e) for n, e in zip(names, sim_err, strict=True) if e > limit},
        "georef_error": f"{np.median(georef_err):.2f} / {np.max(georef_err):.2f}",
        "error_georef_m": {n: float(e) for n, e in zip(names, georef_err, strict=True)},
        "error_similar_m": {n: float(e) for n, e in zip(names, sim_err, strict=True)},
    }


def run_one(
    seed: int, photos: int, which: str, rendered: dict[str, Any], judge_only: bool = False
) -> dict[str, Any]:
    """One run as a child process, judged; ``judge_only``: the run's folder as it is (a run
    finished elsewhere, or one that outlived this script), judged without its wall time and
    peak memory (the summary's own total stands for the time)."""
    scene = scene_dir(seed, photos)
    images = scene / "images"
    if which == "geomatch":
        out = scene / "geomatch"
        cmd = [sys.executable, "-m", "geomatch_app", "run", str(images), "--out", str(out)]
        label = "geomatch run (defaults)"
    else:
        out = scene / "colmap"
        cmd = [sys.executable, "bench/peer_colmap.py", str(images), str(out), "--matcher", "spatial"]
        label = "COLMAP SIFT (spatial, incremental)"
    if judge_only:
        total = json.loads((out / "summary.json").read_text())["timings"]["total"]
        wall, rss = float(total), None
    else:
        if which == "geomatch":
            import shutil

            shutil.rmtree(out, ignore_errors=True)
        wall, rss, rc = timed(cmd, scene / f"{which}.log")
        if rc:
            sys.exit(f"{label} failed on seed {seed} (log: {scene / f'{which}.log'})")
    row: dict[str, Any] = {
        "seed": seed,
        "split": split_of(seed),
        "photos": photos,
        "run": label,
        "wall": wall,
        "rss_mib": rss,
        "render_per_photo": rendered["per_photo"],
    }
    row.update(judge(out, scene / "gt"))
    s = json.loads((out / "summary.json").read_text())
    row["models"] = int(s.get("models", 0))
    row["left_out"] = int(row["unregistered"])
    p = placement(out, scene, own_georef=which == "geomatch")
    row.update(p)
    row["wrong_georef_n"] = len(p["wrong_georef"])
    row["wrong_similar_n"] = len(p["wrong_similar"])
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0")) if (out / "sparse" / "0").is_dir() else None
    registered = {im.name for im in rec.images.values() if im.has_pose} if rec is not None else set()
    places = where(scene)
    row["left_out_names"] = {n: places[n] for n in sorted(places) if n not in registered}
    (scene / f"{which}.row.json").write_text(json.dumps(row, indent=1) + "\n")
    plot(row, scene / f"{which}.png")
    return row


def diagnosis(rows: list[dict[str, Any]]) -> str:
    """Every misplaced and left-out photo of each row, with where in the flight it was taken."""
    lines = []
    for r in rows:
        places = where(scene_dir(r["seed"], r["photos"]))
        lines.append(f"\nseed {r['seed']} ({r['split']}), {r['run']}:")
        wrong = sorted(set(r["wrong_georef"]) | set(r["wrong_similar"]))
        for n in wrong:
            g, s = r["error_georef_m"].get(n, float("nan")), r["error_similar_m"].get(n, float("nan"))
            lines.append(
                f"  misplaced {n}: {g:.1f} m georeferenced, {s:.1f} m after a similarity; {places[n]}"
            )
        for n, place in r["left_out_names"].items():
            lines.append(f"  left out  {n}: {place}")
        if not wrong and not r["left_out_names"]:
            lines.append("  every photo registered and placed within 3 sigma")
    return "\n".join(lines)


def plot(row: dict[str, Any], path: Path) -> None:
    """The flight from above: every photo at its true position, by part of the flight, those the
    run misplaced ringed red and those it left out crossed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    flight = json.loads((scene_dir(row["seed"], row["photos"]) / "gt" / "flight.json").read_text())
    colours = {"outbound": "tab:green", "return": "tab:orange"}
    fig, ax = plt.subplots(figsize=(7, 7))
    wrong = set(row["wrong_georef"]) | set(row["wrong_similar"])
    for t in flight["triggers"]:
        if not t["name"]:
            continue
        x, y, _ = t["position"]
        ax.plot(x, y, "o", ms=4, color=colours.get(t["part"], "tab:blue"))
        if t["name"] in wrong:
            ax.plot(x, y, "o", ms=10, mfc="none", mec="red")
        if t["name"] in row["left_out_names"]:
            ax.plot(x, y, "kx", ms=9)
    ax.set_aspect("equal")
    ax.set_xlabel("east m")
    ax.set_ylabel("north m")
    ax.set_title(
        f"seed {row['seed']}, {row['run']}: green outbound, orange return, blue turns;\n"
        "red ring misplaced, cross left out"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="", help="comma-separated seeds (default: the split's)")
    ap.add_argument("--split", choices=tuple(SPLITS), default="tuning")
    ap.add_argument("--photos", type=int, default=PHOTOS)
    ap.add_argument("--runs", default="geomatch,peer", help="geomatch, peer: comma-separated")
    ap.add_argument("--report", action="store_true", help="print the saved rows (and redraw), run nothing")
    ap.add_argument("--render-only", action="store_true", help="render (and cache) the flights")
    ap.add_argument("--judge", action="store_true", help="judge the runs' folders as they are, run nothing")
    args = ap.parse_args()
    seeds = [int(x) for x in args.seeds.split(",") if x] or list(SPLITS[args.split])
    runs = [r.strip() for r in args.runs.split(",") if r.strip()]
    if set(runs) - {"geomatch", "peer"}:
        sys.exit(f"--runs: unknown {sorted(set(runs) - {'geomatch', 'peer'})}")
    rows: list[dict[str, Any]] = []
    for seed in seeds:
        scene = scene_dir(seed, args.photos)
        if args.report:
            for w in runs:
                if (scene / f"{w}.row.json").is_file():
                    rows.append(json.loads((scene / f"{w}.row.json").read_text()))
                    plot(rows[-1], scene / f"{w}.png")
            continue
        rendered = render(seed, args.photos)
        print(
            f"seed {seed}: {args.photos} photos rendered, {rendered['per_photo']:.2f} s a photo", flush=True
        )
        if args.render_only:
            continue
        for which in runs:
            rows.append(run_one(seed, args.photos, which, rendered, args.judge))
            print(
                f"seed {seed} {which}: {rows[-1]['registered']} registered, "
                f"{rows[-1]['wrong_georef_n']} misplaced",
                flush=True,
            )
    if args.render_only:
        return 0
    print_table(
        f"Fixed-wing flights, {args.photos} photos a flight; wrong: > {WRONG_FACTOR:g} sigma of GPS noise "
        "from the true position",
        COLUMNS,
        rows,
    )
    print(diagnosis(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
