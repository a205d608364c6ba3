"""A synthetic survey flight's plan and its cameras, as a mapping app flies it.

Serpentine lines (each flown the other way from the one before, so the photos' headings differ by
180 deg between lines and a return line's photos are turned a half turn against the outbound
one's), a nadir camera whose image top points where the drone heads, a constant height above the
take-off point, forward and side overlap as photogrammetry plans them, and an area about square
that grows with the number of photos. A few ground photos of buildings near the middle are
optional (a phone, 1.6 m up, looking at a wall from 11-17 m).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from .camera import Camera, look_at
from .world import LOT_M, World

# the camera: a 24 mm-equivalent lens (73 deg across a 4:3 frame, a DJI Mavic or Phantom)
FOCAL_PER_WIDTH = 24.0 / 36.0
PHONE_FOCAL_PER_WIDTH = 26.0 / 36.0


@dataclass(frozen=True)
class FlightPlan:
    """The survey: ``photos`` nadir photos on ``lines`` lines, ``step`` metres apart along a line
    and ``spacing`` metres between lines, at ``altitude`` above take-off; lines run along
    ``bearing_deg`` (clockwise from north) and the next line lies to the right of it."""

    photos: int
    altitude: float
    front: float
    side: float
    width: int
    height: int
    bearing_deg: float
    lines: int
    step: float
    spacing: float

    @classmethod
    def make(
        cls,
        photos: int,
        width: int = 640,
        height: int = 480,
        altitude: float = 80.0,
        front: float = 0.78,
        side: float = 0.65,
        bearing_deg: float = 20.0,
    ) -> FlightPlan:
        """A plan over an about square area: the ground one photo sees, from its height and the
        lens, gives the step (image height along the line) and the line spacing (width across)."""
        if photos < 1:
            raise ValueError(f"a flight needs at least one photo, not {photos}")
        if not (0 <= front < 1 and 0 <= side < 1):
            raise ValueError(f"overlaps are fractions in [0, 1): front {front}, side {side}")
        f = FOCAL_PER_WIDTH * width
        step = altitude * height / f * (1 - front)
        spacing = altitude * width / f * (1 - side)
        lines = max(1, min(photos, round(math.sqrt(photos * step / spacing))))
        return cls(photos, altitude, front, side, width, height, bearing_deg, lines, step, spacing)

    @property
    def per_line(self) -> list[int]:
        base, extra = divmod(self.photos, self.lines)
        return [base + (i < extra) for i in range(self.lines)]

    @property
    def along(self) -> np.ndarray:
        b = math.radians(self.bearing_deg)
        return np.array([math.sin(b), math.cos(b), 0.0])

    @property
    def across(self) -> np.ndarray:
        b = math.radians(self.bearing_deg)
        return np.array([math.cos(b), -math.sin(b), 0.0])


# -- the flight's cameras ------------------------------------------------------------------------
def _small_rotation(rng: np.random.Generator, sigma_deg: float) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.radians(rng.normal(0, sigma_deg))
    R, _ = cv2.Rodrigues(axis * angle)
    return np.asarray(R, np.float64)


def aerial_cameras(plan: FlightPlan, seed: int) -> tuple[list[Camera], list[float]]:
    """The survey's cameras in capture order (``DJI_0001.JPG`` ...) and each photo's heading
    (degrees clockwise from north, the way the drone flies): line ``l`` starts where line
    ``l - 1`` ended, one spacing to the right, and runs back. The drone holds its line to about
    a metre (wind), crabs a couple of degrees, and its gimbal levels the camera to under a
    degree."""
    rng = np.random.default_rng([seed, 0xF1A])
    f = FOCAL_PER_WIDTH * plan.width
    K = np.array([[f, 0, plan.width / 2], [0, f, plan.height / 2], [0, 0, 1.0]])
    cams, headings = [], []
    k = 0
    for line, n in enumerate(plan.per_line):
        forward = plan.along if line % 2 == 0 else -plan.along
        for i in range(n):
            pos = i if line % 2 == 0 else n - 1 - i
            C = pos * plan.step * plan.along + line * plan.spacing * plan.across
            C = C + np.array([*rng.normal(0, 0.7, 2), plan.altitude + rng.normal(0, 0.3)])
            crab = np.radians(rng.normal(0, 2.0))
            c, s_ = math.cos(crab), math.sin(crab)
            fwd = np.array([c * forward[0] + s_ * forward[1], -s_ * forward[0] + c * forward[1], 0.0])
            R, _ = look_at(C, C - np.array([0.0, 0.0, 1.0]), up=fwd)
            R = _small_rotation(rng, 0.5) @ R
            k += 1
            cams.append(Camera(f"DJI_{k:04d}.JPG", K, R, -R @ C, plan.width, plan.height, True))
            headings.append(float(np.degrees(np.arctan2(forward[0], forward[1]))))
    return cams, headings


def ground_cameras(world: World, plan: FlightPlan, n: int, seed: int) -> list[Camera]:
    """``n`` handheld photos of the buildings nearest the middle of the area, three a building
    around one of its corners (so neighbours overlap), 1.6 m above the terrain, 11-17 m from the
    wall, looking at it a little upwards; a spot inside or next to another building is not used."""
    if n <= 0:
        return []
    rng = np.random.default_rng([seed, 0x6D])
    f = PHONE_FOCAL_PER_WIDTH * plan.width
    K = np.array([[f, 0, plan.width / 2], [0, f, plan.height / 2], [0, 0, 1.0]])
    mid = (max(plan.per_line) - 1) * plan.step / 2 * plan.along + (
        plan.lines - 1
    ) * plan.spacing / 2 * plan.across
    r = 3 * LOT_M
    near = world.buildings_near(mid[0] - r, mid[0] + r, mid[1] - r, mid[1] + r)
    near.sort(key=lambda b: float(np.linalg.norm((b.lo[:2] + b.hi[:2]) / 2 - mid[:2])))
    cams: list[Camera] = []
    for bld in near:
        centre = (bld.lo + bld.hi) / 2
        base = rng.uniform(0, 2 * np.pi)
        for view in range(3):
            if len(cams) == n:
                return cams
            ang = base + np.radians(25.0) * view
            half = (bld.hi[:2] - bld.lo[:2]) / 2
            reach = float(np.max(np.abs(half))) + rng.uniform(11.0, 17.0)
            xy = centre[:2] + reach * np.array([np.cos(ang), np.sin(ang)])
            if any(
                np.all(xy > other.lo[:2] - 2.0) and np.all(xy < other.hi[:2] + 2.0)
                for other in world.buildings_near(xy[0] - LOT_M, xy[0] + LOT_M, xy[1] - LOT_M, xy[1] + LOT_M)
            ):
                continue
            ground = float(world.terrain.height(xy[:1], xy[1:])[0])
            C = np.array([*xy, ground + 1.6])
            target = np.array([*centre[:2], C[2] + rng.uniform(1.0, 3.0)])
            R, _ = look_at(C, target)
            cams.append(Camera(f"IMG_{len(cams) + 1:04d}.JPG", K, R, -R @ C, plan.width, plan.height, False))
    return cams
