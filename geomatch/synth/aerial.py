"""Synthetic air-to-ground scenes with ground truth, rendered by ray casting.

A textured ground plane (z = 0, z up, metres) carries several textured axis-aligned boxes
("buildings"); textures are photos shipped by scikit-image, tiled so that every part of the
scene looks different (synth.texture). Aerial cameras fly high (nadir and oblique); ground cameras
stand 1.5-2 m above the ground on a ring around the scene, looking near-horizontally at its centre.
Every pixel is a real perspective ray intersected with the plane and the boxes (nearest hit wins,
i.e. a depth test), rendered at 2x and area-downsampled against aliasing.

Output of :func:`write_scene`: ``images/`` (PNG), ``gt/`` (COLMAP text model: cameras.txt,
images.txt, empty points3D.txt; synth.groundtruth) and ``aerial.txt`` (the aerial image names, one
per line). With ``gps_noise`` (metres) every image also carries an EXIF GPS fix and the aerial
images a DJI relative altitude, drawn as synth.sensors describes (the scene's metres are
East-North-Up around its GPS_ORIGIN, so ``gt/`` is already in that ENU frame); ``gt/gps.json``
keeps the origin, both sigmas, every image's true and noisy ENU position and the noisy heights.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .camera import Camera, look_at
from .groundtruth import write_gps_truth, write_gt
from .photos import photo
from .sensors import BARO_NOISE_M, baro_heights, gps_fixes, save_png
from .texture import SKY, TEXTURES, patches, sample_texture, scribble, unique_texture


@dataclass(frozen=True)
class Box:
    lo: np.ndarray  # (3,) min corner
    hi: np.ndarray  # (3,) max corner
    textures: tuple[int, ...]  # texture index per face: -x, +x, -y, +y, -z, +z


class Scene:
    def __init__(self, seed: int, extent: float = 24.0, n_boxes: int = 6) -> None:
        rng = np.random.default_rng(seed)
        self.rng = rng
        self.extent = extent
        self.site = 0.3 * extent  # box centres within +-site metres of the origin
        self.textures: list[np.ndarray] = []
        # every surface gets its own patch: photos are cut into disjoint 3x3 patches and each patch is
        # used once, so no two places in the scene share content (repeats fold SfM reconstructions)
        pool = [p for name in TEXTURES for p in patches(photo(name), 3)]
        order = iter(rng.permutation(len(pool)))
        tiles_per_side = 6
        tile_px = 256
        mosaic = np.zeros((tiles_per_side * tile_px, tiles_per_side * tile_px, 3), np.uint8)
        for i in range(tiles_per_side):
            for j in range(tiles_per_side):
                mosaic[i * tile_px : (i + 1) * tile_px, j * tile_px : (j + 1) * tile_px] = unique_texture(
                    pool[next(order)], tile_px, rng, shapes=0
                )
        scribble(mosaic, rng, 900, max_radius=20)  # marks over tile borders too
        self.ground = mosaic.astype(np.float32)
        self.ground_m_per_px = 2 * extent / mosaic.shape[0]
        self.boxes: list[Box] = []
        # a compact block of buildings (the site a drone and a walker both photograph); the
        # cameras stand outside it, so no wall is closer to a ground camera than a few metres
        tries = 0
        while len(self.boxes) < n_boxes and tries < 10_000:
            tries += 1
            c = rng.uniform(-self.site, self.site, 2)
            size = rng.uniform(2.5, 4.5, 2)
            height = rng.uniform(3.0, 8.0)
            lo = np.array([c[0] - size[0] / 2, c[1] - size[1] / 2, 0.0])
            hi = np.array([c[0] + size[0] / 2, c[1] + size[1] / 2, height])
            if any(np.all(lo[:2] < b.hi[:2] + 1.5) and np.all(b.lo[:2] - 1.5 < hi[:2]) for b in self.boxes):
                continue
            faces = []
            for _ in range(6):  # every face its own texture: repeated surfaces fool SfM
                faces.append(len(self.textures))
                self.textures.append(unique_texture(pool[next(order)], 384, rng).astype(np.float32))
            self.boxes.append(Box(lo, hi, tuple(faces)))

    # -- cameras -------------------------------------------------------------------------
    def cameras(self, n_aerial: int, n_ground: int, width: int, height: int) -> list[Camera]:
        """Ground cameras walk around the site; the drone flies the same arc.

        Ground: 1.5-2 m high, 20-23 m from the centre, 30 degrees apart (the whole ring from 12
        cameras on), looking near-horizontally at the buildings. Aerial, cycling through three
        kinds so that every kind appears from 3 images on: a low oblique (30-40 degrees below the
        horizon, 21-25 m from the centre, 11-17 m up: the view that sees the walls the ground
        cameras see, at about twice their distance, which tiling makes up for), a steep oblique
        (55-65 degrees, 26-32 m) and a nadir view from 30-40 m. Obliques spread over the
        walked arc; the nadir view is headed along it, as a drone flies its survey line.
        """
        rng = self.rng
        f = 0.9 * width
        K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
        step = min(2 * np.pi / max(n_ground, 1), np.pi / 6)
        arc = step * max(n_ground - 1, 0)
        heading = arc / 2  # azimuth of the middle of the walked arc
        n_oblique = sum(i % 3 != 2 for i in range(n_aerial))
        azimuths = iter(np.linspace(0.0, arc, n_oblique) if n_oblique > 1 else np.array([heading]))
        cams = []
        for i in range(n_aerial):
            target = np.array([*rng.uniform(-2, 2, 2), rng.uniform(0.0, 3.0)])
            if i % 3 == 2:  # nadir, jittered, image top towards the site from the walked side
                alt = rng.uniform(30, 40)
                C = np.array([*rng.uniform(-4, 4, 2), alt])
                away = np.array([np.cos(heading), np.sin(heading), 0.0])
                R, t = look_at(C, np.array([C[0], C[1], 0.0]), up=-away)
            else:
                low = i % 3 == 0
                elev = np.deg2rad(rng.uniform(30, 40) if low else rng.uniform(55, 65))
                dist = rng.uniform(21, 25) if low else rng.uniform(26, 32)
                ang = next(azimuths) + rng.uniform(-0.15, 0.15)
                C = target + dist * np.array(
                    [np.cos(elev) * np.cos(ang), np.cos(elev) * np.sin(ang), np.sin(elev)]
                )
                R, t = look_at(C, target)
            cams.append(Camera(f"aerial_{i:02d}.png", K, R, t, width, height, True))
        for i in range(n_ground):
            ang = step * i + rng.uniform(-0.1, 0.1)
            radius = rng.uniform(20, 23)
            C = np.array([radius * np.cos(ang), radius * np.sin(ang), rng.uniform(1.5, 2.0)])
            target = np.array([*rng.uniform(-2.5, 2.5, 2), rng.uniform(1.5, 3.0)])
            R, t = look_at(C, target)
            cams.append(Camera(f"ground_{i:02d}.png", K, R, t, width, height, False))
        return cams

    # -- rendering -----------------------------------------------------------------------
    def render(self, cam: Camera, supersample: int = 2) -> tuple[np.ndarray, np.ndarray]:
        """RGB uint8 image and per-pixel depth (z in the camera, inf for sky)."""
        s = supersample
        w, h = cam.width * s, cam.height * s
        u, v = np.meshgrid((np.arange(w) + 0.5) / s, (np.arange(h) + 0.5) / s)
        pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1)
        dirs = (pix @ np.linalg.inv(cam.K).T) @ cam.R  # world directions, z_cam = 1
        origin = cam.centre
        t_best = np.full(len(dirs), np.inf)
        colour = np.tile(SKY, (len(dirs), 1))
        # ground plane
        with np.errstate(divide="ignore", invalid="ignore"):
            tg = -origin[2] / dirs[:, 2]
        hit = (tg > 0) & np.isfinite(tg)
        P = origin + tg[hit, None] * dirs[hit]
        inside = (np.abs(P[:, 0]) < self.extent) & (np.abs(P[:, 1]) < self.extent)
        idx = np.flatnonzero(hit)[inside]
        t_best[idx] = tg[idx]
        colour[idx] = sample_texture(
            self.ground,
            (P[inside, 0] + self.extent) / self.ground_m_per_px,
            (self.extent - P[inside, 1]) / self.ground_m_per_px,
        )
        for box in self.boxes:
            self._hit_box(box, origin, dirs, t_best, colour)
        img = colour.reshape(h, w, 3)
        depth = t_best.reshape(h, w)  # ray parameter with z_cam = 1 is the depth
        if s > 1:
            img = cv2.resize(img.astype(np.float32), (cam.width, cam.height), interpolation=cv2.INTER_AREA)
            depth = depth[s // 2 :: s, s // 2 :: s]
        return np.clip(img, 0, 255).astype(np.uint8), depth

    def hidden(self, origin: np.ndarray, X: np.ndarray, depth: float) -> bool:
        """Whether a building stands between a camera at ``origin`` and the world point ``X`` at
        ``depth`` along the camera's axis (the ray parameter :meth:`render` uses)."""
        d = (X - origin) / depth
        t_best = np.array([depth * (1.0 - 1e-6)])
        for box in self.boxes:
            self._hit_box(box, origin, d[None], t_best, np.zeros((1, 3)))
        return bool(t_best[0] < depth * (1.0 - 1e-6))

    def _hit_box(
        self, box: Box, o: np.ndarray, d: np.ndarray, t_best: np.ndarray, colour: np.ndarray
    ) -> None:
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d
            t0 = (box.lo - o) * inv
            t1 = (box.hi - o) * inv
        tmin = np.minimum(t0, t1)
        tmax = np.maximum(t0, t1)
        t_enter = np.nanmax(tmin, axis=1)
        t_exit = np.nanmin(tmax, axis=1)
        hit = (t_enter <= t_exit) & (t_enter > 0) & (t_enter < t_best)
        if not hit.any():
            return
        idx = np.flatnonzero(hit)
        axis = np.nanargmax(tmin[idx], axis=1)
        P = o + t_enter[idx, None] * d[idx]
        t_best[idx] = t_enter[idx]
        size = box.hi - box.lo
        for a in range(3):
            sel = axis == a
            if not sel.any():
                continue
            positive = d[idx[sel], a] < 0  # ray travelling towards -a hits the +a face
            u_axis, v_axis = [(1, 2), (0, 2), (0, 1)][a]
            for sign in (False, True):
                m = positive == sign
                if not m.any():
                    continue
                face = 2 * a + int(sign)
                tex = self.textures[box.textures[face]]
                q = P[sel][m]
                # 1 texture image spans the face's longer side
                span = max(size[u_axis], size[v_axis])
                uu = (q[:, u_axis] - box.lo[u_axis]) / span * (tex.shape[1] - 1)
                vv = (box.hi[v_axis] - q[:, v_axis]) / span * (tex.shape[0] - 1)
                colour[idx[np.flatnonzero(sel)[m]]] = sample_texture(tex, uu, vv)


def write_scene(
    out: str | Path,
    n_aerial: int = 8,
    n_ground: int = 12,
    seed: int = 0,
    size: tuple[int, int] = (640, 480),
    gps_noise: float | None = None,
    gps_names: set[str] | None = None,
    baro_noise: float | None = None,
) -> list[Camera]:
    """Render a scene into ``out`` (images/, gt/, aerial.txt) and return its cameras; ``size``:
    the photos' (width, height). ``gps_noise``: write GPS fixes with that sigma (metres), and
    relative altitudes with ``baro_noise`` (None: BARO_NOISE_M); ``gps_names``: fixes only into
    these images (a mixed project), all when None."""
    baro_noise = BARO_NOISE_M if baro_noise is None else baro_noise
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    scene = Scene(seed)
    cams = scene.cameras(n_aerial, n_ground, *size)
    fixes = gps_fixes(cams, gps_noise, seed) if gps_noise is not None else {}
    heights = baro_heights(cams, baro_noise, seed) if gps_noise is not None else {}
    if gps_names is not None:
        fixes = {n: v for n, v in fixes.items() if n in gps_names}
    for c in cams:
        img, _ = scene.render(c)
        save_png(out / "images" / c.name, img, c, fixes.get(c.name), heights.get(c.name))
    write_gt(cams, out / "gt")
    if gps_noise is not None:
        write_gps_truth(out / "gt", cams, fixes, gps_noise, heights, baro_noise)
    (out / "aerial.txt").write_text("".join(f"{c.name}\n" for c in cams if c.aerial))
    return cams


def covisibility(scene: Scene, cams: list[Camera], stride: int = 8, scale: float = 0.25) -> np.ndarray:
    """(N, N) fraction of camera i's pixels (on a ``stride`` grid of a ``scale``-sized render)
    that camera j sees unoccluded: the ground truth for pair recall."""
    small = [
        Camera(
            c.name,
            np.diag([scale, scale, 1.0]) @ c.K,
            c.R,
            c.t,
            max(1, round(c.width * scale)),
            max(1, round(c.height * scale)),
            c.aerial,
        )
        for c in cams
    ]
    depths = [scene.render(c, supersample=1)[1] for c in small]
    n = len(cams)
    out = np.eye(n)
    for i, a in enumerate(small):
        v, u = np.mgrid[0 : a.height : max(1, stride // 4), 0 : a.width : max(1, stride // 4)]
        d = depths[i][v, u]
        ok = np.isfinite(d)
        pix = np.stack([u[ok] + 0.5, v[ok] + 0.5, np.ones(ok.sum())], 1)
        X = (pix @ np.linalg.inv(a.K).T * d[ok, None] - a.t) @ a.R
        for j, b in enumerate(small):
            if i == j:
                continue
            uv, z = b.project(X)
            ub, vb = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
            inside = (z > 0) & (ub >= 0) & (ub < b.width) & (vb >= 0) & (vb < b.height)
            vis = inside.copy()
            vis[inside] = np.abs(depths[j][vb[inside], ub[inside]] - z[inside]) < 0.02 * z[inside]
            out[i, j] = vis.sum() / max(v.size, 1)
    return out
