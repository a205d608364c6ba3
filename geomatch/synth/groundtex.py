"""The ground texture of the survey world (synth.world): endless, made tile by tile on demand.

The ground is tiles, each a turned, scaled and tinted crop of a scikit-image photo cross-faded into
its neighbours, marked with random shapes that run over the tile borders, so no two places share
content (repeated texture folds SfM reconstructions). Nothing is held for the whole area: a tile is
made from its own seeded generator when a view needs it and kept in a cache bounded in bytes, so
memory does not grow with the flight, and a tile made again is the same texels.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..memory import ByteLRU
from .photos import photo
from .texture import TEXTURES, sample_texture

TILE = 256  # texels on a ground tile's side
MARGIN = 24  # texels each tile reaches into its neighbours, cross-faded
SHAPES_PER_TILE = 16
# a crop of a mostly blank photo is a patch of ground no feature lands on
BLANK_PHOTOS = frozenset({"logo", "hubble_deep_field", "cell", "retina"})
PHOTOS = tuple(t for t in TEXTURES if t not in BLANK_PHOTOS)


def seed_key(*ints: int) -> list[int]:
    """Tile and lot indices as a seed sequence (numpy takes no negative entries)."""
    return [2 * i if i >= 0 else -2 * i - 1 for i in ints]


class GroundTiles:
    """The ground's texels, ``texel_m`` metres each, tile by tile (module docstring); the photo
    crops and the finished tiles are cached apart, in ``crops_mb`` and ``tiles_mb``."""

    def __init__(self, seed: int, texel_m: float, crops_mb: float, tiles_mb: float) -> None:
        self.seed = seed
        self.texel = texel_m
        self.photos = [photo(n) for n in PHOTOS]
        self._base: ByteLRU[tuple[int, int], np.ndarray] = ByteLRU(crops_mb)
        self._tiles: ByteLRU[tuple[int, int], np.ndarray] = ByteLRU(tiles_mb)
        ramp = np.minimum((np.arange(TILE + 2 * MARGIN) + 0.5) / (2 * MARGIN), 1.0)
        self._ramp = np.minimum(ramp, ramp[::-1]).astype(np.float32)

    def _tile_base(self, i: int, j: int) -> np.ndarray:
        """Tile (i, j)'s photo crop, texels [i*TILE - MARGIN, (i+1)*TILE + MARGIN) east (axis 1)
        and the same north (axis 0): turned, scaled (0.35-0.7 photo pixels a texel, so a tile
        shows a small part of its photo) and tinted."""
        hit = self._base.get((i, j))
        if hit is not None:
            return hit
        rng = np.random.default_rng([self.seed, 0x711E, *seed_key(i, j)])
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
        rng = np.random.default_rng([self.seed, 0x5A9E, *seed_key(i, j)])
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

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
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
        return sample_texture(region, tx - i0 * TILE - 0.5, ty - j0 * TILE - 0.5).astype(np.float32)
