"""A thousand photos: synthetic survey flights of growing size, ``geomatch run`` end to end.

Each size is a nadir survey rendered once by ``geomatch synth --kind flight`` (serpentine lines,
GPS and DJI XMP on every photo, rolling terrain and buildings; geomatch/synth/flight.py) and cached
under ``bench/out/scale``, then run by the pipeline with the defaults a user of a GPS project gets
(``RunOptions()``: the ``auto`` plan, which is ``gps:12`` beyond 30 photos with fixes) in a child
process of its own, so its peak RSS (``os.wait4``) is the run's alone. Per size: the pairs planned,
seconds per stage, peak memory of the render and of the run, and registered and correct cameras
(geomatch/eval: <= 3 deg and <= 5 % of the flight's extent after a robust alignment; the median
position error in metres beside it, since 5 % of a kilometre is lenient).

Stages: ``features`` is the time inside the matcher's feature extraction (wherever it ran: the
plan's turn probes or the matching), ``plan`` and ``matching`` are the pipeline's own timings
less the features they extracted, ``writing`` is the COLMAP database writes (their verification;
a thread of their own, behind the matching), then the mapping's own laps (summary.json
``mapping_seconds``: ``view_graph``, ``track_refine``, ``mapper``, ``georeference``; ``verify`` is
folded into ``mapper``). ``--peer SIZES`` also runs COLMAP's SIFT pipeline with its spatial
matcher (bench/peer_colmap.py) on those sizes, judged the same way, with the mapper geomatch picks
at those sizes (``--peer-mapper``, global by default).

``--service embedded`` and ``--service redis`` run the same flight through the service as a cloud
batch user does (``geomatch submit FOLDER --wait --out``, the server's defaults): the embedded
server doing the work in its own process, or Redis with ``--workers`` ``geomatch worker``
processes (each its own host's worth: one Celery process tree). Their rows give the wall time
split at the reconstruct job's start (matching through the queue, then the mapping's own laps) and
the peak RSS of the largest process of each tree (server, or each worker), sampled every 0.5 s.

    .venv/bin/python bench/scale.py                      # 100, 300 and 1000 photos
    .venv/bin/python bench/scale.py --sizes 100 --peer 100
    .venv/bin/python bench/scale.py --sizes 100,300 --report   # table and plot of saved rows
    .venv/bin/python bench/scale.py --sizes 1000 --runs redis --workers 2   # the service alone
    .venv/bin/python bench/scale.py --render-only              # the flights alone, cached

Rows are saved per size (``ROW.json`` in the size's run folder) and the table and the log-log
plot (``bench/out/scale/scale.png``: seconds per stage against photos) are made from every saved
row of the sizes asked for, so a size run later joins the others.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from common import print_table
from load_upload import start_server
from worker_memory import REDIS, Sampler

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "out" / "scale"
STAGES = ("features", "plan", "matching", "writing", "view_graph", "track_refine", "mapper", "georeference")

COLUMNS = [
    ("photos", "photos", "d"),
    ("run", "run", "s"),
    ("pairs (plan)", "pairs", "s"),
    ("render s/photo", "render_per_photo", ".2f"),
    ("features s", "features", ".0f"),
    ("plan s", "plan", ".0f"),
    ("matching s", "matching", ".0f"),
    ("writing s", "writing", ".0f"),
    ("view graph s", "view_graph", ".0f"),
    ("track refine s", "track_refine", ".0f"),
    ("mapper s", "mapper", ".0f"),
    ("georef s", "georeference", ".1f"),
    ("total s", "total", ".0f"),
    ("peak RSS MiB (run, or server / each worker; render)", "rss", "s"),
    ("registered", "registered", "s"),
    ("correct", "correct", "s"),
    ("models", "models", "d"),
    ("position error m (median / max)", "position", "s"),
    ("wrong verified pairs (mapped)", "wrong_pairs", "s"),
]


def flight_dir(photos: int, ground: int, seed: int) -> Path:
    return OUT / f"flight{photos}_g{ground}_s{seed}"


def timed(cmd: list[str], log: Path) -> tuple[float, float, int]:
    """(wall seconds, peak RSS MiB, exit status) of a child process, its output into ``log``."""
    with open(log, "w") as f:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
    rc = os.waitstatus_to_exitcode(status)
    if rc:
        print(log.read_text()[-3000:], file=sys.stderr)
    return wall, usage.ru_maxrss / 1024, rc


def render(photos: int, ground: int, seed: int) -> dict[str, Any]:
    """The flight rendered (once: a complete folder is reused) by ``geomatch synth`` in a child."""
    scene = flight_dir(photos, ground, seed)
    done = scene / "render.json"
    if done.is_file():
        return dict(json.loads(done.read_text()))
    cmd = [sys.executable, "-m", "geomatch.cli", "synth", str(scene), "--kind", "flight"]
    cmd += ["--photos", str(photos), "--ground", str(ground), "--seed", str(seed)]
    scene.mkdir(parents=True, exist_ok=True)
    wall, rss, rc = timed(cmd, scene / "render.log")
    if rc:
        sys.exit(f"rendering {photos} photos failed")
    info = {"seconds": wall, "per_photo": wall / (photos + ground), "rss_mib": rss}
    done.write_text(json.dumps(info) + "\n")
    return info


# -- the child: one run with the stages timed ----------------------------------------------------
def worker(images: Path, out: Path) -> None:
    """``geomatch.pipeline.run`` with a user's defaults; the features' seconds counted by wrapping
    the matcher's extraction (outermost call per thread: the stored matcher calls the base one),
    split into those of the plan and those of the matching."""
    from geomatch.matching.matcher import Matcher
    from geomatch.matching.stored import StoredFeaturesMatcher
    from geomatch.pipeline import RunOptions, run
    from geomatch.pipeline import plan as planning

    spent = {"features": 0.0}
    local = threading.local()

    def timed_features(original: Any) -> Any:
        def features(self: Any, *a: Any, **k: Any) -> Any:
            if getattr(local, "inside", False):
                return original(self, *a, **k)
            local.inside = True
            t0 = time.perf_counter()
            try:
                return original(self, *a, **k)
            finally:
                spent["features"] += time.perf_counter() - t0
                local.inside = False

        return features

    Matcher.features = timed_features(Matcher.features)  # type: ignore[method-assign]
    StoredFeaturesMatcher.features = timed_features(StoredFeaturesMatcher.features)  # type: ignore[method-assign]
    plan = planning.plan

    def timed_plan(*a: Any, **k: Any) -> Any:
        before = spent["features"]
        try:
            return plan(*a, **k)
        finally:
            spent["plan_features"] = spent["features"] - before

    planning.plan = timed_plan  # type: ignore[assignment]
    shutil.rmtree(out, ignore_errors=True)
    run(images, out, RunOptions(progress=False))
    (out / "features_seconds.json").write_text(json.dumps(spent) + "\n")


# -- the parent ------------------------------------------------------------------------------------
def judge(out: Path, gt: Path) -> dict[str, Any]:
    """Cameras against the ground truth (geomatch eval), and the verified pairs its epipolar
    geometry calls wrong with how many of them reached the mapper (geomatch/eval/pairtruth.py)."""
    from geomatch.eval.evaluate import evaluate_run

    m = evaluate_run(out, gt).metrics
    nan = float("nan")
    median, largest = m.get("median_position_error", nan), m.get("max_position_error", nan)
    pairs = m.get("pairs") or {}
    return {
        "registered": f"{m['registered']}/{m['images']}",
        "correct": f"{m['correct']}/{m['images']}",
        "all_correct": m["correct"] == m["images"],
        "position": f"{median:.2f} / {largest:.2f}",
        "median_position": median,
        "max_position": largest,
        "wrong_pairs": f"{pairs.get('wrong_pairs', 0)} ({pairs.get('wrong_pairs_admitted', 0)})",
        "wrong": sorted(m["wrong"]),
        "unregistered": m["images"] - m["registered"],
    }


def run_geomatch(photos: int, ground: int, seed: int, rendered: dict[str, Any]) -> dict[str, Any]:
    scene = flight_dir(photos, ground, seed)
    out = scene / "geomatch"
    log = scene / "geomatch.log"
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", str(scene / "images"), str(out)]
    wall, rss, rc = timed(cmd, log)
    if rc:
        sys.exit(f"geomatch run failed on {photos} photos (log: {log})")
    s = json.loads((out / "summary.json").read_text())
    feats = json.loads((out / "features_seconds.json").read_text())
    t, m = s["timings"], s.get("mapping_seconds", {})
    row: dict[str, Any] = {
        "photos": photos + ground,
        "run": "geomatch run (defaults)",
        "pairs": f"{s['pairs']} ({s.get('pair_plan', '?')})",
        "pairs_planned": s["pairs"],
        "render_per_photo": rendered["per_photo"],
        "features": feats["features"],
        "plan": t["plan"] - feats.get("plan_features", 0.0),
        "matching": t["matching"] - (feats["features"] - feats.get("plan_features", 0.0)),
        "writing": t["writing"],
        "view_graph": m.get("view_graph", 0.0),
        "track_refine": m.get("track_refine", 0.0),
        "mapper": m.get("mapper", 0.0) + m.get("verify", 0.0),
        "georeference": m.get("georeference", 0.0),
        "total": t["total"],
        "wall": wall,
        "rss_mib": rss,
        "rss": f"{rss:.0f}; {rendered['rss_mib']:.0f}",
        "models": s.get("models", 0),
        "georeferenced": s.get("georeferenced"),
    }
    t0 = time.perf_counter()
    row.update(judge(out, scene / "gt"))
    row["eval_seconds"] = time.perf_counter() - t0
    (scene / "geomatch.row.json").write_text(json.dumps(row, indent=1) + "\n")
    return row


def plan_stage(home: Path) -> float | None:
    """The match job's plan stage as its plan step logged it: seconds from the job's start to its
    pairs planned, the plan's per-photo steps on every worker included (workers/photosteps.py)."""
    found = None
    for log in sorted(home.glob("*.log")):
        for line in log.read_text(errors="replace").splitlines():
            m = re.search(r"the plan stage took ([0-9.]+)s", line)
            if m:
                found = float(m.group(1))
    return found


def run_service(
    photos: int, ground: int, seed: int, rendered: dict[str, Any], mode: str, workers: int
) -> dict[str, Any]:
    """The flight through the service: ``geomatch submit --wait --out`` against a server started
    here (embedded, or Redis with ``workers`` worker processes), the model judged as the run's."""
    scene = flight_dir(photos, ground, seed)
    home = scene / f"service-{mode}"
    shutil.rmtree(home, ignore_errors=True)
    home.mkdir(parents=True)
    geomatch = str(Path(sys.executable).parent / "geomatch")
    procs: list[subprocess.Popen[bytes]] = []

    def start_workers() -> None:
        """The workers, once the server has made the storage: its readiness waits for them."""
        for _ in range(600):
            server_log = home / "server.log"
            if server_log.is_file() and "geomatch API on" in server_log.read_text(errors="replace"):
                break
            time.sleep(0.2)
        env = {
            k: v
            for k, v in os.environ.items()
            if not k.startswith(("GEOMATCH_", "REDIS_URL", "DATABASE_URL"))
        }
        # the prefix start_server gives the server (this process's pid), so the workers share its queues
        env.update(GEOMATCH_HOME=str(home), GEOMATCH_LOG_FORMAT="text", REDIS_URL=REDIS)
        env["GEOMATCH_REDIS_PREFIX"] = f"gmload-{os.getpid()}:"
        # the cores shared out, as docs/configuration.md has it for several workers on one host
        env["OMP_NUM_THREADS"] = str(max(1, (os.cpu_count() or 1) // workers))
        for i in range(workers):
            log = (home / f"worker{i}.log").open("wb")
            procs.append(
                subprocess.Popen([geomatch, "worker"], env=env, stdout=log, stderr=subprocess.STDOUT)
            )

    starter = threading.Thread(target=start_workers, daemon=True)
    if mode == "redis":
        starter.start()
    server, url, key = start_server(home, REDIS if mode == "redis" else None)
    if mode == "redis":
        starter.join()
    samplers = [Sampler(p.pid) for p in [server, *procs]]
    for sm in samplers:
        sm.start()
    out = home / "model"
    t0 = time.perf_counter()
    try:
        cmd = [geomatch, "submit", str(scene / "images"), "--server", url, "--key", key, "--wait"]
        cmd += ["--out", str(out), "--no-progress"]
        with open(home / "submit.log", "w") as f:
            rc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT).returncode
        wall = time.perf_counter() - t0
    finally:
        for sm in samplers:
            sm.stop.set()
            sm.join()
        for p in [*procs, server]:
            p.terminate()
        for p in [*procs, server]:
            p.wait(60)
    if rc:
        sys.exit(f"the service ({mode}) failed on {photos} photos (log: {home / 'submit.log'})")
    s = json.loads((out / "summary.json").read_text())
    m = s.get("mapping_seconds", {})
    mapping = float(s.get("timings", {}).get("mapping", sum(m.values())))
    peaks = [max(sm.hwm_kb.values(), default=0) / 1024 for sm in samplers]
    label = "service, embedded" if mode == "embedded" else f"service, Redis + {workers} workers"
    row: dict[str, Any] = {
        "photos": photos + ground,
        "run": f"{label} (`geomatch submit`)",
        "pairs": str(s.get("database", {}).get("matched_pairs", "?")),
        "render_per_photo": rendered["per_photo"],
        "features": None,
        "plan": plan_stage(home),
        "matching": wall - mapping,
        "writing": None,
        "view_graph": m.get("view_graph", 0.0),
        "track_refine": m.get("track_refine", 0.0),
        "mapper": m.get("mapper", 0.0) + m.get("verify", 0.0),
        "georeference": m.get("georeference", 0.0),
        "total": wall,
        "wall": wall,
        "rss_mib": max(peaks),
        "rss": " / ".join(f"{p:.0f}" for p in peaks) + f"; {rendered['rss_mib']:.0f}",
        "models": s.get("models", 0),
    }
    row.update(judge(out, scene / "gt"))
    (scene / f"service-{mode}.row.json").write_text(json.dumps(row, indent=1) + "\n")
    return row


def run_peer(photos: int, ground: int, seed: int, rendered: dict[str, Any], mapper: str) -> dict[str, Any]:
    scene = flight_dir(photos, ground, seed)
    name = "colmap" if mapper == "incremental" else f"colmap-{mapper}"
    out = scene / name
    cmd = [sys.executable, "bench/peer_colmap.py", str(scene / "images"), str(out), "--matcher", "spatial"]
    cmd += ["--mapper", mapper]
    wall, rss, rc = timed(cmd, scene / f"{name}.log")
    if rc:
        sys.exit(f"the COLMAP peer failed on {photos} photos")
    s = json.loads((out / "summary.json").read_text())
    t = s["timings"]
    row: dict[str, Any] = {
        "photos": photos + ground,
        "run": f"COLMAP SIFT (spatial, {mapper} mapper)",
        "pairs": "-",
        "render_per_photo": rendered["per_photo"],
        "features": t["extraction"],
        "plan": 0.0,
        "matching": t["matching"],
        "writing": 0.0,
        "view_graph": 0.0,
        "track_refine": 0.0,
        "mapper": t["mapping"],
        "georeference": 0.0,
        "total": t["total"],
        "wall": wall,
        "rss_mib": rss,
        "rss": f"{rss:.0f}; {rendered['rss_mib']:.0f}",
        "models": s.get("models", 0),
    }
    row.update(judge(out, scene / "gt"))
    (scene / f"{name}.row.json").write_text(json.dumps(row, indent=1) + "\n")
    return row


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    """Seconds per stage against photos, log-log, geomatch's rows; dashed lines grow as n and n^2
    through the smallest size's total, for reading the slopes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ours = sorted((r for r in rows if r["run"].startswith("geomatch")), key=lambda r: r["photos"])
    if not ours:
        return
    n = [r["photos"] for r in ours]
    fig, ax = plt.subplots(figsize=(7, 5))
    for stage in (*STAGES, "total"):
        secs = [max(r[stage], 0.01) for r in ours]
        ax.plot(n, secs, "o-", label=stage, lw=2.5 if stage == "total" else 1.2)
    for prefix, style in (("COLMAP", "ks--"), ("service, embedded", "b^--"), ("service, Redis", "rv--")):
        others = sorted((r for r in rows if r["run"].startswith(prefix)), key=lambda r: r["photos"])
        if others:
            name = "COLMAP SIFT" if prefix == "COLMAP" else prefix
            ax.plot([r["photos"] for r in others], [r["total"] for r in others], style, label=f"{name} total")
    if len(n) > 1:
        x0, y0 = n[0], ours[0]["total"]
        for power, style in ((1, ":"), (2, "--")):
            ax.plot([x0, n[-1]], [y0, y0 * (n[-1] / x0) ** power], "k" + style, lw=0.8, label=f"~ n^{power}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("photos")
    ax.set_ylabel("seconds")
    ax.set_title("geomatch run on synthetic survey flights (2 CPU cores)")
    ax.legend(fontsize=7, ncol=2)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="100,300,1000", help="survey photos per run, comma-separated")
    ap.add_argument("--ground", type=int, default=0, help="handheld photos of buildings added to each flight")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--peer", default="", help="sizes on which COLMAP's SIFT pipeline runs too")
    ap.add_argument("--peer-mapper", choices=("incremental", "global"), default="global")
    ap.add_argument("--runs", default="run", help="run, embedded, redis: comma-separated, in that order")
    ap.add_argument("--workers", type=int, default=2, help="worker processes of the redis run")
    ap.add_argument("--report", action="store_true", help="table and plot from saved rows, run nothing")
    ap.add_argument("--render-only", action="store_true", help="render (and cache) the flights, run nothing")
    ap.add_argument("--worker", nargs=2, type=Path, metavar=("IMAGES", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        worker(*args.worker)
        return 0
    sizes = [int(x) for x in args.sizes.split(",") if x]
    peer = {int(x) for x in args.peer.split(",") if x}
    rows: list[dict[str, Any]] = []
    for n in sizes:
        scene = flight_dir(n, args.ground, args.seed)
        if args.report:
            rows += [json.loads(p.read_text()) for p in sorted(scene.glob("*.row.json"))]
            continue
        rendered = render(n, args.ground, args.seed)
        print(
            f"{n} photos rendered: {rendered['per_photo']:.2f} s a photo, "
            f"peak RSS {rendered['rss_mib']:.0f} MiB",
            flush=True,
        )
        if args.render_only:
            continue
        runs = {r.strip() for r in args.runs.split(",") if r.strip()}
        if runs - {"run", "embedded", "redis"}:
            sys.exit(f"--runs: unknown {sorted(runs - {'run', 'embedded', 'redis'})}")
        if "run" in runs:
            rows.append(run_geomatch(n, args.ground, args.seed, rendered))
            print(json.dumps(rows[-1]), flush=True)
        for mode in ("embedded", "redis"):
            if mode in runs:
                rows.append(run_service(n, args.ground, args.seed, rendered, mode, args.workers))
                print(json.dumps(rows[-1]), flush=True)
        if n in peer:
            rows.append(run_peer(n, args.ground, args.seed, rendered, args.peer_mapper))
            print(json.dumps(rows[-1]), flush=True)
    if args.render_only:
        return 0
    print_table(
        f"Synthetic survey flights ({args.ground} ground photos, seed {args.seed}), geomatch run with "
        "its defaults; seconds per stage",
        COLUMNS,
        rows,
    )
    OUT.mkdir(parents=True, exist_ok=True)
    plot(rows, OUT / "scale.png")
    print(f"\nplot: {OUT / 'scale.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
