"""Load run: N concurrent uploaders x M images each, and K concurrent SSE watchers, against one
API process; prints requests, errors and p50/p95/max latency per operation.

    .venv/bin/python bench/load.py                                    # embedded `geomatch serve`
    .venv/bin/python bench/load.py --redis redis://127.0.0.1:6379/0   # Redis mode (no worker)
    .venv/bin/python bench/load.py --uploaders 50 --images 10 --watchers 10 --size 640x480

Every uploader creates its own project and uploads distinct JPEGs one request at a time. The
watchers watch one match job (of a separate two-image project) the whole time the uploads run:
each opens `GET /v1/jobs/{id}/events`, times the first `event: job`, reads on for a second, closes
and opens again. In Redis mode no worker runs, so the job stays queued and its stream open; in
embedded mode it runs in the API process beside the uploads. At the end the server is asked how
many images each project holds.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from load_upload import make_jpeg, start_server


class Recorder:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.lat: dict[str, list[float]] = {}
        self.err: dict[str, list[str]] = {}

    def add(self, op: str, dt: float, error: str | None) -> None:
        with self.lock:
            self.lat.setdefault(op, []).append(dt)
            if error:
                self.err.setdefault(op, []).append(error)

    def table(self) -> str:
        rows = [
            "| operation | requests | errors | p50 ms | p95 ms | max ms |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        for op, lat in self.lat.items():
            ms = np.array(lat) * 1000
            rows.append(
                f"| {op} | {len(ms)} | {len(self.err.get(op, []))} | {np.percentile(ms, 50):.0f} "
                f"| {np.percentile(ms, 95):.0f} | {ms.max():.0f} |"
            )
        return "\n".join(rows)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--uploaders", type=int, default=50)
    ap.add_argument("--images", type=int, default=10, help="uploads per uploader")
    ap.add_argument("--watchers", type=int, default=10)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--redis", help="start the server in Redis mode with this REDIS_URL")
    args = ap.parse_args()
    width, height = (int(v) for v in args.size.split("x"))

    rng = np.random.default_rng(0)
    payloads = [[make_jpeg(rng, width, height) for _ in range(args.images)] for _ in range(args.uploaders)]
    tmp = tempfile.TemporaryDirectory(prefix="geomatch-load-")
    proc, url, key = start_server(Path(tmp.name), args.redis)
    headers = {"Authorization": f"Bearer {key}"}
    rec = Recorder()
    projects: list[str] = []
    done = threading.Event()

    with httpx.Client(base_url=url, headers=headers, timeout=120) as c:
        watched = c.post("/v1/projects", json={"name": "watched"}).json()["id"]
        files = [("files", (f"w{i}.jpg", make_jpeg(rng, width, height), "image/jpeg")) for i in range(2)]
        assert c.post(f"/v1/projects/{watched}/images", files=files).status_code == 201
        job_id = c.post(f"/v1/projects/{watched}/match", json={"resize": 160}).json()["job_id"]

    start = threading.Barrier(args.uploaders + args.watchers + 1)

    def op(c: httpx.Client, name: str, method: str, path: str, want: int, **kw: Any) -> httpx.Response | None:
        t0 = time.perf_counter()
        try:
            r = c.request(method, path, **kw)
            err = None if r.status_code == want else f"HTTP {r.status_code}: {r.text[:120]}"
        except httpx.HTTPError as e:
            r, err = None, repr(e)
        rec.add(name, time.perf_counter() - t0, err)
        return r

    def uploader(i: int) -> None:
        with httpx.Client(base_url=url, headers=headers, timeout=120) as c:
            start.wait()
            r = op(c, "create project", "POST", "/v1/projects", 201, json={"name": f"load-{i}"})
            if r is None or r.status_code != 201:
                return
            pid = r.json()["id"]
            projects.append(pid)
            for j, data in enumerate(payloads[i]):
                files = [("files", (f"img_{j:03d}.jpg", data, "image/jpeg"))]
                op(c, "upload image", "POST", f"/v1/projects/{pid}/images", 201, files=files)
            op(c, "list images", "GET", f"/v1/projects/{pid}/images", 200)

    def watcher() -> None:
        with httpx.Client(base_url=url, headers=headers, timeout=120) as c:
            start.wait()
            while not done.is_set():
                t0 = time.perf_counter()
                err, first = None, None
                try:
                    with c.stream("GET", f"/v1/jobs/{job_id}/events") as r:
                        if r.status_code != 200:
                            err = f"HTTP {r.status_code}"
                        else:
                            for line in r.iter_lines():
                                if first is None and line.startswith("event: job"):
                                    first = time.perf_counter() - t0
                                if first is not None and time.perf_counter() - t0 > first + 1.0:
                                    break
                except httpx.HTTPError as e:
                    err = repr(e)
                if first is None and err is None:
                    err = "stream closed before an event"
                rec.add("SSE first event", first if first is not None else time.perf_counter() - t0, err)

    threads = [threading.Thread(target=uploader, args=(i,)) for i in range(args.uploaders)]
    threads += [threading.Thread(target=watcher) for _ in range(args.watchers)]
    for t in threads:
        t.start()
    start.wait()
    t0 = time.perf_counter()
    for t in threads[: args.uploaders]:
        t.join()
    wall = time.perf_counter() - t0
    done.set()
    for t in threads[args.uploaders :]:
        t.join()

    with httpx.Client(base_url=url, headers=headers, timeout=60) as c:
        stored = sum(len(c.get(f"/v1/projects/{p}/images").json()["images"]) for p in projects)
        c.post(f"/v1/jobs/{job_id}/cancel")
    proc.terminate()
    proc.wait(timeout=30)
    tmp.cleanup()

    mode = "Redis mode (no worker)" if args.redis else "embedded"
    n = args.uploaders * args.images
    print(
        f"\nload: {args.uploaders} uploaders x {args.images} images ({width}x{height} JPEG, "
        f"one per request), "
        f"{args.watchers} SSE watchers, one API process, {mode}; uploads took {wall:.1f} s "
        f"({n / wall:.1f} uploads/s), images stored {stored}/{n}\n"
    )
    print(rec.table())
    errors = [e for es in rec.err.values() for e in es]
    for e in errors[:5]:
        print("error:", e)
    return 0 if not errors and stored == n else 1


if __name__ == "__main__":
    sys.exit(main())
