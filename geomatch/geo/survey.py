"""Whether a project's photos were taken on a survey flight, from their GPS track alone.

A compact camera on a drone writes GPS but no DJI XMP: nothing in one photo says it was taken
from the air, so the project would take the ground path (upright photos, no quarter turns), and
a survey flown in alternating directions has half its photos turned 180 deg against the other
half. Its track says what the photos do not: straight legs flown back and forth, a photo every
few metres, in capture (name) order.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence

import numpy as np

# consecutive fixes closer than this (metres) are one place: a hover, or a photo taken twice
MIN_STEP_M = 0.5
# consecutive steps turning by more than this (deg) end a straight leg
LEG_TURN_DEG = 45.0
# a survey track: at least this many located photos, most steps continuing a straight leg, a
# median step of metres, and legs flown in opposite directions (a lawnmower pattern)
SURVEY_MIN_PHOTOS = 10
SURVEY_STRAIGHT_SHARE = 0.6
SURVEY_MIN_STEP_M = 2.0


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    c = float(np.dot(a, b) / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def is_survey_track(names: Sequence[str], enu: Mapping[str, np.ndarray]) -> bool:
    """Whether the photos' GPS fixes in capture order trace a survey flight: straight legs flown
    in opposite directions, steps of metres. A person walking with a camera also moves in lines,
    but rarely back and forth in parallel lines with a photo every few metres; a project that is
    not a survey can say so with ``--aerial`` (its images become ground)."""
    located = [n for n in sorted(names) if n in enu]
    xy = np.array([np.asarray(enu[n], np.float64)[:2] for n in located]).reshape(-1, 2)
    if len(xy) < SURVEY_MIN_PHOTOS:
        return False
    steps = np.diff(xy, axis=0)
    lengths = np.linalg.norm(steps, axis=1)
    steps = steps[lengths >= MIN_STEP_M]
    if (
        len(steps) < SURVEY_MIN_PHOTOS - 1
        or float(np.median(np.linalg.norm(steps, axis=1))) < SURVEY_MIN_STEP_M
    ):
        return False
    turns = [_angle(a, b) for a, b in itertools.pairwise(steps)]
    straight = float(np.mean(np.asarray(turns) <= LEG_TURN_DEG / 2))
    # legs: runs of steps within a straight line; a survey has legs whose directions are opposite
    legs: list[np.ndarray] = []
    run = [steps[0]]
    for a, b in itertools.pairwise(steps):
        if _angle(a, b) <= LEG_TURN_DEG:
            run.append(b)
        else:
            if len(run) >= 3:
                legs.append(np.sum(run, axis=0))
            run = [b]
    if len(run) >= 3:
        legs.append(np.sum(run, axis=0))
    opposite = any(_angle(a, b) >= 150.0 for i, a in enumerate(legs) for b in legs[i + 1 :])
    return straight >= SURVEY_STRAIGHT_SHARE and opposite
