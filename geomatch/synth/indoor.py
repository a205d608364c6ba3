"""Synthetic indoor rooms with ground truth: the wide-baseline pairs where held-out data says we fail.

Real indoor scans (ScanNet-like, 640x480) are hard for other reasons than the outdoor scenes of
:mod:`geomatch.synth.aerial`: most of the image is plain painted wall, floor and ceiling with nothing to
detect, what texture there is often repeats (floor tiles, shelves, cupboard doors, the same poster
twice), the camera is close to the geometry, so a 20-70 degree rotation changes the view a lot.
A room here is the inside of a box (walls, floor, ceiling) holding furniture boxes on the floor,
lit by ceiling lights (view-independent Lambertian shading, so the ground truth stays exact), and
rendered by ray casting like the outdoor scenes: nearest hit per ray, supersampled colour, depth
(camera z) cast at the exact pixel centres.

Pairs are chosen as the indoor benchmarks choose them: relative rotation 20-70 degrees and a
covisibility of at least 10 %, computed from depth (see :func:`covisibility`). Public API:
:func:`indoor_pairs`, :func:`no_overlap_pairs`, :func:`gt_matches`, :func:`write_room`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .aerial import Camera, look_at, sample_texture, save_png, scribble, unique_texture, write_gt
from .photos import photo as _load_photo

PPM = 250.0  # texture pixels per metre: a wall 2 m away at f = 560 px is seen at ~280 px/m
PHOTOS = ("astronaut", "coffee", "rocket", "chelsea", "motorcycle_left", "camera", "clock", "coins", "retina")
FABRICS = ("gravel", "grass", "cell", "moon")
PAINTS = (
    (232, 228, 218),
    (221, 214, 196),
    (205, 210, 212),
    (214, 222, 230),
    (236, 232, 236),
    (200, 205, 190),
)
MIN_ROTATION_DEG, MAX_ROTATION_DEG, MIN_COVISIBILITY = 20.0, 70.0, 0.10
PAIRS_PER_ROOM = 5


photo = functools.lru_cache(maxsize=None)(_load_photo)  # read-only use: every caller copies or resizes


# -- textures ---------------------------------------------------------------------------------------
def _canvas(w_m: float, h_m: float) -> tuple[int, int]:
    return max(2, round(h_m * PPM)), max(2, round(w_m * PPM))


def _paint(h: int, w: int, base: tuple[int, ...], rng: np.random.Generator, noise: float = 2.0) -> np.ndarray:
    """Plain paint: flat colour, a faint low-frequency blotch and texel noise (no corners to detect)."""
    low = cv2.resize(rng.normal(0, 5.0, (4, 6)).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)
    fine = cv2.GaussianBlur(rng.normal(0, noise, (h, w)).astype(np.float32), (3, 3), 0)
    img = np.asarray(base, np.float32)[None, None] * rng.uniform(0.95, 1.05) + (low + fine)[:, :, None]
    return np.clip(img, 0, 255).astype(np.uint8)


def _px(v: float) -> int:
    return round(v * PPM)


def _poster(img: np.ndarray, x: float, y: float, pic: np.ndarray, w: float, h: float) -> None:
    """A framed picture with its top-left corner at (x, y) metres on the canvas."""
    x0, y0, x1, y1 = _px(x), _px(y), _px(x + w), _px(y + h)
    cv2.rectangle(img, (x0, y0), (x1, y1), (40, 35, 30), -1)
    b = max(2, _px(0.03))
    inner = (x1 - x0 - 2 * b, y1 - y0 - 2 * b)
    if min(inner) > 2:
        img[y0 + b : y0 + b + inner[1], x0 + b : x0 + b + inner[0]] = cv2.resize(
            pic, inner, interpolation=cv2.INTER_AREA
        )


def _crop(src: np.ndarray, aspect: float, rng: np.random.Generator) -> np.ndarray:
    h, w = src.shape[:2]
    ch = int(h * rng.uniform(0.5, 0.9))
    cw = min(w, int(ch * aspect))
    y, x = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
    return np.ascontiguousarray(src[y : y + ch, x : x + cw])


def _wall(
    w_m: float, h_m: float, paint: tuple[int, int, int], rng: np.random.Generator, shared: dict[str, Any]
) -> np.ndarray:
    """A painted wall with a skirting board and a few things on it: a door, a window, framed photos
    (one of them the room's repeated poster), a whiteboard, switches. Mostly paint, on purpose."""
    h, w = _canvas(w_m, h_m)
    img = _paint(h, w, paint, rng)
    cv2.rectangle(img, (0, h - _px(0.08)), (w, h), tuple(int(c * 0.55) for c in paint), -1)
    x = rng.uniform(0.2, 0.8)
    while x < w_m - 0.6:
        kind = rng.choice(
            ["door", "window", "poster", "repeat", "board", "switch", "gap"],
            p=[0.1, 0.1, 0.3, 0.15, 0.1, 0.1, 0.15],
        )
        if kind == "door" and x + 1.0 < w_m:
            wood = tuple(int(c) for c in rng.integers([120, 80, 50], [190, 140, 100]))
            cv2.rectangle(img, (_px(x), h - _px(2.05)), (_px(x + 0.9), h), wood, -1)
            cv2.rectangle(img, (_px(x), h - _px(2.05)), (_px(x + 0.9), h), (60, 50, 40), 3)
            cv2.circle(img, (_px(x + 0.78), h - _px(1.0)), max(2, _px(0.03)), (180, 180, 170), -1)
            x += 1.0
        elif kind == "window" and x + 1.3 < w_m and h_m > 2.5:
            x0, y0, x1, y1 = _px(x), _px(0.7), _px(x + 1.2), _px(1.9)
            sky = np.linspace([235, 225, 205], [250, 248, 240], y1 - y0)[:, None, :]
            img[y0:y1, x0:x1] = sky.astype(np.uint8)
            cv2.rectangle(img, (x0, y0), (x1, y1), (245, 245, 245), max(2, _px(0.05)))
            cv2.line(img, ((x0 + x1) // 2, y0), ((x0 + x1) // 2, y1), (245, 245, 245), max(2, _px(0.04)))
            x += 1.3
        elif kind in ("poster", "repeat"):
            pic = shared["poster"] if kind == "repeat" else _crop(photo(str(rng.choice(PHOTOS))), 0.75, rng)
            pw = 0.6 if kind == "repeat" else rng.uniform(0.4, 0.8)
            ph = pw * pic.shape[0] / pic.shape[1]
            if x + pw < w_m:
                _poster(img, x, rng.uniform(0.5, 1.0), pic, pw, ph)
            x += pw + 0.1
        elif kind == "board" and x + 1.3 < w_m:
            x0, y0, x1, y1 = _px(x), _px(0.8), _px(x + 1.2), _px(1.7)
            board = np.full((y1 - y0, x1 - x0, 3), 246, np.uint8)
            scribble(board, rng, int(rng.integers(4, 12)), max_radius=_px(0.08))
            img[y0:y1, x0:x1] = board
            cv2.rectangle(img, (x0, y0), (x1, y1), (150, 150, 155), 3)
            x += 1.3
        elif kind == "switch":
            cv2.rectangle(img, (_px(x), _px(h_m - 1.1)), (_px(x + 0.08), _px(h_m - 1.0)), (245, 245, 240), -1)
            cv2.rectangle(img, (_px(x), _px(h_m - 1.1)), (_px(x + 0.08), _px(h_m - 1.0)), (180, 180, 180), 1)
        x += rng.uniform(0.15, 0.7)
    return img


def _floor(w_m: float, h_m: float, rng: np.random.Generator) -> np.ndarray:
    """Tiles (a repeated grid), planks or carpet; sometimes a rug with a photo pattern."""
    h, w = _canvas(w_m, h_m)
    kind = rng.integers(3)
    if kind == 0:  # tiles: the same square again and again, grout lines
        base = tuple(int(c) for c in rng.integers([150, 140, 120], [220, 210, 200]))
        img = _paint(h, w, base, rng, noise=4.0)
        step = _px(rng.choice([0.3, 0.4, 0.5, 0.6]))
        for p in range(0, max(h, w), step):
            cv2.line(img, (p, 0), (p, h), (90, 90, 85), 2)
            cv2.line(img, (0, p), (w, p), (90, 90, 85), 2)
    elif kind == 1:  # planks along x, each its own tone
        img = np.zeros((h, w, 3), np.uint8)
        step = _px(0.18)
        wood = np.array(rng.integers([120, 80, 45], [180, 130, 80]), np.float32)
        for y in range(0, h, step):
            tone = np.clip(wood * rng.uniform(0.85, 1.15), 0, 255)
            img[y : y + step] = _paint(min(step, h - y), w, tuple(int(c) for c in tone), rng, noise=5.0)
            cv2.line(img, (0, y), (w, y), (50, 35, 25), 2)
            for x in range(int(rng.integers(0, _px(1.5))), w, _px(1.5)):
                cv2.line(img, (x, y), (x, min(h, y + step)), (50, 35, 25), 2)
    else:  # carpet: fine noise, no structure
        base = tuple(int(c) for c in rng.integers([70, 70, 70], [150, 140, 130]))
        img = _paint(h, w, base, rng, noise=9.0)
    if rng.random() < 0.6:  # a rug
        rw, rh = rng.uniform(1.2, 2.0), rng.uniform(0.8, 1.4)
        rx, ry = rng.uniform(0.5, max(0.6, w_m - rw - 0.5)), rng.uniform(0.5, max(0.6, h_m - rh - 0.5))
        rug = unique_texture(photo(str(rng.choice(FABRICS + PHOTOS))), 256, rng, shapes=20)
        _poster(img, rx, ry, rug, rw, rh)
    return img


def _ceiling(w_m: float, h_m: float, rng: np.random.Generator) -> np.ndarray:
    """Uniform white with a regular grid of light panels: nothing unique up there."""
    h, w = _canvas(w_m, h_m)
    img = _paint(h, w, (240, 240, 238), rng, noise=1.5)
    step = rng.uniform(1.5, 2.2)
    for x in np.arange(step / 2, w_m - 0.5, step):
        for y in np.arange(step / 2, h_m - 0.5, step):
            cv2.rectangle(img, (_px(x), _px(y)), (_px(x + 0.6), _px(y + 0.6)), (255, 255, 252), -1)
            cv2.rectangle(img, (_px(x), _px(y)), (_px(x + 0.6), _px(y + 0.6)), (190, 190, 190), 2)
    return img


def _front(kind: str, w_m: float, h_m: float, rng: np.random.Generator, shared: dict[str, Any]) -> np.ndarray:
    """A vertical furniture face: cupboard doors, shelves of books, fabric, or a textured object."""
    h, w = _canvas(w_m, h_m)
    if kind == "cupboard":  # plain doors, identical handles: repeated, low texture
        paint = tuple(int(c) for c in shared["cupboard"])
        img = _paint(h, w, paint, rng)
        n = max(1, round(w_m / 0.5))
        for i in range(n):
            x0 = i * w // n
            cv2.rectangle(img, (x0 + 3, 3), (x0 + w // n - 3, h - 3), tuple(int(c * 0.7) for c in paint), 2)
            hx = x0 + (w // n - 12 if i % 2 == 0 else 12)
            cv2.rectangle(img, (hx - 3, h // 2 - _px(0.1)), (hx + 3, h // 2 + _px(0.1)), (90, 90, 95), -1)
        return img
    if kind == "shelf":  # shelves of books: the same few rows of spines repeat
        img = _paint(h, w, (110, 80, 55), rng)
        rows = shared["books"]
        board = _px(0.03)
        row_h = _px(0.36)
        for i, y in enumerate(range(board, h - row_h, row_h + board)):
            spines = rows[i % len(rows)]
            seg = spines[:, : w - 2 * board] if spines.shape[1] >= w - 2 * board else None
            if seg is None:
                seg = cv2.resize(spines, (w - 2 * board, spines.shape[0]))
            img[y + row_h - seg.shape[0] : y + row_h, board : board + seg.shape[1]] = seg
        return img
    if kind == "sofa":
        fabric = photo(str(rng.choice(FABRICS)))
        fabric = cv2.resize(_crop(fabric, w_m / h_m, rng), (w, h), interpolation=cv2.INTER_AREA)
        tint = np.asarray(shared["sofa"], np.float32) / 255.0
        grey = fabric.astype(np.float32).mean(axis=2, keepdims=True)
        img = (0.75 * np.asarray(shared["sofa"], np.float32) + 0.25 * grey * tint * 1.5).clip(0, 255)
        return img.astype(np.uint8)
    if kind == "object":  # a textured thing (a painted crate, a printed box): matchable
        return unique_texture(photo(str(rng.choice(PHOTOS))), max(h, w), rng, shapes=15)[:h, :w].copy()
    # table sides: plain dark wood
    return _paint(h, w, tuple(int(c) for c in shared["table"]), rng)


def _books(rng: np.random.Generator) -> list[np.ndarray]:
    rows = []
    for _ in range(2):
        row = np.zeros((_px(0.3), _px(2.5), 3), np.uint8)
        x = 0
        while x < row.shape[1]:
            bw = int(rng.integers(_px(0.02), _px(0.06)))
            bh = int(rng.integers(_px(0.2), _px(0.3)))
            colour = tuple(int(c) for c in rng.integers(30, 230, 3))
            row[row.shape[0] - bh :, x : x + bw] = colour
            cv2.line(row, (x, row.shape[0] - bh), (x, row.shape[0]), (20, 20, 20), 1)
            x += bw
        rows.append(row)
    return rows


# -- geometry ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Item:
    """An axis-aligned box: the room (seen from inside) or a piece of furniture (from outside)."""

    lo: np.ndarray
    hi: np.ndarray
    faces: tuple[np.ndarray, ...]  # texture per face: -x, +x, -y, +y, -z, +z
    inside: bool = False


# face a's texture (u, v) axes; v runs downwards (from hi) on walls, along -y on floors
_UV = [(1, 2), (0, 2), (0, 1)]


class Room:
    """One room (seeded): the geometry, its textures, lights, candidate cameras and renders."""

    def __init__(self, seed: int | np.random.SeedSequence) -> None:
        rng = np.random.default_rng(seed)
        self.rng = rng
        L, W, H = rng.uniform(5.0, 8.0), rng.uniform(4.0, 6.0), rng.uniform(2.6, 3.0)
        self.size = np.array([L, W, H])
        poster = _crop(photo(str(rng.choice(PHOTOS))), 0.75, rng)
        shared = {
            "poster": poster,
            "cupboard": rng.integers([180, 170, 150], [245, 240, 230]),
            "sofa": rng.integers([60, 50, 50], [170, 150, 150]),
            "table": rng.integers([80, 55, 35], [150, 110, 80]),
            "books": _books(rng),
        }
        paint = PAINTS[int(rng.integers(len(PAINTS)))]
        walls = [
            _wall(W, H, paint, rng, shared),  # -x wall (u = y)
            _wall(W, H, paint, rng, shared),
            _wall(L, H, paint, rng, shared),  # -y wall (u = x)
            _wall(L, H, paint, rng, shared),
        ]
        self.items = [
            Item(np.zeros(3), self.size.copy(), (*walls, _floor(L, W, rng), _ceiling(L, W, rng)), True)
        ]
        self._furnish(rng, shared)
        # lights under the ceiling: smooth view-independent shading on every plain surface
        self.lights = [
            np.array([rng.uniform(0.25, 0.75) * L, rng.uniform(0.25, 0.75) * W, H - 0.3]) for _ in range(2)
        ]

    def _furnish(self, rng: np.random.Generator, shared: dict[str, Any]) -> None:
        L, W, _ = self.size
        kinds = ["table", "cupboard", "shelf", "sofa", "object"]
        kinds += list(rng.choice(["table", "cupboard", "shelf", "object"], size=int(rng.integers(2, 5))))
        dims = {
            "table": ((1.2, 1.8), (0.7, 0.9), (0.72, 0.76)),
            "cupboard": ((0.8, 1.6), (0.4, 0.6), (1.8, 2.2)),
            "shelf": ((0.8, 1.2), (0.3, 0.4), (1.8, 2.0)),
            "sofa": ((1.8, 2.2), (0.8, 0.9), (0.75, 0.85)),
            "object": ((0.4, 0.7), (0.4, 0.7), (0.5, 1.1)),
        }
        self.footprints: list[tuple[np.ndarray, np.ndarray]] = []
        for kind in kinds:
            for _ in range(200):
                (a0, a1), (b0, b1), (c0, c1) = dims[kind]
                sx, sy, sz = rng.uniform(a0, a1), rng.uniform(b0, b1), rng.uniform(c0, c1)
                if rng.random() < 0.5:
                    sx, sy = sy, sx
                if kind in ("cupboard", "shelf", "sofa"):  # against a wall
                    side = int(rng.integers(4))
                    if side < 2:
                        sx, sy = min(sx, sy), max(sx, sy)
                        x = 0.0 if side == 0 else L - sx
                        y = rng.uniform(0.0, W - sy)
                    else:
                        sx, sy = max(sx, sy), min(sx, sy)
                        y = 0.0 if side == 2 else W - sy
                        x = rng.uniform(0.0, L - sx)
                else:
                    x, y = rng.uniform(0.6, L - sx - 0.6), rng.uniform(0.6, W - sy - 0.6)
                lo, hi = np.array([x, y, 0.0]), np.array([x + sx, y + sy, sz])
                if any(
                    np.all(lo[:2] < b_hi[:2] + 0.5) and np.all(b_lo[:2] - 0.5 < hi[:2])
                    for b_lo, b_hi in self.footprints
                ):
                    continue
                self.footprints.append((lo, hi))
                size = hi - lo
                faces = []
                for f in range(6):
                    u, v = _UV[f // 2]
                    if f == 5:  # the top
                        top = _paint(*_canvas(size[u], size[v]), shared["table"], rng)
                        if kind == "table":  # papers, a laptop, a mug: a few textured things
                            for _ in range(int(rng.integers(2, 5))):
                                pw = rng.uniform(0.2, 0.4)
                                _poster(
                                    top,
                                    rng.uniform(0, max(0.01, size[u] - pw)),
                                    rng.uniform(0, max(0.01, size[v] - pw)),
                                    _crop(photo(str(rng.choice(PHOTOS))), 1.0, rng),
                                    pw,
                                    pw * 0.75,
                                )
                        faces.append(top)
                    elif f == 4:
                        faces.append(np.zeros((2, 2, 3), np.uint8))
                    else:
                        faces.append(_front(kind, size[u], size[v], rng, shared))
                self.items.append(Item(lo, hi, tuple(faces)))
                break

    # -- cameras ------------------------------------------------------------------------------------
    def camera(self, rng: np.random.Generator, width: int, height: int, name: str) -> Camera:
        """A hand-held scanner: 1.2-1.8 m up, away from walls and furniture, pitched down a little."""
        L, W, _ = self.size
        while True:
            c = np.array([rng.uniform(0.4, L - 0.4), rng.uniform(0.4, W - 0.4), rng.uniform(1.2, 1.8)])
            if not any(
                np.all(c[:2] > lo[:2] - 0.3) and np.all(c[:2] < hi[:2] + 0.3) for lo, hi in self.footprints
            ):
                break
        yaw, pitch, roll = (
            rng.uniform(0, 2 * np.pi),
            np.deg2rad(rng.uniform(-35, 5)),
            np.deg2rad(rng.uniform(-6, 6)),
        )
        d = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
        R, _ = look_at(c, c + d)
        cr, sr = np.cos(roll), np.sin(roll)
        R = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1.0]]) @ R
        f = rng.uniform(0.8, 0.92) * width
        K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
        return Camera(name, K, R, -R @ c, width, height, False)

    # -- rendering ----------------------------------------------------------------------------------
    def _cast(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hit per ray: (ray parameter, item * 6 + face). The camera is inside the room.

        Slab tests on one contiguous array per axis: several times faster than on (N, 3) arrays."""
        tiny = np.asarray(1e-12, d.dtype)
        comps = [np.where(np.abs(c) < tiny, tiny, c) for c in d.T]
        inv = [1.0 / c for c in comps]
        room = self.items[0]
        exits = [np.maximum((room.lo[a] - o[a]) * inv[a], (room.hi[a] - o[a]) * inv[a]) for a in range(3)]
        t_best = np.minimum(np.minimum(exits[0], exits[1]), exits[2])
        axis = np.where(exits[0] == t_best, 0, np.where(exits[1] == t_best, 1, 2))
        face = 2 * axis + (np.choose(axis, comps) > 0)
        for k, item in enumerate(self.items[1:], 1):
            tmins, tmaxs = [], []
            for a in range(3):
                t0, t1 = (item.lo[a] - o[a]) * inv[a], (item.hi[a] - o[a]) * inv[a]
                tmins.append(np.minimum(t0, t1))
                tmaxs.append(np.maximum(t0, t1))
            t_enter = np.maximum(np.maximum(tmins[0], tmins[1]), tmins[2])
            t_exit = np.minimum(np.minimum(tmaxs[0], tmaxs[1]), tmaxs[2])
            hit = (t_enter <= t_exit) & (t_enter > 0) & (t_enter < t_best)
            idx = np.flatnonzero(hit)
            if idx.size == 0:
                continue
            te = t_enter[idx]
            hit_axis = np.where(tmins[0][idx] == te, 0, np.where(tmins[1][idx] == te, 1, 2))
            t_best[idx] = te
            face[idx] = 6 * k + 2 * hit_axis + (np.choose(hit_axis, [c[idx] for c in comps]) < 0)
        return t_best, face

    def _rays(self, cam: Camera, s: int, dtype: type = np.float64) -> tuple[np.ndarray, int, int]:
        w, h = cam.width * s, cam.height * s
        u, v = np.meshgrid((np.arange(w) + 0.5) / s, (np.arange(h) + 0.5) / s)
        pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1)
        dirs = (pix @ np.linalg.inv(cam.K).T) @ cam.R  # world directions with z_cam = 1
        return dirs.astype(dtype), w, h

    def depth(self, cam: Camera) -> np.ndarray:
        """Camera z at the exact pixel centres (the convention of Camera.project)."""
        dirs, w, h = self._rays(cam, 1)
        return self._cast(cam.centre, dirs)[0].reshape(h, w)

    def render(
        self, cam: Camera, supersample: int = 2, noise_seed: int | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """RGB uint8 image (with sensor noise when ``noise_seed`` is given) and depth (camera z)."""
        s = supersample
        dirs, w, h = self._rays(cam, s, np.float32)  # colour needs no more precision; depth is cast apart
        o = cam.centre.astype(np.float32)
        t, face = self._cast(o, dirs)
        P = o + t[:, None] * dirs
        colour = np.zeros((len(t), 3), np.float32)
        order = np.argsort(face, kind="stable")
        bounds = np.searchsorted(face[order], np.arange(6 * len(self.items) + 1))
        shade = np.zeros(len(t), np.float32)
        for fid in range(6 * len(self.items)):
            sel = order[bounds[fid] : bounds[fid + 1]]
            if sel.size == 0:
                continue
            item = self.items[fid // 6]
            a, positive = (fid % 6) // 2, fid % 2 == 1
            u_ax, v_ax = _UV[a]
            tex = item.faces[fid % 6]
            q = P[sel]
            uu = (q[:, u_ax] - item.lo[u_ax]) * PPM
            vv = (item.hi[v_ax] - q[:, v_ax]) * PPM
            colour[sel] = _sample(tex, uu, vv)
            normal = np.zeros(3)
            normal[a] = 1.0 if positive != item.inside else -1.0
            shade[sel] = self._shade(q, normal)
        img: np.ndarray = (colour * shade[:, None]).reshape(h, w, 3)
        if s > 1:
            img = cv2.resize(img, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
        if noise_seed is not None:  # per-shot exposure and sensor noise: view-dependent, as in a scan
            nrng = np.random.default_rng(noise_seed)
            img = img * nrng.uniform(0.9, 1.1) + nrng.normal(0, 2.0, img.shape).astype(np.float32)
        depth = self.depth(cam)
        return np.clip(img, 0, 255).astype(np.uint8), depth

    def _shade(self, q: np.ndarray, normal: np.ndarray) -> np.ndarray:
        out = np.full(len(q), 0.55, np.float32)
        for light in self.lights:
            v = light - q
            dist2 = np.einsum("ij,ij->i", v, v)
            lam = np.clip(v @ normal, 0, None) / np.sqrt(dist2 + 1e-9)
            out += (0.55 * lam / (1.0 + dist2 / 9.0)).astype(np.float32)
        return np.minimum(out, 1.15)


def _sample(tex: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Texel centres at +0.5 here (the outdoor scene samples at integers), edges clamped."""
    return sample_texture(tex, x - 0.5, y - 0.5, cv2.BORDER_REPLICATE).astype(np.float32)


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


def _choose_pairs(
    seed: int,
    salt: int,
    n_pairs: int,
    n_candidates: int,
    tag: str,
    candidate: Callable[[float, float, float], bool],
    keep: Callable[[IndoorPair], bool],
    width: int,
    height: int,
    supersample: int,
) -> list[IndoorPair]:
    """Room after room, up to :data:`PAIRS_PER_ROOM` pairs of ``n_candidates`` random views: the
    view pairs whose (rotation, covisibility, baseline) on the small depth renders pass
    ``candidate``, in random order, no view in two pairs, each rendered full size and taken if it
    passes ``keep``. Deterministic per (seed, salt)."""
    out: list[IndoorPair] = []
    for k, room, rng in _rooms(seed, salt):
        cams, small, depths = _candidates(room, rng, n_candidates, width, height)
        options = [
            (i, j)
            for i in range(len(cams))
            for j in range(i + 1, len(cams))
            if candidate(*_pair_stats(small, depths, i, j))
        ]
        used: set[int] = set()
        taken = 0
        for idx in rng.permutation(len(options)):
            i, j = options[idx]
            if i in used or j in used or taken == PAIRS_PER_ROOM or len(out) == n_pairs:
                continue
            name = f"s{seed}_{tag}r{k}_{i:02d}_{j:02d}"
            pair = _make_pair(room, cams[i], cams[j], name, supersample, 1000 * k + 2 * taken)
            if not keep(pair):
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

    return _choose_pairs(seed, 0, n_pairs, 48, "", candidate, keep, width, height, supersample)


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

    return _choose_pairs(seed, 1, n_pairs, 32, "none_", candidate, keep, width, height, supersample)


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
