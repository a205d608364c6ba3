"""Synthetic indoor rooms with ground truth: the wide-baseline pairs where held-out data says we fail.

Real indoor scans (ScanNet-like, 640x480) are hard for other reasons than the outdoor scenes of
:mod:`geomatch.synth.aerial`: most of the image is plain painted wall, floor and ceiling with nothing to
detect, what texture there is often repeats (floor tiles, shelves, cupboard doors, the same poster
twice), the camera is close to the geometry, so a 20-70 degree rotation changes the view a lot.
A room (:mod:`geomatch.synth.room`, its textures in :mod:`geomatch.synth.roomtex`) is the inside of
a box (walls, floor, ceiling) holding furniture boxes on the floor, lit by ceiling lights and
rendered by ray casting with exact depth; this module chooses and scores its views.

Pairs are chosen as the indoor benchmarks choose them: relative rotation 20-70 degrees and a
covisibility of at least 10 %, computed from depth (see :func:`covisibility`). Public API:
:func:`indoor_pairs`, :func:`no_overlap_pairs`, :func:`gt_matches`, :func:`write_room`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .camera import Camera
from .groundtruth import write_gt
from .room import Room
from .sensors import save_png

MIN_ROTATION_DEG, MAX_ROTATION_DEG, MIN_COVISIBILITY = 20.0, 70.0, 0.10
PAIRS_PER_ROOM = 5


# -- pairs and ground truth ---------------------------------------------------------------------------
def relative_pose(cam0: Camera, cam1: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of cam1_from_cam0."""
    R = cam1.R @ cam0.R.T
    return R, cam1.t - R @ cam0.t


def rotation_angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def warp(
    points0: np.ndarray,
    depth0: np.ndarray,
    K0: np.ndarray,
    K1: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    depth1: np.ndarray,
    rel_tol: float = 0.03,
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of image 0 (centres at integers) carried into image 1 through depth0 and (R, t).

    Valid where depth0 is known at the nearest pixel, the point lies in front of camera 1, inside
    its image, and camera 1's own depth at the nearest pixel agrees within ``rel_tol`` (not occluded).
    """
    points0 = np.asarray(points0, np.float64).reshape(-1, 2)
    h0, w0 = depth0.shape
    h1, w1 = depth1.shape
    u = np.clip(np.round(points0[:, 0]).astype(int), 0, w0 - 1)
    v = np.clip(np.round(points0[:, 1]).astype(int), 0, h0 - 1)
    d = depth0[v, u]
    ok = np.isfinite(d) & (d > 0)
    pix = np.stack([points0[:, 0] + 0.5, points0[:, 1] + 0.5, np.ones(len(points0))], 1)
    X = (pix @ np.linalg.inv(K0).T) * np.where(ok, d, 1.0)[:, None] @ R.T + t
    z = X[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (X @ K1.T)[:, :2] / z[:, None] - 0.5
    ub, vb = np.round(uv[:, 0]), np.round(uv[:, 1])
    ok &= (z > 1e-6) & (ub >= 0) & (ub < w1) & (vb >= 0) & (vb < h1)
    ubi = np.clip(np.nan_to_num(ub), 0, w1 - 1).astype(int)
    vbi = np.clip(np.nan_to_num(vb), 0, h1 - 1).astype(int)
    ok &= np.abs(depth1[vbi, ubi] - z) < rel_tol * np.abs(z)
    return uv, ok


def covisibility(
    depth0: np.ndarray,
    depth1: np.ndarray,
    K0: np.ndarray,
    K1: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    stride: int = 4,
) -> float:
    """Fraction of image 0's pixels (on a ``stride`` grid) that image 1 sees unoccluded, and vice versa;
    the smaller of the two, so a pair whose small view sits inside a wide one still counts as hard."""
    fractions = []
    for da, db, Ka, Kb, Ra, ta in ((depth0, depth1, K0, K1, R, t), (depth1, depth0, K1, K0, R.T, -R.T @ t)):
        v, u = np.mgrid[0 : da.shape[0] : stride, 0 : da.shape[1] : stride]
        _, ok = warp(np.stack([u.ravel(), v.ravel()], 1), da, Ka, Kb, Ra, ta, db)
        fractions.append(float(ok.mean()))
    return min(fractions)


@dataclass(frozen=True)
class IndoorPair:
    """Two views of one room; (R, t) is cam1_from_cam0, depths are camera z per pixel."""

    name: str
    image0: np.ndarray
    image1: np.ndarray
    K0: np.ndarray
    K1: np.ndarray
    R: np.ndarray
    t: np.ndarray
    depth0: np.ndarray
    depth1: np.ndarray
    covisibility: float
    rotation_deg: float


def gt_matches(pair: IndoorPair, points0: np.ndarray, rel_tol: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
    """Where image 0's pixels land in image 1 (N, 2) and whether that is a true, unoccluded match."""
    return warp(points0, pair.depth0, pair.K0, pair.K1, pair.R, pair.t, pair.depth1, rel_tol)


def _small(cam: Camera, width: int = 80) -> Camera:
    s = width / cam.width
    return Camera(cam.name, np.diag([s, s, 1.0]) @ cam.K, cam.R, cam.t, width, round(cam.height * s), False)


def _candidates(
    room: Room, rng: np.random.Generator, n: int, width: int, height: int
) -> tuple[list[Camera], list[Camera], list[np.ndarray]]:
    """``n`` cameras with their 80-px depth renders; views closer than 1.3 m (median) to what they
    look at are dropped: a scanner operator does not film a wall from arm's length."""
    cams: list[Camera] = []
    small: list[Camera] = []
    depths: list[np.ndarray] = []
    while len(cams) < n:
        cam = room.camera(rng, width, height, f"view_{len(cams):02d}.png")
        sc = _small(cam)
        d = room.depth(sc)
        if np.median(d) < 1.3:
            continue
        cams.append(cam)
        small.append(sc)
        depths.append(d)
    return cams, small, depths


def _pair_stats(small: list[Camera], depths: list[np.ndarray], i: int, j: int) -> tuple[float, float, float]:
    R, t = relative_pose(small[i], small[j])
    cov = covisibility(depths[i], depths[j], small[i].K, small[j].K, R, t, stride=1)
    return rotation_angle_deg(R), cov, float(np.linalg.norm(small[i].centre - small[j].centre))


def _make_pair(room: Room, cam0: Camera, cam1: Camera, name: str, supersample: int, noise: int) -> IndoorPair:
    img0, d0 = room.render(cam0, supersample, noise_seed=noise)
    img1, d1 = room.render(cam1, supersample, noise_seed=noise + 1)
    R, t = relative_pose(cam0, cam1)
    cov = covisibility(d0, d1, cam0.K, cam1.K, R, t)
    return IndoorPair(name, img0, img1, cam0.K, cam1.K, R, t, d0, d1, cov, rotation_angle_deg(R))


def _solvable(pair: IndoorPair) -> bool:
    """Exact correspondences recover the pose under the scoring protocol: a pair that is nearly one
    plane can fool the essential-matrix RANSAC even with perfect matches, and would measure luck,
    not matching."""
    from ..eval.pose import relative_pose_error

    h, w = pair.depth0.shape
    for stride in (2, 3, 4, 5, 7):  # several samplings: RANSAC on a near-degenerate pair is erratic
        v, u = np.mgrid[0:h:stride, 0:w:stride]
        pts0 = np.stack([u.ravel(), v.ravel()], 1).astype(np.float64)
        pts1, ok = gt_matches(pair, pts0)
        if max(relative_pose_error(pts0[ok], pts1[ok], pair.K0, pair.K1, pair.R, pair.t)) >= 1.0:
            return False
    return True


def _rooms(seed: int, salt: int) -> Iterator[tuple[int, Room, np.random.Generator]]:
    k = 0
    while True:
        ss = np.random.SeedSequence([seed, salt, k])
        yield k, Room(ss), np.random.default_rng(ss.spawn(1)[0])
        k += 1


@dataclass(frozen=True)
class _Draw:
    """How one kind of pair is drawn: its stream of rooms (``salt``), the random views per room,
    the name tag, the test on the small depth renders and the test on the full-size pair."""

    salt: int
    n_candidates: int
    tag: str
    candidate: Callable[[float, float, float], bool]
    keep: Callable[[IndoorPair], bool]


def _choose_pairs(
    seed: int, n_pairs: int, draw: _Draw, width: int, height: int, supersample: int
) -> list[IndoorPair]:
    """Room after room, up to :data:`PAIRS_PER_ROOM` pairs of ``draw.n_candidates`` random views:
    the view pairs whose (rotation, covisibility, baseline) on the small depth renders pass
    ``draw.candidate``, in random order, no view in two pairs, each rendered full size and taken if
    it passes ``draw.keep``. Deterministic per (seed, salt)."""
    out: list[IndoorPair] = []
    for k, room, rng in _rooms(seed, draw.salt):
        cams, small, depths = _candidates(room, rng, draw.n_candidates, width, height)
        options = [
            (i, j)
            for i in range(len(cams))
            for j in range(i + 1, len(cams))
            if draw.candidate(*_pair_stats(small, depths, i, j))
        ]
        used: set[int] = set()
        taken = 0
        for idx in rng.permutation(len(options)):
            i, j = options[idx]
            if i in used or j in used or taken == PAIRS_PER_ROOM or len(out) == n_pairs:
                continue
            name = f"s{seed}_{draw.tag}r{k}_{i:02d}_{j:02d}"
            pair = _make_pair(room, cams[i], cams[j], name, supersample, 1000 * k + 2 * taken)
            if not draw.keep(pair):
                continue
            used |= {i, j}
            out.append(pair)
            taken += 1
        if len(out) == n_pairs:
            return out
    raise AssertionError("unreachable")


def indoor_pairs(
    seed: int, n_pairs: int, width: int = 640, height: int = 480, supersample: int = 2
) -> list[IndoorPair]:
    """Wide-baseline pairs (rotation 20-70 degrees, covisibility >= 10 %), deterministic per seed.

    Every :data:`PAIRS_PER_ROOM` pairs come from a new room, so a split sees several layouts. Pairs
    are chosen on 80-px-wide depth renders and confirmed on the full-size ones.
    """

    def candidate(rot: float, cov: float, base: float) -> bool:
        return (
            MIN_ROTATION_DEG + 1 <= rot <= MAX_ROTATION_DEG - 1
            and cov >= MIN_COVISIBILITY + 0.03
            and base > 0.3
        )

    def keep(pair: IndoorPair) -> bool:
        return (
            pair.covisibility >= MIN_COVISIBILITY
            and MIN_ROTATION_DEG <= pair.rotation_deg <= MAX_ROTATION_DEG
            and _solvable(pair)
        )

    return _choose_pairs(seed, n_pairs, _Draw(0, 48, "", candidate, keep), width, height, supersample)


def no_overlap_pairs(
    seed: int, n_pairs: int, width: int = 640, height: int = 480, supersample: int = 2
) -> list[IndoorPair]:
    """Two views of the same room that share no surface point (covisibility exactly 0 in both
    directions at full size), so every match is false: the same paint, tiles, shelves and repeated
    poster can still be in both. Deterministic per seed."""

    def candidate(rot: float, cov: float, base: float) -> bool:
        return cov == 0.0

    def keep(pair: IndoorPair) -> bool:
        return not covisibility(pair.depth0, pair.depth1, pair.K0, pair.K1, pair.R, pair.t, stride=2) > 0

    draw = _Draw(1, 32, "none_", candidate, keep)
    return _choose_pairs(seed, n_pairs, draw, width, height, supersample)


def write_room(
    out: str | Path, n_views: int = 12, seed: int = 0, width: int = 640, height: int = 480
) -> list[Camera]:
    """Render ``n_views`` overlapping views of one room into ``out``: images/ (PNG), gt/ (COLMAP
    text model) and depth/ (float32 .npy, camera z). Each view after the first overlaps (>= 10 %)
    an earlier one, so the set can be reconstructed."""
    out = Path(out)
    for sub in ("images", "depth"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    ss = np.random.SeedSequence([seed, 2, 0])
    room, rng = Room(ss), np.random.default_rng(ss.spawn(1)[0])
    cams, small, depths = _candidates(room, rng, max(24, 3 * n_views), width, height)
    chosen = [0]
    for j in rng.permutation(np.arange(1, len(cams))):
        if len(chosen) == n_views:
            break
        if any(_pair_stats(small, depths, i, int(j))[1] >= MIN_COVISIBILITY for i in chosen):
            chosen.append(int(j))
    views = [
        Camera(f"view_{n:02d}.png", cams[i].K, cams[i].R, cams[i].t, width, height, False)
        for n, i in enumerate(chosen)
    ]
    for n, cam in enumerate(views):
        img, depth = room.render(cam, noise_seed=n)
        save_png(out / "images" / cam.name, img, cam)
        np.save(out / "depth" / f"{Path(cam.name).stem}.npy", depth.astype(np.float32))
    write_gt(views, out / "gt")
    return views
