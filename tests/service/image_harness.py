"""The service run from the built image: `geomatch serve`, `geomatch worker` and `geomatch keys`
inside a container of the image (buildah, chroot isolation, the host's network), so the tests
that drive a Deployment over loopback drive the image instead (`make image`, docker/build_local.sh).

No Docker engine is needed, nor a registry: buildah with the vfs driver and chroot isolation runs as
root without a daemon, cgroups or overlay mounts. The container shares the host's network (the
server listens on loopback, Redis is the host's) and process table (chroot isolation makes no PID
namespace), so the host finds the container's processes among the descendants of the `buildah run`
that started them.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path
from types import ModuleType
from typing import Any

from .harness import Deployment

IMAGE_ENV = "GEOMATCH_TEST_IMAGE"  # set by `make image`: the service tests run from this image
DEFAULT_IMAGE = "localhost/geomatch:cpu"  # what docker/build_local.sh tags
STORAGE_DRIVER = os.environ.get("STORAGE_DRIVER", "vfs")
IMAGE_UID = 10001  # the Dockerfile's USER: /data must be writable by it
ROOT = Path(__file__).resolve().parents[2]


def buildah(*args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["buildah", "--storage-driver", STORAGE_DRIVER, *args],
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def image_name() -> str:
    return os.environ.get(IMAGE_ENV) or DEFAULT_IMAGE


def unavailable(image: str) -> str | None:
    """Why the image cannot be run here (the skip reason), or None. Costs nothing without buildah,
    so that `make test` on a machine without it (CI) is not slowed down."""
    if shutil.which("buildah") is None:
        return (
            "buildah is not installed: the image tests run the built image with buildah "
            "(apt-get install buildah debootstrap; `make image` builds and tests it, docs/deploy.md)"
        )
    if os.geteuid() != 0:
        return "not root: the image tests use rootful buildah (vfs storage, chroot isolation)"
    if buildah("inspect", "--type", "image", image, timeout=60).returncode != 0:
        return f"the image {image} is not built here (storage driver {STORAGE_DRIVER}): run `make image`"
    return None


def image_config(image: str) -> dict[str, Any]:
    """The image's Docker config (Entrypoint, Healthcheck, User ...)."""
    r = buildah("inspect", "--type", "image", image, timeout=60)
    assert r.returncode == 0, r.stderr
    return dict(json.loads(r.stdout)["Docker"]["config"])


def _healthcheck_module() -> ModuleType:
    """docker/healthcheck.py, for its /proc reading (the same rules the image's check applies)."""
    spec = importlib.util.spec_from_file_location(
        "geomatch_image_healthcheck", ROOT / "docker" / "healthcheck.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class ImageDeployment(Deployment):
    """A Deployment whose processes run in one container of ``image``; GEOMATCH_HOME is a host
    folder mounted at the image's /data, so the test reads the metadata store as before."""

    def __init__(self, root: Path, redis_url: str | None, image: str, **env: str) -> None:
        super().__init__(root, redis_url, **env)
        self.image = image
        self.home.mkdir(parents=True, exist_ok=True)
        os.chown(self.home, IMAGE_UID, IMAGE_UID)
        r = buildah("from", "--pull=never", "--name", f"gmtest-{self.uid}", image)
        assert r.returncode == 0, r.stderr
        self.container = r.stdout.strip().splitlines()[-1]
        self._hc = _healthcheck_module()

    def run_args(self) -> list[str]:
        """`buildah run` of this container: the host's network, /data from the host, the
        deployment's settings (all but GEOMATCH_HOME, which the image sets to /data)."""
        settings = [
            f"--env={k}={v}"
            for k, v in self.env.items()
            if (k.startswith("GEOMATCH_") and k != "GEOMATCH_HOME") or k in ("REDIS_URL", "DATABASE_URL")
        ]
        return [
            "buildah",
            "--storage-driver",
            STORAGE_DRIVER,
            "run",
            "--isolation",
            "chroot",
            "--network",
            "host",
            f"--volume={self.home}:/data",
            *settings,
            self.container,
            "--",
        ]

    def command(self) -> list[str]:
        return [*self.run_args(), "geomatch"]

    # -- the container's processes ------------------------------------------------------------
    @staticmethod
    def descendants(pid: int) -> list[int]:
        """The processes under ``pid``: a `buildah run` starts its runtime, which starts the
        command chrooted into a mount of the container of its own (so the root directory does not
        tell which container a process is in; its ancestry does)."""
        children: dict[int, list[int]] = {}
        for entry in Path("/proc").iterdir():
            if entry.name.isdigit():
                with contextlib.suppress(OSError, IndexError, ValueError):
                    stat = (entry / "stat").read_text()
                    children.setdefault(int(stat.rsplit(")", 1)[1].split()[1]), []).append(int(entry.name))
        out, todo = [], [pid]
        while todo:
            for c in children.get(todo.pop(), []):
                out.append(c)
                todo.append(c)
        return sorted(out)

    def main_pid(self, role: str, timeout: float = 60.0) -> int:
        """The `geomatch ROLE` main process in the container: the image's Python running the
        console script (not buildah's exec helper, whose arguments look alike), whose parent is not
        one too (prefork children are)."""
        procs = {"serve": [self.server] if self.server else [], "worker": self.workers}[role]
        deadline = time.monotonic() + timeout
        while True:
            found = {}
            for proc in procs:
                for pid in self.descendants(proc.pid):
                    argv = self._hc.cmdline(pid)
                    args = self._hc.geomatch_args(argv)
                    if args and args[0] == role and os.path.basename(argv[0]).startswith("python"):
                        found[pid] = args
            mains = [p for p in found if self._hc.ppid(p) not in found]
            if mains:
                return min(mains)
            if time.monotonic() > deadline:
                raise RuntimeError(f"no `geomatch {role}` in the container:\n{self.logs()}")
            time.sleep(0.5)

    def healthcheck(self, pid: int) -> subprocess.CompletedProcess[str]:
        """The image's own HEALTHCHECK command, run inside the container for process ``pid``
        (--pid: the host's process table may hold other `geomatch` servers than this one)."""
        test = image_config(self.image)["Healthcheck"]["Test"]
        assert test[0] == "CMD", test
        return subprocess.run(
            [*self.run_args(), *test[1:], "--pid", str(pid)],
            capture_output=True,
            text=True,
            timeout=120,
        )

    def stop(self) -> None:
        spawned = [*self.workers, *([self.server] if self.server else [])]
        inside = [pid for p in spawned if p.poll() is None for pid in self.descendants(p.pid)]
        super().stop()
        # what left the process group of its `buildah run` goes too (found before that ended)
        for pid in inside:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        buildah("rm", self.container)
