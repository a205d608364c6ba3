"""The world the survey flights (synth.flight) photograph, and its renders.

East-North-Up metres; the take-off point on the ground is the origin, which is synth.sensors'
GPS_ORIGIN. Rolling terrain (a sum of long sinusoids: a flat ground would make every fundamental
matrix degenerate) carries box buildings on some lots; the ground's texture is synth.groundtex's
tiles, and every building face has a photo patch of its own. Nothing is held for the whole area:
a lot's building and its faces, like a tile, are made from their own seeded generator when a view
needs them and kept in a cache bounded in bytes, so memory does not grow with the flight.

Rendering, at 2x and area-downsampled: nadir views meet the terrain by fixed-point iteration
along each ray (a few steps on gentle slopes), the buildings in view by a slab test on the rays
of their projected box, and sample the tiles in view; ground photos march their near-horizontal
rays instead, and see nothing beyond GROUND_VIEW_M (sky colour).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..memory import ByteLRU
from .camera import Camera
from .groundtex import GroundTiles, seed_key
from .texture import SKY, sample_texture, unique_texture

LOT_M = 48.0  # one building at most per lot
BUILDING_SHARE = 0.6  # of the lots
FACE_TEXELS = 192  # a building face's texture across its longer side
GROUND_VIEW_M = 150.0  # a ground photo's rays that meet nothing nearer see sky
CACHE_MB = 96.0  # tiles and buildings together


@dataclass(frozen=True)
class Building:
    lo: np.ndarray  # (3,) min corner, metres
    hi: np.ndarray  # (3,) max corner
    lot: tuple[int, int]


class Terrain:
    """Rolling ground: a sum of sinusoids of 150-600 m wavelength, 0 m at the take-off point,
    slopes under 15 % (the fixed-point ray casting converges on them in a few steps)."""

    def __init__(self, seed: int, waves: int = 6) -> None:
        rng = np.random.default_rng([seed, 0x7E4])
        ang = rng.uniform(0, 2 * np.pi, waves)
        wavelength = np.exp(rng.uniform(np.log(150.0), np.log(600.0), waves))
        self.k = (2 * np.pi / wavelength)[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)  # (W, 2)
        self.amp = rng.uniform(0.5, 1.0, waves) * wavelength / 100.0  # metres: longer waves higher
        self.phase = rng.uniform(0, 2 * np.pi, waves)
        self.offset = 0.0
        self.offset = float(self.height(np.zeros(1), np.zeros(1))[0])

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        h = np.full(np.shape(x), -self.offset)
        for (kx, ky), a, p in zip(self.k, self.amp, self.phase, strict=True):
            h += a * np.sin(kx * x + ky * y + p)
        return h


class World:
    """The terrain, its ground texture and its buildings, made on demand (module docstring)."""

    def __init__(
        self,
        seed: int,
        texel_m: float,
        cache_mb: float = CACHE_MB,
        ground: GroundTiles | None = None,
        building_share: float = BUILDING_SHARE,
    ) -> None:
        """``ground``: another ground (synth.farmtex's farmland), else groundtex's photo tiles;
        ``building_share``: of the lots (a farm has few buildings, a town many)."""
        self.seed = seed
        self.texel = texel_m
        self.terrain = Terrain(seed)
        self.ground = ground or GroundTiles(seed, texel_m, crops_mb=cache_mb * 0.3, tiles_mb=cache_mb * 0.4)
        self.building_share = building_share
        self._faces: ByteLRU[tuple[int, int], list[np.ndarray]] = ByteLRU(
            cache_mb * 0.3, lambda v: sum(int(t.nbytes) for t in v)
        )

    # -- buildings -----------------------------------------------------------------------------
    def building(self, a: int, b: int) -> Building | None:
        """Lot (a, b)'s building, or None: 8-20 m a side, 4-14 m high, set into the terrain at
        its lowest corner, at least 3 m inside its lot (two buildings stand 6 m apart or more)."""
        rng = np.random.default_rng([self.seed, 0xB1D, *seed_key(a, b)])
        if rng.random() >= self.building_share:
            return None
        size = rng.uniform(8.0, 20.0, 2)
        free = LOT_M - size - 6.0
        lo_xy = np.array([a * LOT_M, b * LOT_M]) + 3.0 + rng.uniform(0, 1, 2) * free
        hi_xy = lo_xy + size
        xs = np.array([lo_xy[0], hi_xy[0], lo_xy[0], hi_xy[0], (lo_xy[0] + hi_xy[0]) / 2])
        ys = np.array([lo_xy[1], lo_xy[1], hi_xy[1], hi_xy[1], (lo_xy[1] + hi_xy[1]) / 2])
        z0 = float(self.terrain.height(xs, ys).min()) - 0.3
        height = rng.uniform(4.0, 14.0)
        return Building(np.array([*lo_xy, z0]), np.array([*hi_xy, z0 + 0.3 + height]), (a, b))

    def buildings_near(self, x0: float, x1: float, y0: float, y1: float) -> list[Building]:
        out = []
        for b in range(math.floor(y0 / LOT_M), math.floor(y1 / LOT_M) + 1):
            for a in range(math.floor(x0 / LOT_M), math.floor(x1 / LOT_M) + 1):
                bld = self.building(a, b)
                if bld is not None:
                    out.append(bld)
        return out

    def faces(self, bld: Building) -> list[np.ndarray]:
        """The building's face textures, -x, +x, -y, +y, -z, +z (float32), each its own."""
        hit = self._faces.get(bld.lot)
        if hit is not None:
            return hit
        rng = np.random.default_rng([self.seed, 0xFACE, *seed_key(*bld.lot)])
        out = []
        for _ in range(6):
            src = self.ground.photos[int(rng.integers(len(self.ground.photos)))]
            h, w = src.shape[:2]
            cy, cx = int(rng.integers(0, h // 2)), int(rng.integers(0, w // 2))
            patch = src[cy : cy + h // 2, cx : cx + w // 2]
            out.append(unique_texture(patch, FACE_TEXELS, rng).astype(np.float32))
        self._faces.put(bld.lot, out)
        return out

    # -- rendering ------------------------------------------------------------------------------
    def render(self, cam: Camera, supersample: int = 2) -> tuple[np.ndarray, np.ndarray]:
        """The camera's RGB uint8 view (module docstring) and per-pixel depth (z in the camera,
        inf for sky)."""
        s = supersample
        w, h = cam.width * s, cam.height * s
        dirs = _rays(cam, s, np.arange(w), np.arange(h))  # world directions, z_cam = 1
        o = cam.centre
        steep = dirs[:, 2].max() < -0.2  # every ray downwards: a nadir view
        t = self._terrain_nadir(cam, s, w, h) if steep else self._terrain_march(o, dirs)
        colour = np.tile(SKY.astype(np.float32), (len(dirs), 1))
        hit = np.isfinite(t)
        P = o + t[hit, None] * dirs[hit]
        colour[hit] = self.ground.sample(P[:, 0], P[:, 1])
        if hit.any():
            (x0, y0), (x1, y1) = P[:, :2].min(0) - 20.0, P[:, :2].max(0) + 20.0
        else:
            x0, y0, x1, y1 = o[0] - 20, o[1] - 20, o[0] + 20, o[1] + 20
        t_best = np.where(hit, t, np.inf)
        for bld in self.buildings_near(x0, x1, y0, y1):
            rows = _box_rays(cam, bld, s, w, h)
            if rows is not None:
                self._hit_box(bld, o, dirs, rows, t_best, colour)
        img: np.ndarray = colour.reshape(h, w, 3)
        depth = t_best.reshape(h, w)  # the ray parameter with z_cam = 1 is the depth
        if s > 1:
            img = cv2.resize(img, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
            depth = depth[s // 2 :: s, s // 2 :: s]
        return np.clip(img + 0.5, 0, 255).astype(np.uint8), depth

    def _terrain_nadir(
        self, cam: Camera, s: int, w: int, h: int, steps: int = 8, grid: int = 8
    ) -> np.ndarray:
        """Ray parameters where the downward rays meet the terrain: t = (o_z - h(o + t d)) / -d_z,
        iterated from the take-off height (each step shrinks the error by the slope times the
        ray's tilt), on every ``grid``-th ray and interpolated between (the terrain is smooth
        over metres, where ``grid`` rays span decimetres)."""
        o = cam.centre
        cols, rows = np.arange(0, w + grid, grid), np.arange(0, h + grid, grid)
        d = _rays(cam, s, cols, rows)
        t = o[2] / -d[:, 2]
        for _ in range(steps):
            t = (o[2] - self.terrain.height(o[0] + t * d[:, 0], o[1] + t * d[:, 1])) / -d[:, 2]
        coarse = t.reshape(len(rows), len(cols)).astype(np.float32)
        mx, my = np.meshgrid(np.arange(w, dtype=np.float32) / grid, np.arange(h, dtype=np.float32) / grid)
        return np.asarray(cv2.remap(coarse, mx, my, cv2.INTER_LINEAR), np.float64).ravel()

    def _terrain_march(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Ray parameters where any rays first meet the terrain (inf: not within GROUND_VIEW_M):
        geometric steps, then bisection on the step that crosses."""
        norm = np.linalg.norm(d, axis=1)
        steps = np.geomspace(0.2, GROUND_VIEW_M, 160)
        t = np.full(len(d), np.inf)
        lo = np.zeros(len(d))
        active = np.arange(len(d))
        prev = 0.0
        for dist in steps:
            tt = dist / norm[active]
            pz = o[2] + tt * d[active, 2]
            below = pz < self.terrain.height(o[0] + tt * d[active, 0], o[1] + tt * d[active, 1])
            done = active[below]
            t[done] = tt[below]
            lo[done] = prev / norm[done]
            active = active[~below]
            prev = dist
            if active.size == 0:
                break
        idx = np.flatnonzero(np.isfinite(t))
        a, b = lo[idx], t[idx]
        for _ in range(14):
            m = (a + b) / 2
            below = o[2] + m * d[idx, 2] < self.terrain.height(o[0] + m * d[idx, 0], o[1] + m * d[idx, 1])
            b = np.where(below, m, b)
            a = np.where(below, a, m)
        t[idx] = b
        return t

    def _hit_box(
        self,
        bld: Building,
        o: np.ndarray,
        d_all: np.ndarray,
        rows: np.ndarray,
        t_best: np.ndarray,
        colour: np.ndarray,
    ) -> None:
        d = d_all[rows]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d
            t0 = (bld.lo - o) * inv
            t1 = (bld.hi - o) * inv
        tmin, tmax = np.minimum(t0, t1), np.maximum(t0, t1)
        t_enter, t_exit = np.nanmax(tmin, axis=1), np.nanmin(tmax, axis=1)
        hit = (t_enter <= t_exit) & (t_enter > 0) & (t_enter < t_best[rows])
        if not hit.any():
            return
        sel = np.flatnonzero(hit)
        idx = rows[sel]
        axis = np.nanargmax(tmin[sel], axis=1)
        P = o + t_enter[sel, None] * d[sel]
        t_best[idx] = t_enter[sel]
        size = bld.hi - bld.lo
        textures = self.faces(bld)
        for a in range(3):
            on = axis == a
            if not on.any():
                continue
            positive = d[sel[on], a] < 0  # a ray travelling towards -a meets the +a face
            u_axis, v_axis = [(1, 2), (0, 2), (0, 1)][a]
            span = max(size[u_axis], size[v_axis])
            for sign in (False, True):
                m = positive == sign
                if not m.any():
                    continue
                tex = textures[2 * a + int(sign)]
                q = P[on][m]
                uu = (q[:, u_axis] - bld.lo[u_axis]) / span * (tex.shape[1] - 1)
                vv = (bld.hi[v_axis] - q[:, v_axis]) / span * (tex.shape[0] - 1)
                colour[idx[np.flatnonzero(on)[m]]] = sample_texture(tex, uu, vv)


def _rays(cam: Camera, s: int, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """World directions (z_cam = 1) of the rays through the centres of sub-pixels ``cols`` x
    ``rows`` of a ``s`` x render, row-major, (rows * cols, 3)."""
    K, R = cam.K, cam.R
    x = ((cols + 0.5) / s - K[0, 2]) / K[0, 0]
    y = ((rows + 0.5) / s - K[1, 2]) / K[1, 1]
    d = x[None, :, None] * R[0] + y[:, None, None] * R[1] + R[2]
    return d.reshape(-1, 3)


def _box_rays(cam: Camera, bld: Building, s: int, w: int, h: int) -> np.ndarray | None:
    """Indices of the rays (row-major at ``s`` x) inside the box's projected bounding
    rectangle; all rays when a corner is behind the camera; None when it is out of view."""
    corners = np.array(
        [
            [x, y, z]
            for x in (bld.lo[0], bld.hi[0])
            for y in (bld.lo[1], bld.hi[1])
            for z in (bld.lo[2], bld.hi[2])
        ]
    )
    uv, z = cam.project(corners)
    if (z <= 0.1).any():
        return np.arange(w * h)
    u0, v0 = np.floor((uv.min(0) + 0.5) * s).astype(int) - 1
    u1, v1 = np.ceil((uv.max(0) + 0.5) * s).astype(int) + 1
    u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, w), min(v1, h)
    if u0 >= u1 or v0 >= v1:
        return None
    vv, uu = np.mgrid[v0:v1, u0:u1]
    return (vv * w + uu).ravel()
