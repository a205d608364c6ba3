"""A synthetic indoor room: its geometry (a box seen from inside, furniture boxes on the floor),
its lights, the cameras a hand-held scanner would take, and its renders.

Rendered by ray casting like the outdoor scenes of :mod:`geomatch.synth.aerial`: nearest hit per
ray, supersampled colour, depth (camera z) cast at the exact pixel centres. The shading is
view-independent Lambertian light from the ceiling lights, so the ground truth stays exact.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from . import roomtex
from .camera import Camera, look_at
from .texture import sample_texture


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
        poster = roomtex.crop(roomtex.photo(str(rng.choice(roomtex.PHOTOS))), 0.75, rng)
        shared = {
            "poster": poster,
            "cupboard": rng.integers([180, 170, 150], [245, 240, 230]),
            "sofa": rng.integers([60, 50, 50], [170, 150, 150]),
            "table": rng.integers([80, 55, 35], [150, 110, 80]),
            "books": roomtex.books(rng),
        }
        paint = roomtex.PAINTS[int(rng.integers(len(roomtex.PAINTS)))]
        walls = [
            roomtex.wall(W, H, paint, rng, shared),  # -x wall (u = y)
            roomtex.wall(W, H, paint, rng, shared),
            roomtex.wall(L, H, paint, rng, shared),  # -y wall (u = x)
            roomtex.wall(L, H, paint, rng, shared),
        ]
        self.items = [
            Item(
                np.zeros(3),
                self.size.copy(),
                (*walls, roomtex.floor(L, W, rng), roomtex.ceiling(L, W, rng)),
                True,
            )
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
                        top = roomtex.plain_paint(*roomtex.canvas(size[u], size[v]), shared["table"], rng)
                        if kind == "table":  # papers, a laptop, a mug: a few textured things
                            for _ in range(int(rng.integers(2, 5))):
                                pw = rng.uniform(0.2, 0.4)
                                roomtex.poster(
                                    top,
                                    rng.uniform(0, max(0.01, size[u] - pw)),
                                    rng.uniform(0, max(0.01, size[v] - pw)),
                                    roomtex.crop(roomtex.photo(str(rng.choice(roomtex.PHOTOS))), 1.0, rng),
                                    pw,
                                    pw * 0.75,
                                )
                        faces.append(top)
                    elif f == 4:
                        faces.append(np.zeros((2, 2, 3), np.uint8))
                    else:
                        faces.append(roomtex.front(kind, size[u], size[v], rng, shared))
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
            uu = (q[:, u_ax] - item.lo[u_ax]) * roomtex.PPM
            vv = (item.hi[v_ax] - q[:, v_ax]) * roomtex.PPM
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
