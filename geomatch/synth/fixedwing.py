"""A fixed-wing survey's plan and its cameras: a racetrack over one field, flown again and again.

A multicopter's survey (synth.flightplan) hovers its camera level over a serpentine; a small
fixed-wing does not, and its photos differ in ways a matcher and a mapper feel:

- **Legs both ways, in wind.** Outbound legs run along ``bearing_deg`` (north-east by default), the
  return legs the other way, one ``return_gap_m`` to the right (the turns need room), and the
  photos of a return leg are turned a half turn against the outbound ones. The camera fires on a
  timer, so the wind that slows the outbound legs stretches the return legs' photo spacing by
  ``return_ratio`` (a wind from the outbound direction: ``(v + w) / (v - w)``), and a crosswind
  crabs the airframe (and the camera with it).
- **Repeated passes.** The field is circled ``lines`` times a pass, each loop's outbound line one
  ``spacing_m`` to the right of the last; every other pass circles the other way (left turns)
  half a spacing over, so its outbound legs fly over the return strip and its return legs over
  the outbound strip (FixedWingPlan.circuit): a patch of ground is seen from many loops, both
  ways. Between passes the autopilot loiters round with the camera paused.
- **Banked turns, photographed.** The turns at the line ends are a quarter arc, a straight
  crossing and a quarter arc of ``turn_radius_m``; the aircraft banks (right or left with the
  circuit) to the roll its ground speed needs (``atan(v^2 / (g r))``, 10-30 deg at the
  defaults), rolling in and out over RAMP_M of path, and the camera, fixed to the airframe, keeps
  firing: turn photos are oblique and yawed.
- **An airframe, not a gimbal**: roll, pitch and heading scatter by a degree or two on the legs,
  the height wanders by metres (``ALTITUDE_WANDER_M``).
- **Missing photos**: each trigger fails with probability ``missing``; the file names are the
  camera's counter (``IMG_0001.JPG`` ...), which counts written photos only, so a gap in the
  flight leaves no gap in the names.

Positions are ENU metres around the take-off point (synth.sensors.GPS_ORIGIN); the first
outbound line starts there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .camera import Camera
from .flightplan import FOCAL_PER_WIDTH

G = 9.81
RAMP_M = 25.0  # path over which the aircraft rolls into (and out of) a turn
ALTITUDE_WANDER_M = 1.5  # the height's scatter about the planned altitude (slowly varying)
ATTITUDE_NOISE_DEG = 1.5  # roll, pitch and heading scatter of the airframe on a leg
PATH_STEP_M = 0.5  # the path's sampling, for timing the triggers
LEG, EAST_TURN, RETURN, WEST_TURN = "outbound", "turn at the far end", "return", "turn at the start"
TRANSIT = "between passes"  # not photographed
PARTS = (LEG, EAST_TURN, RETURN, WEST_TURN)


@dataclass(frozen=True)
class FixedWingPlan:
    """The flight (module docstring). ``step_m``: photo spacing on outbound legs; ``leg_m``: a
    line's length; ``spacing_m``: between neighbouring outbound lines."""

    photos: int
    width: int = 640
    height: int = 480
    altitude: float = 100.0
    bearing_deg: float = 40.0
    leg_m: float = 450.0
    step_m: float = 30.0
    return_ratio: float = 1.75
    side: float = 0.65
    lines: int = 2
    turn_radius_m: float = 60.0
    airspeed: float = 14.0
    crosswind: float = 0.8
    missing: float = 0.03
    spacing_m: float = field(init=False)
    return_gap_m: float = field(init=False)

    def __post_init__(self) -> None:
        if self.photos < 1:
            raise ValueError(f"a flight needs at least one photo, not {self.photos}")
        if not 1.0 <= self.return_ratio < 3.0:
            raise ValueError(
                f"return_ratio (return spacing over outbound) must lie in [1, 3): {self.return_ratio}"
            )
        if not 0.0 <= self.missing < 0.5:
            raise ValueError(f"missing is a probability under 0.5: {self.missing}")
        footprint = self.altitude * self.width / (FOCAL_PER_WIDTH * self.width)
        spacing = footprint * (1 - self.side)
        # the return line lies a whole number of spacings to the right, far enough that both
        # turns fit their two quarter arcs (the start turn crosses one spacing less)
        gap = spacing * math.ceil((2 * self.turn_radius_m + spacing) / spacing)
        object.__setattr__(self, "spacing_m", spacing)
        object.__setattr__(self, "return_gap_m", gap)

    @property
    def along(self) -> np.ndarray:
        b = math.radians(self.bearing_deg)
        return np.array([math.sin(b), math.cos(b)])

    @property
    def across(self) -> np.ndarray:
        b = math.radians(self.bearing_deg)
        return np.array([math.cos(b), -math.sin(b)])

    @property
    def wind(self) -> np.ndarray:
        """Wind velocity (m/s, east and north): from the outbound direction at the strength that
        gives ``return_ratio``, and a crosswind from the left."""
        w = self.airspeed * (self.return_ratio - 1) / (self.return_ratio + 1)
        return -w * self.along + self.crosswind * self.across

    def circuit(self, loop: int) -> tuple[float, int]:
        """Loop ``loop``'s outbound line (metres right of the first) and its hand: +1 turning
        right (its return line one gap to the right), -1 turning left. Even passes turn right;
        odd passes circle the other way, half a spacing over, so their outbound legs are flown
        over the even passes' return strip and their return legs over the outbound strip: every
        patch of the field is photographed both ways."""
        pass_, k = divmod(loop, self.lines)
        shift = (pass_ // 2 % 2) * self.spacing_m / 4  # later passes a little off the first ones
        if pass_ % 2 == 0:
            return k * self.spacing_m + shift, 1
        return self.return_gap_m + (k + 0.5) * self.spacing_m + shift, -1


@dataclass(frozen=True)
class Shot:
    """One trigger of the camera: where and how the airframe was, and which part of the flight."""

    index: int  # the trigger's number, counting failed ones
    name: str | None  # the written file, None when the trigger failed
    part: str  # one of PARTS
    loop: int
    position: np.ndarray  # (3,) ENU metres
    heading_deg: float  # the nose, clockwise from north
    track_deg: float  # the ground track, clockwise from north
    roll_deg: float  # right wing down positive
    pitch_deg: float
    ground_speed: float


def _path(
    plan: FixedWingPlan, loops: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str], np.ndarray]:
    """The racetracks sampled every PATH_STEP_M: points (N, 2) in the field's (along, right)
    frame, unit track directions in that frame, signed curvature (right turns positive), the part
    of the flight and the loop of each sample."""
    pts: list[np.ndarray] = []
    dirs: list[np.ndarray] = []
    curv: list[np.ndarray] = []
    parts: list[str] = []
    loop_of: list[np.ndarray] = []
    r = plan.turn_radius_m

    def straight(p0: np.ndarray, p1: np.ndarray, part: str, loop: int) -> None:
        n = max(int(np.linalg.norm(p1 - p0) / PATH_STEP_M), 1)
        t = np.arange(n)[:, None] / n
        pts.append(p0 + t * (p1 - p0))
        d = (p1 - p0) / max(float(np.linalg.norm(p1 - p0)), 1e-9)
        dirs.append(np.repeat(d[None], n, 0))
        curv.append(np.zeros(n))
        parts.extend([part] * n)
        loop_of.append(np.full(n, loop))

    def quarter(
        p0: np.ndarray, d0: np.ndarray, hand: int, part: str, loop: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """A quarter turn from p0 heading d0, to the right (``hand`` 1) or left (-1); returns its
        end and direction (in this frame, x along and y right, the right of (d_x, d_y) is
        (-d_y, d_x))."""
        side = hand * np.array([-d0[1], d0[0]])
        centre = p0 + r * side
        n = max(int(math.pi / 2 * r / PATH_STEP_M), 1)
        a = np.arange(n)[:, None] / n * (math.pi / 2)
        pts.append(centre - r * side * np.cos(a) + r * d0 * np.sin(a))
        dirs.append(d0 * np.cos(a) + side * np.sin(a))
        curv.append(np.full(n, hand / r))
        parts.extend([part] * n)
        loop_of.append(np.full(n, loop))
        return centre + r * d0, side

    along = np.array([1.0, 0.0])
    for loop in range(loops):
        a, hand = plan.circuit(loop)
        b = a + hand * plan.return_gap_m
        straight(np.array([0.0, a]), np.array([plan.leg_m, a]), LEG, loop)
        p, d = quarter(np.array([plan.leg_m, a]), along, hand, EAST_TURN, loop)
        straight(p, np.array([plan.leg_m + r, b - hand * r]), EAST_TURN, loop)
        quarter(np.array([plan.leg_m + r, b - hand * r]), d, hand, EAST_TURN, loop)
        straight(np.array([plan.leg_m, b]), np.array([0.0, b]), RETURN, loop)
        nxt, next_hand = plan.circuit(loop + 1)
        if next_hand != hand or (b - nxt) * hand < 2 * r:
            # a new pass: the autopilot loiters round to the next line with the camera paused
            straight(np.array([0.0, b]), np.array([0.0, nxt]), TRANSIT, loop)
            continue
        # the crossing to the next line, one spacing on: the gap leaves room for both arcs
        p, d = quarter(np.array([0.0, b]), -along, hand, WEST_TURN, loop)
        straight(p, np.array([-r, nxt + hand * r]), WEST_TURN, loop)
        quarter(np.array([-r, nxt + hand * r]), d, hand, WEST_TURN, loop)
    return (
        np.concatenate(pts),
        np.concatenate(dirs),
        np.concatenate(curv),
        parts,
        np.concatenate(loop_of),
    )


def _ground_speed(track: np.ndarray, wind: np.ndarray, airspeed: float) -> np.ndarray:
    """Ground speed along unit ``track`` directions (N, 2) at ``airspeed`` in ``wind`` (2,)."""
    tw = track @ wind
    return np.asarray(tw + np.sqrt(airspeed**2 - (wind @ wind - tw**2)), np.float64)


def shots(plan: FixedWingPlan, seed: int) -> list[Shot]:
    """The camera's triggers in order until ``plan.photos`` photos are written (module
    docstring): the camera fires every ``step_m`` / (outbound ground speed) seconds."""
    rng = np.random.default_rng([seed, 0xF1C3])
    basis = np.stack([plan.along, plan.across])  # field frame (along, right) -> east, north
    wind = basis @ plan.wind  # the wind in the field frame
    period = plan.step_m / float(_ground_speed(np.array([[1.0, 0.0]]), wind, plan.airspeed)[0])
    loop_len = 2 * plan.leg_m + 2 * math.pi * plan.turn_radius_m + plan.return_gap_m
    loops = max(1, math.ceil(plan.photos * plan.step_m / loop_len * 0.7))
    while True:
        pts, track, curv, parts, loop_of = _path(plan, loops)
        speed = _ground_speed(track, wind, plan.airspeed)
        seg = np.linalg.norm(np.diff(pts, axis=0, append=pts[-1:] + track[-1:] * PATH_STEP_M), axis=1)
        time = np.concatenate([[0.0], np.cumsum(seg / speed)[:-1]])
        n_ramp = max(int(RAMP_M / PATH_STEP_M), 1)
        roll = np.degrees(np.arctan(speed**2 * curv / G))
        roll = np.convolve(roll, np.ones(n_ramp) / n_ramp, mode="same")
        needed = plan.photos / (1 - plan.missing) * 1.3 + 5
        if time[-1] / period >= needed:
            break
        loops *= 2
    out: list[Shot] = []
    written = 0
    height = 0.0
    k = 0
    start = rng.uniform(0.0, period)
    while written < plan.photos:
        t = start + k * period + rng.normal(0.0, 0.01 * period)
        i = int(np.clip(np.searchsorted(time, t), 1, len(time) - 1))
        f = float(np.clip((t - time[i - 1]) / max(time[i] - time[i - 1], 1e-9), 0.0, 1.0))
        p = pts[i - 1] + f * (pts[i] - pts[i - 1])
        air = speed[i] * track[i] - wind  # where the nose points: into the crosswind
        height = 0.8 * height + rng.normal(0.0, ALTITUDE_WANDER_M * 0.6)
        xy = basis.T @ p
        east_north = basis.T @ air
        track_w = basis.T @ track[i]
        k += 1
        if parts[i] == TRANSIT:
            continue
        ok = rng.random() >= plan.missing
        name = f"IMG_{written + 1:04d}.JPG" if ok else None
        written += ok
        out.append(
            Shot(
                len(out),
                name,
                parts[i],
                int(loop_of[i]),
                np.array([xy[0], xy[1], plan.altitude + height]),
                float(
                    np.degrees(np.arctan2(east_north[0], east_north[1])) + rng.normal(0, ATTITUDE_NOISE_DEG)
                ),
                float(np.degrees(np.arctan2(track_w[0], track_w[1]))),
                float(roll[i] + rng.normal(0.0, ATTITUDE_NOISE_DEG)),
                float(rng.normal(0.0, ATTITUDE_NOISE_DEG)),
                float(speed[i]),
            )
        )
    return out


def airframe_rotation(heading_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """cam_from_world of a camera fixed to the airframe looking down, the image top towards the
    nose (synth.camera's convention), after pitch (nose up positive) and roll (right wing down
    positive): a right bank turns the view to the left, out of the turn."""
    psi, theta, phi = (math.radians(a) for a in (heading_deg, pitch_deg, roll_deg))
    fwd = np.array([math.sin(psi), math.cos(psi), 0.0])
    right = np.array([math.cos(psi), -math.sin(psi), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    fwd, down = fwd * math.cos(theta) - down * math.sin(theta), down * math.cos(theta) + fwd * math.sin(theta)
    right, down = right * math.cos(phi) + down * math.sin(phi), down * math.cos(phi) - right * math.sin(phi)
    return np.stack([right, -fwd, down])


def fixedwing_cameras(plan: FixedWingPlan, seed: int) -> tuple[list[Camera], list[Shot]]:
    """The written photos' cameras in capture order, and every trigger (failed ones too)."""
    f = FOCAL_PER_WIDTH * plan.width
    K = np.array([[f, 0, plan.width / 2], [0, f, plan.height / 2], [0, 0, 1.0]])
    fired = shots(plan, seed)
    cams = []
    for s in fired:
        if s.name is None:
            continue
        R = airframe_rotation(s.heading_deg, s.pitch_deg, s.roll_deg)
        cams.append(Camera(s.name, K, R, -R @ s.position, plan.width, plan.height, True))
    return cams, fired
