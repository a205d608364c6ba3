"""Synthetic air-to-ground scenes with ground truth, rendered by ray casting.

A textured ground plane (z = 0, z up, metres) carries several textured axis-aligned boxes
("buildings"); textures are photos shipped by scikit-image, tiled so that every part of the
scene looks different. Aerial cameras fly high (nadir and oblique); ground cameras stand 1.5-2 m
above the ground on a ring around the scene, looking near-horizontally at its centre. Every pixel
is a real perspective ray intersected with the plane and the boxes (nearest hit wins, i.e. a
depth test), rendered at 2x and area-downsampled against aliasing.

Output of :func:`write_scene`: ``images/`` (PNG), ``gt/`` (COLMAP text model: cameras.txt,
images.txt, empty points3D.txt; poses are cam_from_world as COLMAP stores them) and
``aerial.txt`` (the aerial image names, one per line). With ``gps_noise`` (metres) every image
also carries an EXIF GPS fix: the scene's metres are East-North-Up around :data:`GPS_ORIGIN`
(so ``gt/`` is already in that ENU frame), each camera centre is perturbed by N(0, sigma) east and
north and N(0, 1.5 sigma) up (consumer GNSS is worse vertically) and converted to WGS84, and
the aerial images' DJI relative altitude (a barometer's height above take-off, exact without GPS)
gets its own N(0, ``baro_noise``); ``gt/gps.json`` keeps the origin, both sigmas, every image's
true and noisy ENU position and the noisy heights.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image
from PIL.PngImagePlugin import PngInfo

from ..geo.geodesy import EnuFrame
from ..metadata import ImageMeta, dji_xmp, exif_for, gps_exif, up_in_camera
from .photos import photo

TEXTURES = (
    "astronaut",
    "coffee",
    "rocket",
    "chelsea",
    "immunohistochemistry",
    "hubble_deep_field",
    "retina",
    "motorcycle_left",
    "camera",
    "brick",
    "gravel",
    "coins",
    "clock",
    "cell",
    "moon",
    "grass",
    "logo",
)
SKY = np.array([200.0, 215.0, 235.0])
GPS_ORIGIN = EnuFrame(47.3769, 8.5417, 408.0)  # Zurich; the scene's (0, 0, 0), ellipsoidal height
GPS_VERTICAL_FACTOR = 1.5  # vertical GNSS noise over horizontal
# a DJI barometer's relative altitude over one short flight: decimetres (per image, independent)
BARO_NOISE_M = 0.3


def scribble(img: np.ndarray, rng: np.random.Generator, n: int, max_radius: int | None = None) -> None:
    """Random coloured shapes drawn in place: unique, corner-rich marks at every scale."""
    h, w = img.shape[:2]
    max_radius = max_radius or w // 24
    for _ in range(n):
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        r = int(rng.integers(3, max(4, max_radius)))
        kind = rng.integers(3)
        if kind == 0:
            cv2.circle(img, (x, y), r, colour, -1 if rng.random() < 0.6 else 2, cv2.LINE_AA)
        elif kind == 1:
            cv2.rectangle(img, (x, y), (x + r, y + int(rng.integers(3, 2 * r + 4))), colour, -1)
        else:
            pts = (np.array([x, y]) + rng.integers(-2 * r, 2 * r + 1, (3, 2))).astype(np.int32)
            cv2.polylines(img, [pts], False, colour, int(rng.integers(1, 4)), cv2.LINE_AA)


def _patches(img: np.ndarray, n: int) -> list[np.ndarray]:
    h, w = img.shape[:2]
    return [
        img[i * h // n : (i + 1) * h // n, j * w // n : (j + 1) * w // n] for i in range(n) for j in range(n)
    ]


def unique_texture(src: np.ndarray, size: int, rng: np.random.Generator, shapes: int = 60) -> np.ndarray:
    """A photo patch, colour-shifted and marked with random shapes."""
    img = cv2.resize(src, (size, size), interpolation=cv2.INTER_CUBIC)
    gain = rng.uniform(0.7, 1.2, 3)
    img = np.clip(img.astype(np.float32) * gain + rng.uniform(-25, 25, 3), 0, 255).astype(np.uint8)
    img = np.ascontiguousarray(img)
    scribble(img, rng, shapes)
    return img


@dataclass(frozen=True)
class Camera:
    name: str
    K: np.ndarray  # 3x3
    R: np.ndarray  # cam_from_world rotation (COLMAP: x right, y down, z forward)
    t: np.ndarray  # cam_from_world translation
    width: int
    height: int
    aerial: bool

    @property
    def centre(self) -> np.ndarray:
        return -self.R.T @ self.t

    def project(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (pixel centres at integers) and depths of world points (N, 3)."""
        Xc = X @ self.R.T + self.t
        uv = Xc @ self.K.T
        return uv[:, :2] / uv[:, 2:3] - 0.5, Xc[:, 2]


@dataclass(frozen=True)
class Box:
    lo: np.ndarray  # (3,) min corner
    hi: np.ndarray  # (3,) max corner
    textures: tuple[int, ...]  # texture index per face: -x, +x, -y, +y, -z, +z


def look_at(
    centre: np.ndarray, target: np.ndarray, up: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world looking from ``centre`` at ``target``; ``up`` is the world direction that
    appears upwards in the image (default: +z, or +y when looking straight down)."""
    f = target - centre
    f = f / np.linalg.norm(f)
    if up is None:
        up = np.array([0.0, 0.0, 1.0]) if abs(f[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    R = np.stack([r, d, f])
    return R, -R @ centre


class Scene:
    def __init__(self, seed: int, extent: float = 24.0, n_boxes: int = 6) -> None:
        rng = np.random.default_rng(seed)
        self.rng = rng
        self.extent = extent
        self.site = 0.3 * extent  # box centres within +-site metres of the origin
        self.textures: list[np.ndarray] = []
        # every surface gets its own patch: photos are cut into disjoint 3x3 patches and each patch is
        # used once, so no two places in the scene share content (repeats fold SfM reconstructions)
        pool = [p for name in TEXTURES for p in _patches(photo(name), 3)]
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


def sample_texture(
    tex: np.ndarray, x: np.ndarray, y: np.ndarray, border: int = cv2.BORDER_REFLECT
) -> np.ndarray:
    """Bilinear texture lookups at (x, y) texel coordinates; cv2.remap wants a 2-D map under 32767
    a side, so the points are laid out in rows of 4096."""
    n = x.size
    cols = 4096
    rows = -(-n // cols)
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n], my[:n] = x, y
    out = cv2.remap(tex, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR, borderMode=border)
    return out.reshape(-1, 3)[:n]


def rotmat_to_qvec(R: np.ndarray) -> np.ndarray:
    """Hamilton quaternion (w, x, y, z), COLMAP's convention."""
    K = (
        np.array(
            [
                [R[0, 0] - R[1, 1] - R[2, 2], 0, 0, 0],
                [R[1, 0] + R[0, 1], R[1, 1] - R[0, 0] - R[2, 2], 0, 0],
                [R[2, 0] + R[0, 2], R[2, 1] + R[1, 2], R[2, 2] - R[0, 0] - R[1, 1], 0],
                [R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], R[0, 0] + R[1, 1] + R[2, 2]],
            ]
        )
        / 3.0
    )
    vals, vecs = np.linalg.eigh(K)
    q = vecs[[3, 0, 1, 2], np.argmax(vals)]
    return q if q[0] >= 0 else -q


def write_gt(cams: list[Camera], gt: Path) -> None:
    gt.mkdir(parents=True, exist_ok=True)
    with open(gt / "cameras.txt", "w") as f:
        f.write("# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        for i, c in enumerate(cams, 1):
            fx, fy, cx, cy = c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2]
            f.write(f"{i} PINHOLE {c.width} {c.height} {fx:.10g} {fy:.10g} {cx:.10g} {cy:.10g}\n")
    with open(gt / "images.txt", "w") as f:
        f.write(
            "# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n# POINTS2D[] as (X, Y, POINT3D_ID)\n"
        )
        for i, c in enumerate(cams, 1):
            q = rotmat_to_qvec(c.R)
            vals = " ".join(f"{v:.12g}" for v in (*q, *c.t))
            f.write(f"{i} {vals} {i} {c.name}\n\n")
    (gt / "points3D.txt").write_text("# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]\n")


def gimbal_angles(R: np.ndarray) -> tuple[float, float, float]:
    """DJI's gimbal pitch, yaw and roll (degrees) of a camera ``R`` (world -> camera, world ENU,
    camera x right, y down, z forward). Pitch: the optical axis above the horizon (-90 nadir).
    Yaw: clockwise from north, of the image's top-forward direction (the optical axis for a
    level view, the image top for a nadir one: where the drone heads). Roll: positive when the
    image's right side is down. metadata.gimbal_rotation is the inverse."""
    pitch = float(np.degrees(np.arcsin(np.clip(R[2, 2], -1, 1))))
    heading = R[2, :2] - R[1, :2]  # forward minus down, horizontal: the heading at any pitch
    yaw = float(np.degrees(np.arctan2(heading[0], heading[1])))
    roll = float(np.degrees(np.arctan2(-R[0, 2], -R[1, 2]))) if abs(R[2, 2]) < 0.999 else 0.0
    return pitch, yaw, roll


def xmp_ups(cams: list[Camera]) -> dict[str, np.ndarray]:
    """The world's up in each aerial camera as ``geomatch run`` reads it from the XMP this module
    writes (gimbal angles to the XMP's 0.1 deg, through metadata.up_in_camera): the gravity
    benchmarks and tests georeference with, without rendering a scene."""
    out = {}
    for c in cams:
        if c.aerial:
            pitch, yaw, roll = (round(a, 1) for a in gimbal_angles(c.R))
            up = up_in_camera(
                ImageMeta(1, 1, gimbal_pitch_deg=pitch, gimbal_yaw_deg=yaw, gimbal_roll_deg=roll)
            )
            if up is not None:
                out[c.name] = up
    return out


def save_png(
    path: Path,
    image: np.ndarray,
    cam: Camera,
    gps_enu: np.ndarray | None = None,
    height: float | None = None,
) -> None:
    """PNG with the EXIF a camera would write (exact focal length, one device per capture type,
    the GPS fix at ``gps_enu`` metres in :data:`GPS_ORIGIN`'s frame when given) and, for aerial
    images, the DJI XMP a drone would (relative altitude, ``height`` or the true one, gimbal
    pitch, yaw and roll)."""
    info = PngInfo()
    if cam.aerial:
        h = float(cam.centre[2]) if height is None else height
        info.add_itxt("XML:com.adobe.xmp", dji_xmp(h, *gimbal_angles(cam.R)))
    model = "synth-drone" if cam.aerial else "synth-handheld"
    exif = exif_for("geomatch", model, float(cam.K[0, 0]) / 100.0, 100.0)
    if gps_enu is not None:
        lat, lon, alt = GPS_ORIGIN.to_geodetic(np.asarray(gps_enu, np.float64))
        gps_exif(exif, float(lat), float(lon), float(alt))
    Image.fromarray(image).save(path, exif=exif.tobytes(), pnginfo=info)


def gps_fixes(cams: list[Camera], sigma: float, seed: int) -> dict[str, np.ndarray]:
    """Noisy ENU positions of the camera centres. A generator of its own (not the scene's), so
    that asking for GPS leaves the scene and its renders bit-identical."""
    rng = np.random.default_rng([seed, 0x675])
    scale = np.array([sigma, sigma, GPS_VERTICAL_FACTOR * sigma])
    return {c.name: c.centre + rng.normal(0.0, 1.0, 3) * scale for c in cams}


def baro_heights(cams: list[Camera], sigma: float, seed: int) -> dict[str, float]:
    """Noisy relative altitudes of the aerial cameras (take-off at the ground, z = 0), from a
    generator of their own: adding them leaves the GPS draws as they were."""
    rng = np.random.default_rng([seed, 0xBA0])
    return {c.name: float(c.centre[2] + rng.normal(0.0, sigma)) for c in cams if c.aerial}


def write_gps_truth(
    gt: Path,
    cams: list[Camera],
    fixes: dict[str, np.ndarray],
    gps_noise: float,
    heights: dict[str, float],
    baro_noise: float,
) -> None:
    """``gt/gps.json``: the cameras' true ENU centres beside the fixes and relative altitudes
    written into their EXIF/XMP, with the noise they were drawn with."""
    (gt / "gps.json").write_text(
        json.dumps(
            {
                "origin": GPS_ORIGIN.as_dict(),
                "frame": "ENU",
                "sigma_m": gps_noise,
                "vertical_factor": GPS_VERTICAL_FACTOR,
                "true_enu": {c.name: c.centre.tolist() for c in cams},
                "gps_enu": {n: v.tolist() for n, v in fixes.items()},
                "baro_sigma_m": baro_noise,
                "relative_altitude": heights,
            },
            indent=1,
        )
        + "\n"
    )


def write_scene(
    out: str | Path,
    n_aerial: int = 8,
    n_ground: int = 12,
    seed: int = 0,
    width: int = 640,
    height: int = 480,
    gps_noise: float | None = None,
    gps_names: set[str] | None = None,
    baro_noise: float | None = None,
) -> list[Camera]:
    """Render a scene into ``out`` (images/, gt/, aerial.txt) and return its cameras.
    ``gps_noise``: write GPS fixes with that sigma (metres), and relative altitudes with
    ``baro_noise`` (None: BARO_NOISE_M); ``gps_names``: fixes only into these images (a mixed
    project), all when None."""
    baro_noise = BARO_NOISE_M if baro_noise is None else baro_noise
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    scene = Scene(seed)
    cams = scene.cameras(n_aerial, n_ground, width, height)
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
