"""Farmland as a fixed-wing survey photographs it (synth.fixedwing): large fields of little texture
between dark roads, a pond now and then, optionally as a near-infrared camera sees it.

Matching farmland is hard for reasons the photo-tile ground of synth.groundtex hides: a field is
tens of metres of one crop whose rows and tramlines repeat, the detail a detector can hold on to is
faint (soil, weeds, wheel marks), and the strong edges are few (roads, field borders, hedges). A
converted NIR camera makes it worse: vegetation is bright, roads and water dark, and the colour
that tells one field from the next is gone. So the ground here is:

- parcels: the Voronoi cells of one seed point per PARCEL_M cell of a jittered grid, each a crop
  (rows and tramlines along its own direction), grass, bare soil or (rarely) water, with a
  brightness of its own and a border strip (a furrow or a hedge) of its own;
- roads: two families of straight roads in a frame turned once per world, dark in both palettes;
- detail: synth.groundtex's unique photo tiles, grey and scaled by ``detail`` (0.15: the faint
  texture of a field; 1: the photo's full contrast), so no two places are alike.

The layout is a function of the position (every texel asks its nearest parcel seeds), so tiles
made on demand agree at their borders and nothing is held for the whole area; tiles are cached
in bytes as groundtex's are.
"""

from __future__ import annotations

import math

import numpy as np

from ..memory import ByteLRU
from .groundtex import TILE, GroundTiles, seed_key

PARCEL_M = 200.0  # one field per cell of this side, on average
ROAD_PERIODS_M = (380.0, 530.0)  # between parallel roads of each family
ROAD_WIDTH_M = 5.5
BORDER_M = 1.6  # a field's border strip (furrow or hedge), each side of the boundary
WATER, CROP, GRASS, SOIL = 0, 1, 2, 3
# class brightness (lo, hi) in near infrared: vegetation reflects it, water and asphalt absorb it
NIR_LEVEL = {WATER: (14.0, 28.0), CROP: (170.0, 232.0), GRASS: (150.0, 205.0), SOIL: (105.0, 145.0)}
ROAD_NIR = 55.0
# visible colours of the same classes (RGB), for the colour option
VISIBLE = {
    WATER: (40.0, 62.0, 80.0),
    CROP: (78.0, 128.0, 52.0),
    GRASS: (96.0, 142.0, 70.0),
    SOIL: (138.0, 116.0, 88.0),
}
ROAD_VISIBLE = (96.0, 96.0, 100.0)


class FarmTiles(GroundTiles):
    """The farmland's texels, ``texel_m`` metres each (module docstring), with groundtex's tile
    interface (``sample``, ``photos`` for building faces), whose own tiles are the detail.
    ``nir``: near-infrared palette (grey, vegetation bright); ``detail``: how much of the unique
    photo detail shows through."""

    def __init__(
        self,
        seed: int,
        texel_m: float,
        nir: bool = True,
        detail: float = 0.15,
        crops_mb: float = 20.0,
        tiles_mb: float = 40.0,
    ) -> None:
        super().__init__(seed, texel_m, crops_mb=crops_mb, tiles_mb=tiles_mb / 2)
        self.nir = nir
        self.detail = detail
        self._farm: ByteLRU[tuple[int, int], np.ndarray] = ByteLRU(tiles_mb / 2)
        rng = np.random.default_rng([seed, 0x40AD])
        self._road_angle = rng.uniform(0, math.pi / 2)
        self._road_offsets = rng.uniform(0, 1, 2) * np.array(ROAD_PERIODS_M)

    def _parcels(self, ci: np.ndarray, cj: np.ndarray) -> dict[str, np.ndarray]:
        """Seed point and properties of the parcels of grid cells (ci, cj) (1-D arrays)."""
        rows = []
        for a, b in zip(ci.tolist(), cj.tolist(), strict=True):
            rng = np.random.default_rng([self.seed, 0xFA12, *seed_key(a, b)])
            u = rng.random()
            kind = WATER if u < 0.04 else CROP if u < 0.62 else GRASS if u < 0.82 else SOIL
            lo, hi = NIR_LEVEL[kind]
            rows.append(
                (
                    (a + rng.uniform(0.15, 0.85)) * PARCEL_M,
                    (b + rng.uniform(0.15, 0.85)) * PARCEL_M,
                    kind,
                    rng.uniform(lo, hi),  # brightness
                    rng.uniform(0, math.pi),  # row direction
                    rng.uniform(0.6, 3.0),  # row period, m
                    rng.uniform(2.0, 7.0) if kind in (CROP, SOIL) else 0.0,  # row amplitude
                    rng.uniform(18.0, 28.0),  # tramline spacing, m
                    rng.uniform(-30.0, 30.0),  # border strip: darker (furrow) or brighter (hedge)
                    rng.uniform(0, 2 * math.pi),  # phase of the slow blotches
                    rng.uniform(25.0, 70.0),  # their wavelength, m
                )
            )
        arr = np.array(rows, np.float64).reshape(-1, 11)
        keys = ("x", "y", "kind", "level", "dir", "period", "amp", "tram", "border", "phase", "blotch")
        return {k: arr[:, i] for i, k in enumerate(keys)}

    def layout(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per point: the NIR-like brightness, the class (roads: -1) and the distance to its
        field's border (metres)."""
        c0i, c1i = math.floor(x.min() / PARCEL_M) - 1, math.floor(x.max() / PARCEL_M) + 1
        c0j, c1j = math.floor(y.min() / PARCEL_M) - 1, math.floor(y.max() / PARCEL_M) + 1
        gi, gj = np.meshgrid(np.arange(c0i, c1i + 1), np.arange(c0j, c1j + 1))
        p = self._parcels(gi.ravel(), gj.ravel())
        d2 = (x[:, None] - p["x"][None]) ** 2 + (y[:, None] - p["y"][None]) ** 2
        order = np.argsort(d2, axis=1)[:, :2]
        near, second = order[:, 0], order[:, 1]
        rows = np.arange(len(x))
        s1 = np.stack([p["x"][near], p["y"][near]], 1)
        s2 = np.stack([p["x"][second], p["y"][second]], 1)
        border = (d2[rows, second] - d2[rows, near]) / (2 * np.linalg.norm(s2 - s1, axis=1) + 1e-9)
        kind = p["kind"][near]
        along = np.cos(p["dir"][near]) * x + np.sin(p["dir"][near]) * y
        across = -np.sin(p["dir"][near]) * x + np.cos(p["dir"][near]) * y
        v = p["level"][near].copy()
        v += p["amp"][near] * np.sin(2 * np.pi * across / p["period"][near])
        tram = np.abs(((across / p["tram"][near]) + 0.5) % 1.0 - 0.5) * p["tram"][near]
        v -= np.where((kind == CROP) & (tram < 0.35), 22.0, 0.0)
        v += 6.0 * np.sin(2 * np.pi * (along + 0.6 * across) / p["blotch"][near] + p["phase"][near])
        v += np.where(border < BORDER_M, p["border"][near], 0.0)
        water = kind == WATER
        v[water] = p["level"][near][water]
        # roads: distance to the nearest line of each family, in the roads' frame
        cos_a, sin_a = math.cos(self._road_angle), math.sin(self._road_angle)
        road = np.zeros(len(x), bool)
        for k, (period, off) in enumerate(zip(ROAD_PERIODS_M, self._road_offsets, strict=True)):
            t = (cos_a * x + sin_a * y) if k == 0 else (-sin_a * x + cos_a * y)
            dist = np.abs(((t - off) / period + 0.5) % 1.0 - 0.5) * period
            road |= dist < ROAD_WIDTH_M / 2
            v = np.where(dist < ROAD_WIDTH_M / 2 + 0.8, np.minimum(v, ROAD_NIR + 40.0), v)
        v[road] = ROAD_NIR
        kind = np.where(road, -1.0, kind)
        return v, kind, border

    def tile(self, i: int, j: int) -> np.ndarray:
        """Texels [i*TILE, (i+1)*TILE) east by [j*TILE, (j+1)*TILE) north (row 0 south), uint8."""
        hit = self._farm.get((i, j))
        if hit is not None:
            return hit
        c = (np.arange(TILE) + 0.5) * self.texel
        x, y = np.meshgrid(i * TILE * self.texel + c, j * TILE * self.texel + c)
        v, kind, _ = self.layout(x.ravel(), y.ravel())
        detail = super().tile(i, j).astype(np.float32).mean(axis=2).ravel()
        still = (kind == WATER) | (kind == -1)  # water and asphalt carry less detail
        v = v + (detail - 128.0) * self.detail * np.where(still, 0.3, 1.0)
        if self.nir:
            # a converted camera's false colour: NIR in red, some of it in green and blue
            rgb = np.stack([v, 0.86 * v + 8.0, 0.9 * v + 4.0], 1)
        else:
            # the class's colour, as bright as the texel is against its class's mean level
            cls = np.where(kind < 0, 4, kind).astype(int)
            palette = np.array([*(VISIBLE[k] for k in range(4)), ROAD_VISIBLE])
            mean = np.array([*(sum(NIR_LEVEL[k]) / 2 for k in range(4)), ROAD_NIR])
            rgb = palette[cls] * (v / mean[cls])[:, None]
        img = np.clip(rgb + 0.5, 0, 255).astype(np.uint8).reshape(TILE, TILE, 3)
        self._farm.put((i, j), img)
        return img
