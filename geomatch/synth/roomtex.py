"""The textures of a synthetic indoor room: painted walls with a few things on them, tiled or
planked floors, a ceiling of light panels, furniture faces. Mostly plain paint and repeated
patterns, on purpose: that is what makes real indoor scans hard to match.

Textures are drawn in metres at :data:`PPM` texels per metre; the package photos
(:mod:`geomatch.synth.photos`) serve as posters, rugs and printed boxes.
"""

from __future__ import annotations

import functools
from typing import Any

import cv2
import numpy as np

from .photos import photo as _load_photo
from .texture import scribble, unique_texture

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


photo = functools.lru_cache(maxsize=None)(_load_photo)  # read-only use: every caller copies or resizes


def canvas(w_m: float, h_m: float) -> tuple[int, int]:
    return max(2, round(h_m * PPM)), max(2, round(w_m * PPM))


def plain_paint(
    h: int, w: int, base: tuple[int, ...], rng: np.random.Generator, noise: float = 2.0
) -> np.ndarray:
    """Plain paint: flat colour, a faint low-frequency blotch and texel noise (no corners to detect)."""
    low = cv2.resize(rng.normal(0, 5.0, (4, 6)).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)
    fine = cv2.GaussianBlur(rng.normal(0, noise, (h, w)).astype(np.float32), (3, 3), 0)
    img = np.asarray(base, np.float32)[None, None] * rng.uniform(0.95, 1.05) + (low + fine)[:, :, None]
    return np.clip(img, 0, 255).astype(np.uint8)


def _px(v: float) -> int:
    return round(v * PPM)


def poster(img: np.ndarray, x: float, y: float, pic: np.ndarray, w: float, h: float) -> None:
    """A framed picture with its top-left corner at (x, y) metres on the canvas."""
    x0, y0, x1, y1 = _px(x), _px(y), _px(x + w), _px(y + h)
    cv2.rectangle(img, (x0, y0), (x1, y1), (40, 35, 30), -1)
    b = max(2, _px(0.03))
    inner = (x1 - x0 - 2 * b, y1 - y0 - 2 * b)
    if min(inner) > 2:
        img[y0 + b : y0 + b + inner[1], x0 + b : x0 + b + inner[0]] = cv2.resize(
            pic, inner, interpolation=cv2.INTER_AREA
        )


def crop(src: np.ndarray, aspect: float, rng: np.random.Generator) -> np.ndarray:
    h, w = src.shape[:2]
    ch = int(h * rng.uniform(0.5, 0.9))
    cw = min(w, int(ch * aspect))
    y, x = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
    return np.ascontiguousarray(src[y : y + ch, x : x + cw])


def wall(
    w_m: float, h_m: float, paint: tuple[int, int, int], rng: np.random.Generator, shared: dict[str, Any]
) -> np.ndarray:
    """A painted wall with a skirting board and a few things on it: a door, a window, framed photos
    (one of them the room's repeated poster), a whiteboard, switches. Mostly paint, on purpose."""
    h, w = canvas(w_m, h_m)
    img = plain_paint(h, w, paint, rng)
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
            pic = shared["poster"] if kind == "repeat" else crop(photo(str(rng.choice(PHOTOS))), 0.75, rng)
            pw = 0.6 if kind == "repeat" else rng.uniform(0.4, 0.8)
            ph = pw * pic.shape[0] / pic.shape[1]
            if x + pw < w_m:
                poster(img, x, rng.uniform(0.5, 1.0), pic, pw, ph)
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


def floor(w_m: float, h_m: float, rng: np.random.Generator) -> np.ndarray:
    """Tiles (a repeated grid), planks or carpet; sometimes a rug with a photo pattern."""
    h, w = canvas(w_m, h_m)
    kind = rng.integers(3)
    if kind == 0:  # tiles: the same square again and again, grout lines
        base = tuple(int(c) for c in rng.integers([150, 140, 120], [220, 210, 200]))
        img = plain_paint(h, w, base, rng, noise=4.0)
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
            img[y : y + step] = plain_paint(min(step, h - y), w, tuple(int(c) for c in tone), rng, noise=5.0)
            cv2.line(img, (0, y), (w, y), (50, 35, 25), 2)
            for x in range(int(rng.integers(0, _px(1.5))), w, _px(1.5)):
                cv2.line(img, (x, y), (x, min(h, y + step)), (50, 35, 25), 2)
    else:  # carpet: fine noise, no structure
        base = tuple(int(c) for c in rng.integers([70, 70, 70], [150, 140, 130]))
        img = plain_paint(h, w, base, rng, noise=9.0)
    if rng.random() < 0.6:  # a rug
        rw, rh = rng.uniform(1.2, 2.0), rng.uniform(0.8, 1.4)
        rx, ry = rng.uniform(0.5, max(0.6, w_m - rw - 0.5)), rng.uniform(0.5, max(0.6, h_m - rh - 0.5))
        rug = unique_texture(photo(str(rng.choice(FABRICS + PHOTOS))), 256, rng, shapes=20)
        poster(img, rx, ry, rug, rw, rh)
    return img


def ceiling(w_m: float, h_m: float, rng: np.random.Generator) -> np.ndarray:
    """Uniform white with a regular grid of light panels: nothing unique up there."""
    h, w = canvas(w_m, h_m)
    img = plain_paint(h, w, (240, 240, 238), rng, noise=1.5)
    step = rng.uniform(1.5, 2.2)
    for x in np.arange(step / 2, w_m - 0.5, step):
        for y in np.arange(step / 2, h_m - 0.5, step):
            cv2.rectangle(img, (_px(x), _px(y)), (_px(x + 0.6), _px(y + 0.6)), (255, 255, 252), -1)
            cv2.rectangle(img, (_px(x), _px(y)), (_px(x + 0.6), _px(y + 0.6)), (190, 190, 190), 2)
    return img


def front(kind: str, w_m: float, h_m: float, rng: np.random.Generator, shared: dict[str, Any]) -> np.ndarray:
    """A vertical furniture face: cupboard doors, shelves of books, fabric, or a textured object."""
    h, w = canvas(w_m, h_m)
    if kind == "cupboard":  # plain doors, identical handles: repeated, low texture
        paint = tuple(int(c) for c in shared["cupboard"])
        img = plain_paint(h, w, paint, rng)
        n = max(1, round(w_m / 0.5))
        for i in range(n):
            x0 = i * w // n
            cv2.rectangle(img, (x0 + 3, 3), (x0 + w // n - 3, h - 3), tuple(int(c * 0.7) for c in paint), 2)
            hx = x0 + (w // n - 12 if i % 2 == 0 else 12)
            cv2.rectangle(img, (hx - 3, h // 2 - _px(0.1)), (hx + 3, h // 2 + _px(0.1)), (90, 90, 95), -1)
        return img
    if kind == "shelf":  # shelves of books: the same few rows of spines repeat
        img = plain_paint(h, w, (110, 80, 55), rng)
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
        fabric = cv2.resize(crop(fabric, w_m / h_m, rng), (w, h), interpolation=cv2.INTER_AREA)
        tint = np.asarray(shared["sofa"], np.float32) / 255.0
        grey = fabric.astype(np.float32).mean(axis=2, keepdims=True)
        img = (0.75 * np.asarray(shared["sofa"], np.float32) + 0.25 * grey * tint * 1.5).clip(0, 255)
        return img.astype(np.uint8)
    if kind == "object":  # a textured thing (a painted crate, a printed box): matchable
        return unique_texture(photo(str(rng.choice(PHOTOS))), max(h, w), rng, shapes=15)[:h, :w].copy()
    # table sides: plain dark wood
    return plain_paint(h, w, tuple(int(c) for c in shared["table"]), rng)


def books(rng: np.random.Generator) -> list[np.ndarray]:
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
