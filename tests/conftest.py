from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import torch

from geomatch import Matcher, MatcherConfig
from geomatch.synth.photos import WarpedPair, warped_pair

from .small_scene import GPS_NOISE_M, SEED, WITH_GPS, run_options, write_pairs

# two cores: one process uses both; under pytest-xdist (``make test``: two processes) one each, so
# that the two do not fight over the cores
torch.set_num_threads(1 if "PYTEST_XDIST_WORKER" in os.environ else 2)

TIERS = ("unit", "nets", "pipeline", "service", "browser", "chaos")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """A test without a tier would silently drop out of `make test-fast` or be run where it does not
    belong; one with two would be counted twice by anyone timing the tiers."""
    wrong = []
    for item in items:
        tiers = sorted({m.name for m in item.iter_markers() if m.name in TIERS})
        if len(tiers) != 1:
            wrong.append(f"{item.nodeid}: {', '.join(tiers) or 'no tier'}")
    if wrong:
        raise pytest.UsageError(
            "every test needs exactly one tier marker (" + ", ".join(TIERS) + "):\n" + "\n".join(wrong)
        )


@pytest.fixture(autouse=True)
def colmap_seed() -> None:
    """COLMAP's random numbers (its synthetic datasets, its samplers) from one seed at every
    test's start: otherwise they follow from whichever tests ran before in the same process, and a
    test's scene changes with the order pytest-xdist happens to give it."""
    import pycolmap

    pycolmap.set_random_seed(0)


@pytest.fixture(scope="session")
def matcher() -> Matcher:
    """One set of real networks for the whole session (weights load once)."""
    return Matcher(MatcherConfig(resize=480, device="cpu"))


@pytest.fixture(scope="session")
def astronaut_pair() -> WarpedPair:
    return warped_pair("astronaut", seed=1, strength=0.15)


def made_once(factory: pytest.TempPathFactory, name: str, make: Callable[[Path], None]) -> Path:
    """A folder ``make`` fills once for the whole test run: with pytest-xdist (``make test`` runs
    the files on two processes) the processes share it, the first one makes it under a file lock
    and the others wait for it, so minutes of matching are not spent once per process."""
    if "PYTEST_XDIST_WORKER" not in os.environ:
        folder = factory.mktemp(name)
        make(folder)
        return folder
    from filelock import FileLock

    folder = factory.getbasetemp().parent / name  # the run's folder, above each process's own
    made = folder.with_name(f"{name}.made")  # beside it: nothing in the folder but what make wrote
    with FileLock(f"{folder}.lock"):
        if not made.is_file():
            folder.mkdir(exist_ok=True)
            make(folder)
            made.touch()
    return folder


@pytest.fixture(scope="session")
def small_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """tests/small_scene.py's scene, rendered once (images/, gt/, aerial.txt)."""
    from geomatch.synth.aerial import write_scene

    def make(d: Path) -> None:
        write_scene(d, 2, 4, seed=SEED, gps_noise=GPS_NOISE_M, gps_names=WITH_GPS)
        write_pairs(d)

    return made_once(tmp_path_factory, "small-scene", make)


def _listing(folder: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.rglob("*")}


@pytest.fixture(scope="session")
def small_run(small_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """One ``geomatch run`` of the small scene for the whole session (matching it takes minutes):
    read it, never write into it; a test that re-runs, evaluates or exports into a run folder
    works on a copy (tests/small_scene.py's ``copy_of_run``). That nothing wrote into it is
    checked when the session ends."""
    from geomatch.cli import main

    def make(out: Path) -> None:
        args = ["run", str(small_scene / "images"), "--out", str(out)]
        assert main([*args, *run_options(small_scene)]) == 0

    out = made_once(tmp_path_factory, "small-run", make)
    before = _listing(out)
    yield out
    assert _listing(out) == before, "a test wrote into the shared run; it should work on a copy_of_run()"
