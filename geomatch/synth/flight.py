"""Synthetic drone survey flights over an area that grows with the photos, with ground truth.

The flight is a survey as a mapping app flies it: serpentine lines (each flown the other way from
the one before, so the photos' headings differ by 180 deg between lines and a return line's
photos are turned a half turn against the outbound one's), a nadir camera whose image top points
where the drone heads (DJI XMP: gimbal pitch -90, gimbal and flight yaw the heading), a constant
height above the take-off point, forward and side overlap as photogrammetry plans them, and an
area about square that grows with the number of photos. A few ground photos of buildings near
the middle are optional (a phone, 1.6 m up, looking at a wall from 11-17 m).

The world (East-North-Up metres; the take-off point on the ground is the origin, which is
synth.aerial's GPS_ORIGIN) is rolling terrain (a sum of long sinusoids: a flat ground would make
every fundamental matrix degenerate) with box buildings on some lots, textured with content no
other place shares (repeated texture folds SfM reconstructions): the ground is tiles, each a
turned, scaled and tinted crop of a scikit-image photo cross-faded into its neighbours, marked
with random shapes that run over the tile borders. Nothing is held for the whole area: a tile,
and a lot's building, is made from its own seeded generator when a view needs it and kept in a
cache bounded in bytes, so memory does not grow with the flight.

Rendering, at 2x and area-downsampled: nadir views meet the terrain by fixed-point iteration
along each ray (a few steps on gentle slopes), the buildings in view by a slab test on the rays
of their projected box, and sample the tiles in view; ground photos march their near-horizontal
rays instead, and see nothing beyond GROUND_VIEW_M (sky colour).

Output of :func:`write_flight`: ``images/`` (JPEG: EXIF focal length and GPS; DJI XMP on the
aerial photos), ``gt/`` (COLMAP text model and ``gps.json``, as synth.aerial.write_scene writes
them, and ``flight.json``: the plan), ``aerial.txt``.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from ..lru import ByteLRU
from ..metadata import dji_xmp, exif_for, gps_exif
from .aerial import (
    BARO_NOISE_M,
    GPS_ORIGIN,
    SKY,
    Camera,
    baro_heights,
    gimbal_angles,
    gps_fixes,
    look_at,
    unique_texture,
    write_gps_truth,
    write_gt,
)
from .photos import photo

# the camera: a 24 mm-equivalent lens (73 deg across a 4:3 frame, a DJI Mavic or Phantom)
FOCAL_PER_WIDTH = 24.0 / 36.0
PHONE_FOCAL_PER_WIDTH = 26.0 / 36.0
GPS_NOISE_M = 1.5  # consumer GNSS, per axis horizontally (1.5x that vertically: synth.aerial)
TILE = 256  # texels on a ground tile's side
MARGIN = 24  # texels each tile reaches into its neighbours, cross-faded
SHAPES_PER_TILE = 16
LOT_M = 48.0  # one building at most per lot
BUILDING_SHARE = 0.6  # of the lots
FACE_TEXELS = 192  # a building face's texture across its longer side
GROUND_VIEW_M = 150.0  # a ground photo's rays that meet nothing nearer see sky
CACHE_MB = 96.0  # tiles and buildings together
# synth.aerial's textures less those mostly blank (logo, hubble_deep_field, cell, retina): a crop
# of blank photo is a patch of ground no feature lands on
PHOTOS = (
    "astronaut",
    "coffee",
    "rocket",
    "chelsea",
    "immunohistochemistry",
    "motorcycle_left",
    "camera",
    "brick",
    "gravel",
    "coins",
    "clock",
    "moon",
    "grass",
)


def _key(*ints: int) -> list[int]:
    """Tile and lot indices as a seed sequence (numpy takes no negative entries)."""
    return [2 * i if i >= 0 else -2 * i - 1 for i in ints]


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

    def __init__(self, seed: int, texel_m: float, cache_mb: float = CACHE_MB) -> None:
        self.seed = seed
        self.texel = texel_m
        self.terrain = Terrain(seed)
        self.photos = [photo(n) for n in PHOTOS]
        self._base: ByteLRU[tuple[int, int], np.ndarray] = ByteLRU(cache_mb * 0.3)
        self._tiles: ByteLRU[tuple[int, int], np.ndarray] = ByteLRU(cache_mb * 0.4)
        self._faces: ByteLRU[tuple[int, int], list[np.ndarray]] = ByteLRU(
            cache_mb * 0.3, lambda v: sum(int(t.nbytes) for t in v)
        )
        ramp = np.minimum((np.arange(TILE + 2 * MARGIN) + 0.5) / (2 * MARGIN), 1.0)
        self._ramp = np.minimum(ramp, ramp[::-1]).astype(np.float32)

    # -- ground texture ----------------------------------------------------------------------
    def _tile_base(self, i: int, j: int) -> np.ndarray:
        """Tile (i, j)'s photo crop, texels [i*TILE - MARGIN, (i+1)*TILE + MARGIN) east (axis 1)
        and the same north (axis 0): turned, scaled (0.35-0.7 photo pixels a texel, so a tile
        shows a small part of its photo) and tinted."""
        hit = self._base.get((i, j))
        if hit is not None:
            return hit
        rng = np.random.default_rng([self.seed, 0x711E, *_key(i, j)])
        src = self.photos[int(rng.integers(len(self.photos)))]
        size = TILE + 2 * MARGIN
        scale = rng.uniform(0.35, 0.7)
        h, w = src.shape[:2]
        centre = rng.uniform(0.2, 0.8, 2) * (w, h)
        M = cv2.getRotationMatrix2D((float(centre[0]), float(centre[1])), rng.uniform(0, 360), 1 / scale)
        M[:, 2] += (size / 2 - centre[0], size / 2 - centre[1])
        img = cv2.warpAffine(src, M, (size, size), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT_101)
        gain = rng.uniform(0.7, 1.2, 3)
        base = np.clip(img.astype(np.float32) * gain + rng.uniform(-25, 25, 3), 0, 255).astype(np.uint8)
        self._base.put((i, j), base)
        return base

    def _tile_shapes(self, i: int, j: int) -> list[tuple[int, tuple[int, ...], tuple[int, ...], int]]:
        """Tile (i, j)'s marks in texels of the whole ground: (kind, colour, points, width); a mark
        reaches less than a tile from its tile, so only the 3x3 tiles around one can touch it."""
        rng = np.random.default_rng([self.seed, 0x5A9E, *_key(i, j)])
        out: list[tuple[int, tuple[int, ...], tuple[int, ...], int]] = []
        for _ in range(SHAPES_PER_TILE):
            colour = tuple(int(c) for c in rng.integers(0, 256, 3))
            x, y = int(i * TILE + rng.integers(TILE)), int(j * TILE + rng.integers(TILE))
            r = int(rng.integers(4, 40))
            kind = int(rng.integers(3))
            width = -1 if rng.random() < 0.6 else int(rng.integers(2, 5))
            if kind == 0:
                out.append((0, colour, (x, y, r), width))
            elif kind == 1:
                out.append((1, colour, (x, y, x + r, y + int(rng.integers(4, 2 * r + 4))), -1))
            else:
                pts = rng.integers(-2 * r, 2 * r + 1, 6)
                out.append(
                    (
                        2,
                        colour,
                        (x, y, x + int(pts[0]), y + int(pts[1]), x + int(pts[2]), y + int(pts[3])),
                        width,
                    )
                )
        return out

    def tile(self, i: int, j: int) -> np.ndarray:
        """The ground's texels [i*TILE, (i+1)*TILE) east by [j*TILE, (j+1)*TILE) north (row 0
        south), uint8: its own crop cross-faded with its neighbours', then every mark that
        reaches it, drawn in one order for the whole ground (so borders agree)."""
        hit = self._tiles.get((i, j))
        if hit is not None:
            return hit
        acc = np.zeros((TILE, TILE, 3), np.float32)
        for dj in (-1, 0, 1):
            for di in (-1, 0, 1):
                base = self._tile_base(i + di, j + dj)
                # the neighbour's texels inside this tile: offsets in its extended frame
                r0, r1 = max(0, MARGIN - dj * TILE), min(TILE + 2 * MARGIN, MARGIN + TILE - dj * TILE)
                c0, c1 = max(0, MARGIN - di * TILE), min(TILE + 2 * MARGIN, MARGIN + TILE - di * TILE)
                if r0 >= r1 or c0 >= c1:
                    continue
                w = self._ramp[r0:r1, None] * self._ramp[None, c0:c1]
                rr, cc = r0 - MARGIN + dj * TILE, c0 - MARGIN + di * TILE
                acc[rr : rr + r1 - r0, cc : cc + c1 - c0] += w[..., None] * base[r0:r1, c0:c1]
        img = np.ascontiguousarray(np.clip(acc + 0.5, 0, 255).astype(np.uint8))
        ox, oy = i * TILE, j * TILE
        for dj in (-1, 0, 1):
            for di in (-1, 0, 1):
                for kind, colour, p, width in self._tile_shapes(i + di, j + dj):
                    if kind == 0:
                        cv2.circle(img, (p[0] - ox, p[1] - oy), p[2], colour, width, cv2.LINE_AA)
                    elif kind == 1:
                        cv2.rectangle(img, (p[0] - ox, p[1] - oy), (p[2] - ox, p[3] - oy), colour, -1)
                    else:
                        pts = np.array(p, np.int32).reshape(3, 2) - (ox, oy)
                        cv2.polylines(img, [pts.astype(np.int32)], False, colour, max(width, 1), cv2.LINE_AA)
        self._tiles.put((i, j), img)
        return img

    def sample_ground(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(N, 3) float32 colours of the ground at east ``x``, north ``y`` (metres), bilinear
        over the tiles their bounding box covers."""
        if x.size == 0:
            return np.zeros((0, 3), np.float32)
        tx, ty = x / self.texel, y / self.texel
        i0, i1 = int(np.floor(tx.min() - 1)) // TILE, int(np.floor(tx.max() + 1)) // TILE
        j0, j1 = int(np.floor(ty.min() - 1)) // TILE, int(np.floor(ty.max() + 1)) // TILE
        region = np.empty(((j1 - j0 + 1) * TILE, (i1 - i0 + 1) * TILE, 3), np.uint8)
        for j in range(j0, j1 + 1):
            for i in range(i0, i1 + 1):
                region[(j - j0) * TILE : (j - j0 + 1) * TILE, (i - i0) * TILE : (i - i0 + 1) * TILE] = (
                    self.tile(i, j)
                )
        return _remap(region, tx - i0 * TILE - 0.5, ty - j0 * TILE - 0.5)

    # -- buildings -----------------------------------------------------------------------------
    def building(self, a: int, b: int) -> Building | None:
        """Lot (a, b)'s building, or None: 8-20 m a side, 4-14 m high, set into the terrain at
        its lowest corner, at least 3 m inside its lot (two buildings stand 6 m apart or more)."""
        rng = np.random.default_rng([self.seed, 0xB1D, *_key(a, b)])
        if rng.random() >= BUILDING_SHARE:
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
        rng = np.random.default_rng([self.seed, 0xFACE, *_key(*bld.lot)])
        out = []
        for _ in range(6):
            src = self.photos[int(rng.integers(len(self.photos)))]
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
        colour[hit] = self.sample_ground(P[:, 0], P[:, 1])
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
                colour[idx[np.flatnonzero(on)[m]]] = _remap(tex, uu, vv)


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


def _remap(tex: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear lookups (float32 (N, 3)) at texel coordinates; cv2.remap wants a 2-D map under
    32767 a side, so the points go in rows of 4096."""
    n = x.size
    cols = 4096
    rows = -(-n // cols)
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n], my[:n] = x, y
    out = cv2.remap(
        tex, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
    )
    return out.reshape(-1, 3)[:n].astype(np.float32)


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


def save_jpeg(
    path: Path,
    image: np.ndarray,
    cam: Camera,
    gps_enu: np.ndarray | None,
    height: float | None = None,
    yaw_error_deg: float = 0.0,
) -> None:
    """JPEG with the EXIF a camera writes (focal length, GPS at ``gps_enu`` in GPS_ORIGIN's ENU)
    and, for a drone's photo, DJI's XMP: relative altitude ``height``, the gimbal's angles and
    the flight yaw, the yaws off by the compass's ``yaw_error_deg``."""
    model = "synth-drone" if cam.aerial else "synth-phone"
    exif = exif_for("geomatch", model, float(cam.K[0, 0]) / 100.0, 100.0)
    if gps_enu is not None:
        lat, lon, alt = GPS_ORIGIN.to_geodetic(np.asarray(gps_enu, np.float64))
        gps_exif(exif, float(lat), float(lon), float(alt))
    xmp = b""
    if cam.aerial:
        pitch, yaw, roll = gimbal_angles(cam.R)
        yaw = (yaw + yaw_error_deg + 180.0) % 360.0 - 180.0
        h = float(cam.centre[2]) if height is None else height
        xmp = (
            dji_xmp(h, pitch, yaw, roll)
            .replace(
                "drone-dji:GimbalPitchDegree",
                f'drone-dji:FlightYawDegree="{yaw:+.1f}" drone-dji:GimbalPitchDegree',
            )
            .encode()
        )
    # Pillow writes the XMP into an APP1 segment, where drones put it (an empty one: none)
    Image.fromarray(image).save(path, quality=92, exif=exif.tobytes(), xmp=xmp)


def write_flight(
    out: str | Path,
    photos: int,
    ground: int = 0,
    seed: int = 0,
    width: int = 640,
    height: int = 480,
    gps_noise: float = GPS_NOISE_M,
    baro_noise: float = BARO_NOISE_M,
    altitude: float = 80.0,
) -> list[Camera]:
    """Render a survey of ``photos`` nadir photos (and ``ground`` handheld ones) into ``out``
    (module docstring) and return its cameras. An image already in ``images/`` is kept (the
    renders are deterministic), so an interrupted render resumes."""
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    plan = FlightPlan.make(photos, width, height, altitude)
    gsd = altitude / (FOCAL_PER_WIDTH * width)
    world = World(seed, texel_m=gsd / 2)
    cams, headings = aerial_cameras(plan, seed)
    cams += ground_cameras(world, plan, ground, seed)
    fixes = gps_fixes(cams, gps_noise, seed)
    heights = baro_heights(cams, baro_noise, seed)
    compass = np.random.default_rng([seed, 0xC0A]).normal(0.0, 2.0, len(cams))
    for c, err in zip(cams, compass, strict=True):
        path = out / "images" / c.name
        if not path.is_file():
            tmp = path.with_suffix(".tmp.jpg")
            save_jpeg(tmp, world.render(c)[0], c, fixes[c.name], heights.get(c.name), float(err))
            tmp.replace(path)
    write_gt(cams, out / "gt")
    write_gps_truth(out / "gt", cams, fixes, gps_noise, heights, baro_noise)
    (out / "gt" / "flight.json").write_text(
        json.dumps(
            {
                **asdict(plan),
                "per_line": plan.per_line,
                "headings_deg": dict(zip((c.name for c in cams if c.aerial), headings, strict=True)),
                "ground": [c.name for c in cams if not c.aerial],
                "seed": seed,
            },
            indent=1,
        )
        + "\n"
    )
    (out / "aerial.txt").write_text("".join(f"{c.name}\n" for c in cams if c.aerial))
    return cams
