"""A Celery worker's peak memory on a whole project: a synthetic scene submitted through the API
(Redis mode), matched and reconstructed by one `geomatch worker` with the default cache setting.

    .venv/bin/python bench/worker_memory.py                      # 30 images at 1024 px
    .venv/bin/python bench/worker_memory.py --aerial 2 --ground 6 --resize 640 --pairs exhaustive

Why a bench and not a test: a worker's memory is bounded by its caches (GEOMATCH_CACHE_MB, each
cache in bytes) plus what no cache holds (networks, torch's allocator, one pair's working set).
Only a whole project shows whether the bound holds; the target is <= 3 GB peak RSS for
a worker on a 30-image 1024 px project.

The worker runs as its own process tree (Celery's prefork pool, concurrency 1, as deployed); every
process of the tree is sampled every 0.5 s, and the table gives the largest VmHWM (the kernel's
peak resident set of one process) and the largest sum of VmRSS over the tree. The images are
rendered at ``--width`` x ``--height`` by `geomatch synth`; the model is evaluated against the
scene's ground truth, so memory is never bought with lost cameras.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import print_table
from load_upload import start_server

REDIS = "redis://127.0.0.1:6379/0"


def _status(pid: int) -> dict[str, int]:
    out = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            k, _, v = line.partition(":")
            if k in ("VmHWM", "VmRSS"):
                out[k] = int(v.split()[0])  # kB
    except OSError:
        pass
    return out


def _tree(root: int) -> list[int]:
    """The process and its descendants (from /proc's parent links)."""
    parent: dict[int, int] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            with contextlib.suppress(OSError, IndexError, ValueError):
                parent[int(d.name)] = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
    out, todo = [], [root]
    while todo:
        p = todo.pop()
        out.append(p)
        todo += [c for c, pp in parent.items() if pp == p]
    return out


class Sampler(threading.Thread):
    def __init__(self, root: int) -> None:
        super().__init__(daemon=True)
        self.root = root
        self.hwm_kb: dict[int, int] = {}
        self.tree_rss_kb = 0
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            total = 0
            for pid in _tree(self.root):
                s = _status(pid)
                total += s.get("VmRSS", 0)
                self.hwm_kb[pid] = max(self.hwm_kb.get(pid, 0), s.get("VmHWM", 0))
            self.tree_rss_kb = max(self.tree_rss_kb, total)
            self.stop.wait(0.5)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--aerial", type=int, default=4)
    ap.add_argument("--ground", type=int, default=26)
    ap.add_argument("--width", type=int, default=1024)
    ap.add_argument("--height", type=int, default=768)
    ap.add_argument("--resize", type=int, default=1024)
    ap.add_argument("--pairs", default="sequential:2")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cache-mb", type=int, default=None, help="GEOMATCH_CACHE_MB (default: unset)")
    ap.add_argument("--keep", type=Path, default=None, help="keep the scene, logs and model here")
    args = ap.parse_args()
    geomatch = str(Path(sys.executable).parent / "geomatch")
    tmp = tempfile.TemporaryDirectory()
    root = args.keep or Path(tmp.name)
    root.mkdir(parents=True, exist_ok=True)
    scene, home = root / "scene", root / "home"
    subprocess.run(
        [geomatch, "synth", str(scene), "--aerial", str(args.aerial), "--ground", str(args.ground),
         "--seed", str(args.seed), "--width", str(args.width), "--height", str(args.height)],
        check=True,
        capture_output=True,
    )  # fmt: skip
    home.mkdir(exist_ok=True)
    server, url, key = start_server(home, REDIS)
    env = {
        k: v for k, v in os.environ.items() if not k.startswith(("GEOMATCH_", "REDIS_URL", "DATABASE_URL"))
    }
    env.update(
        GEOMATCH_HOME=str(home),
        GEOMATCH_LOG_FORMAT="text",
        REDIS_URL=REDIS,
        GEOMATCH_REDIS_PREFIX=f"gmload-{os.getpid()}:",  # as load_upload.start_server
    )
    if args.cache_mb is not None:
        env["GEOMATCH_CACHE_MB"] = str(args.cache_mb)
    log = (home / "worker.log").open("wb")
    worker = subprocess.Popen([geomatch, "worker"], env=env, stdout=log, stderr=subprocess.STDOUT)
    sampler = Sampler(worker.pid)
    sampler.start()
    t0 = time.perf_counter()
    try:
        sub = subprocess.run(
            [geomatch, "submit", str(scene / "images"), "--server", url, "--key", key, "--aerial-list",
             str(scene / "aerial.txt"), "--pairs", args.pairs, "--resize", str(args.resize), "--out",
             str(root / "model"), "--no-progress"],
            capture_output=True,
            text=True,
        )  # fmt: skip
        wall = time.perf_counter() - t0
        if sub.returncode != 0:
            print(sub.stdout[-2000:], sub.stderr[-2000:], file=sys.stderr)
            return 1
    finally:
        sampler.stop.set()
        sampler.join()
        worker.terminate()
        server.terminate()
        worker.wait(60)
        server.wait(60)
    ev = subprocess.run(
        [geomatch, "eval", str(root / "model"), "--gt", str(scene / "gt")], capture_output=True, text=True
    )
    summary = json.loads((root / "model" / "summary.json").read_text())
    correct = _correct(ev.stdout)
    row = dict(
        images=args.aerial + args.ground,
        px=args.resize,
        pairs=args.pairs,
        matched=summary.get("database", {}).get("matched_pairs", -1),
        cache=str(args.cache_mb) if args.cache_mb is not None else "default",
        hwm=max(sampler.hwm_kb.values()) / 1024,
        tree=sampler.tree_rss_kb / 1024,
        procs=len(sampler.hwm_kb),
        correct=correct,
        wall=wall,
    )
    print_table(
        "A worker's peak memory on one project (Redis mode, `geomatch worker` defaults)",
        [
            ("images", "images", "d"),
            ("px", "px", "d"),
            ("pairs", "pairs", "s"),
            ("pairs matched", "matched", "d"),
            ("GEOMATCH_CACHE_MB", "cache", "s"),
            ("peak RSS of one process MB", "hwm", ".0f"),
            ("peak RSS of the tree MB", "tree", ".0f"),
            ("processes", "procs", "d"),
            ("correct cameras", "correct", "s"),
            ("wall s", "wall", ".0f"),
        ],
        [row],
    )
    return 0


def _correct(eval_stdout: str) -> str:
    for line in eval_stdout.splitlines():
        if line.startswith("correct "):
            return line.split()[1]
    return "?"


if __name__ == "__main__":
    sys.exit(main())
