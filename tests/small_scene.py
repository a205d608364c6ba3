"""The small synthetic scene (seed 1, 2 aerial + 4 ground, 640x480) that several tiers use, and
the one ``geomatch run`` of it that the tests which only read a run's result share
(tests/conftest.py's ``small_run``): matching it with the real networks takes minutes on 2 cores,
and the end-to-end, GPS and export tests each used to match it again.

The run is the GPS run of a mixed project: half the images carry a fix (``WITH_GPS``), so one
model is at once an end-to-end result (every image registered, evaluated against the ground
truth), a georeferenced one (ENU metres, images without a fix placed by the others) and one to
export. ``gps:2`` pairs all 15 here (three of six images have no fix), at the default 640 px: at
480 px the view graph's tree check drops three right aerial x ground pairs of this scene and the
model splits (3 of 6 registered, the same with keypoints jittered by 0.05 px).

The tests that read the run bound its numbers by their measured spread over 9 mappings of it:
the run itself, and its matches mapped again 8 times (``geomatch run`` on a copy resumes without
matching), 7 of them with every keypoint moved by N(0, 0.05 px) (seeds 1-7), as another
machine's arithmetic moves them; mapping alone already varies from run to run (the same matches
unmoved gave 881 points in one run, 883 in another and when mapped again). Each bound is stated
with its range where it is asserted.

``PAIRS``: the pair list the gRPC end-to-end test maps. Every ground pair, both aerial images,
and for each aerial image its two best ground partners (measured) rather than all eight aerial x
ground pairs: those are tiled (several matchings each), and half of them connect the model as
well as all of them."""

from __future__ import annotations

import shutil
from pathlib import Path

SEED = 1
WITH_GPS = {"aerial_00.png", "ground_00.png", "ground_02.png"}
GPS_NOISE_M = 0.5
RUN_OPTIONS = ["--pairs", "gps:2"]

GROUND = [f"ground_0{i}.png" for i in range(4)]
PAIRS = [(a, b) for i, a in enumerate(GROUND) for b in GROUND[i + 1 :]] + [
    ("aerial_00.png", "aerial_01.png"),
    ("aerial_00.png", "ground_00.png"),
    ("aerial_00.png", "ground_01.png"),
    ("aerial_01.png", "ground_02.png"),
    ("aerial_01.png", "ground_03.png"),
]


def copy_of_run(run: Path, dest: Path) -> Path:
    """A run folder of one's own to write into: the shared run copied (megabytes, not minutes)."""
    shutil.copytree(run, dest)
    return dest
