"""Load run: N concurrent clients uploading images to the API; prints errors and latency percentiles.

    .venv/bin/python bench/load_upload.py                      # starts an embedded `geomatch serve`
    .venv/bin/python bench/load_upload.py --clients 20 --uploads 10 --size 1024x768
    .venv/bin/python bench/load_upload.py --server http://host:8000 --key KEY   # an existing server

Each client creates its own project and uploads distinct JPEGs one request at a time (so every
upload is a new image: decoded in full, hashed, stored, registered). Images are made before the
clock starts. At the end the server is asked how many images each project holds.
"""

from __future__ import annotations

import argparse
import io
import os
import re
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np
from PIL import Image


def make_jpeg(rng: np.random.Generator, width: int, height: int) -> bytes:
    """Smooth random colour fields plus grain: compresses like a photo, not like noise or a flat image."""
    small = rng.integers(0, 256, (height // 32 + 1, width // 32 + 1, 3), dtype=np.uint8)
    img = np.asarray(Image.fromarray(small).resize((width, height), Image.BICUBIC), np.int16)
    img = np.clip(img + rng.integers(-12, 13, img.shape), 0, 255).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="JPEG", quality=90)
    return buf.getvalue()


def start_server(home: Path, redis_url: str | None) -> tuple[subprocess.Popen[bytes], str, str]:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {
        k: v for k, v in os.environ.items() if not k.startswith(("GEOMATCH_", "REDIS_URL", "DATABASE_URL"))
    }
    env.update(GEOMATCH_HOME=str(home), GEOMATCH_LOG_FORMAT="text")
    if redis_url:
        env.update(REDIS_URL=redis_url, GEOMATCH_REDIS_PREFIX=f"gmload-{os.getpid()}:")
    log = (home / "server.log").open("wb")
    geomatch = str(Path(sys.executable).parent / "geomatch")
    proc = subprocess.Popen(
        [geomatch, "serve", "--port", str(port)], env=env, stdout=log, stderr=subprocess.STDOUT
    )
    url = f"http://127.0.0.1:{port}"
    for _ in range(600):
        try:
            if httpx.get(f"{url}/readyz", timeout=2).status_code == 200:
                break
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    else:
        raise SystemExit(f"server did not start: {(home / 'server.log').read_text()[-2000:]}")
    if redis_url:
        r = subprocess.run(
            [geomatch, "keys", "create", "load"], env=env, capture_output=True, text=True, check=True
        )
        key = r.stdout.strip()
    else:
        m = re.search(r"API key \(tenant 'local'\): (\S+)", (home / "server.log").read_text())
        assert m, "no key printed"
        key = m.group(1)
    return proc, url, key


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clients", type=int, default=20)
    ap.add_argument("--uploads", type=int, default=5, help="uploads per client")
    ap.add_argument("--size", default="1024x768")
    ap.add_argument("--server", help="an existing server (default: start an embedded one)")
    ap.add_argument("--key")
    ap.add_argument("--redis", help="start the server in Redis mode with this REDIS_URL")
    args = ap.parse_args()
    width, height = (int(v) for v in args.size.split("x"))

    rng = np.random.default_rng(0)
    payloads = [[make_jpeg(rng, width, height) for _ in range(args.uploads)] for _ in range(args.clients)]
    mb = sum(len(p) for ps in payloads for p in ps) / 1e6

    proc = None
    tmp = tempfile.TemporaryDirectory(prefix="geomatch-load-")
    if args.server:
        url, key = args.server, args.key
    else:
        proc, url, key = start_server(Path(tmp.name), args.redis)
    headers = {"Authorization": f"Bearer {key}"}
    latencies: list[float] = []
    errors: list[str] = []
    projects: list[str] = []
    lock = threading.Lock()
    start = threading.Barrier(args.clients + 1)

    def client(i: int) -> None:
        with httpx.Client(base_url=url, headers=headers, timeout=120) as c:
            pid = c.post("/v1/projects", json={"name": f"load-{i}"}).json()["id"]
            with lock:
                projects.append(pid)
            start.wait()
            for j, data in enumerate(payloads[i]):
                t0 = time.perf_counter()
                try:
                    r = c.post(
                        f"/v1/projects/{pid}/images",
                        files=[("files", (f"img_{j:03d}.jpg", data, "image/jpeg"))],
                    )
                    ok, why = r.status_code == 201, f"HTTP {r.status_code}: {r.text[:120]}"
                except httpx.HTTPError as e:
                    ok, why = False, repr(e)
                dt = time.perf_counter() - t0
                with lock:
                    latencies.append(dt)
                    if not ok:
                        errors.append(why)

    threads = [threading.Thread(target=client, args=(i,)) for i in range(args.clients)]
    for t in threads:
        t.start()
    start.wait()
    t0 = time.perf_counter()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0

    with httpx.Client(base_url=url, headers=headers, timeout=60) as c:
        stored = sum(len(c.get(f"/v1/projects/{p}/images").json()["images"]) for p in projects)
    if proc is not None:
        proc.terminate()
        proc.wait(timeout=30)
    tmp.cleanup()

    ms = np.array(latencies) * 1000
    n = len(latencies)
    mode = "existing server" if args.server else ("server in Redis mode" if args.redis else "embedded server")
    print(
        f"\nload_upload: {args.clients} concurrent clients x {args.uploads} uploads, "
        f"one {width}x{height} JPEG per request"
    )
    print(f"({mb / n * 1000:.0f} kB on average), {mode} at {url}\n")
    print("| requests | errors | p50 ms | p95 ms | max ms | req/s | MB/s | images stored |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    print(
        f"| {n} | {len(errors)} | {np.percentile(ms, 50):.0f} | {np.percentile(ms, 95):.0f} | {ms.max():.0f} "
        f"| {n / wall:.1f} | {mb / wall:.1f} | {stored} |"
    )
    for e in errors[:5]:
        print("error:", e)
    return 0 if not errors and stored == n else 1


if __name__ == "__main__":
    sys.exit(main())
