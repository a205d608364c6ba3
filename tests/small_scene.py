"""The small synthetic scene (seed 1, 2 aerial + 4 ground, 640x480) that several tiers use, and
the one ``geomatch run`` of it that the tests which only read a run's result share
(tests/conftest.py's ``small_run``): matching it with the real networks takes minutes on 2 cores,
and the end-to-end, GPS and export tests each used to match it again.

The run is the GPS run of a mixed project: half the images carry a fix (``WITH_GPS``), so one
model is at once an end-to-end result (every image registered, evaluated against the ground
truth), a georeferenced one (ENU metres, images without a fix placed by the others) and one to
export. It matches ``PAIRS`` (a pair file, ``write_pairs``) at the default 640 px: every ground
pair, both aerial images, and for each aerial image its two best ground partners rather than all
eight aerial x ground pairs. Those are tiled (several matchings each, nine tenths of the matching
time), and half of them connect the model as well as all of them. The GPS plans themselves are
tested on their own (tests/test_gps.py).

The tests that read the run bound its numbers by their measured spread over several mappings of
it (``geomatch run`` on a copy resumes without matching, and mapping alone varies from run to run:
the same matches gave 881 points in one run, 883 in another). Each bound is stated with its range
where it is asserted.

``PAIRS`` is also the pair list the service's end-to-end tests match (REST and gRPC).
"""

from __future__ import annotations

import shutil
from pathlib import Path

SEED = 1
WITH_GPS = {"aerial_00.png", "ground_00.png", "ground_02.png"}
GPS_NOISE_M = 0.5

GROUND = [f"ground_0{i}.png" for i in range(4)]
PAIRS = [(a, b) for i, a in enumerate(GROUND) for b in GROUND[i + 1 :]] + [
    ("aerial_00.png", "aerial_01.png"),
    ("aerial_00.png", "ground_00.png"),
    ("aerial_00.png", "ground_01.png"),
    ("aerial_01.png", "ground_02.png"),
    ("aerial_01.png", "ground_03.png"),
]


def write_pairs(scene: Path) -> Path:
    """:data:`PAIRS` as a pair file in ``scene``, the plan the session's run matches."""
    path = scene / "pairs.txt"
    path.write_text("".join(f"{a} {b}\n" for a, b in PAIRS))
    return path


def run_options(scene: Path) -> list[str]:
    """The options of the session's run of ``scene`` (and of the runs that resume it)."""
    return ["--aerial-list", str(scene / "aerial.txt"), "--pairs", str(scene / "pairs.txt")]


def copy_of_run(run: Path, dest: Path) -> Path:
    """A run folder of one's own to write into: the shared run copied (megabytes, not minutes)."""
    shutil.copytree(run, dest)
    return dest
