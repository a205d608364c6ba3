"""One tile of the orthophoto.

Each output pixel is a ground position: its easting and northing from the grid, its height from
the DSM, and so its place in every photo. The choice of photo is made on a coarse lattice
(every ``COARSE`` pixels, fixed to the map's corner, so that every tile makes the same choices):
at each node the photo with the best score (sight.py: most nadir, nearest its centre, not
hidden by the DSM) wins. Each photo's share is its wins box-blurred over ``FEATHER`` nodes
(the seams between photos are feathered over about ``2 * FEATHER * COARSE`` pixels), held to
where it sees the ground, brought to the full resolution, and the pixel is the share-weighted
mean of the photos' colours times their exposure gains. A tile is computed with a halo as wide
as the blur, so tiles put together equal the map computed at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from .dsm import Dsm
from .grid import Grid
from .photos import PhotoCache, in_frame, to_pixels
from .sight import sees
from .survey import Survey, View

COARSE = 8  # pixels between the lattice's nodes
FEATHER = 3  # nodes each side of a seam
EDGE = 0.05  # of a photo's shorter side: its weight fades to nothing over this towards its edge


@dataclass(frozen=True)
class Mosaic:
    """What every tile reads."""

    survey: Survey
    dsm: Dsm
    grid: Grid  # the orthophoto's
    footprints: np.ndarray  # (P, 4) west, south, east, north of each view's ground
    gains: np.ndarray  # (P, 3)
    scales: np.ndarray  # (P,) working scale of each view's photo


def footprint(view: View, survey: Survey, dsm: Dsm, samples: int = 9) -> np.ndarray:
    """The box (west, south, east, north) holding where the photo's border rays meet the
    heights between the DSM's lowest and highest (rays that do not go down reach 10x the
    camera's height over the lowest)."""
    w, h = view.width, view.height
    s = np.linspace(0, 1, samples)
    border = np.concatenate(
        [
            np.column_stack([s * w, np.zeros(samples)]),
            np.column_stack([s * w, np.full(samples, h)]),
            np.column_stack([np.zeros(samples), s * h]),
            np.column_stack([np.full(samples, w), s * h]),
        ]
    )
    rays_cam = np.column_stack([view.camera.cam_from_img(border), np.ones(len(border))])
    rays = rays_cam @ view.R  # R^T applied to each row: world directions
    centre = -view.R.T @ view.t
    lo, hi = float(np.min(dsm.height)), float(np.max(dsm.height))
    # the model's heights of the lowest and highest ground below the camera
    ce = view.centre
    zs = survey.model_from_projected(np.array([[ce[0], ce[1], lo], [ce[0], ce[1], hi]]))[:, 2]
    pts = []
    reach = 10.0 * max(centre[2] - zs[0], 1.0)
    for z in zs:
        down = rays[:, 2] < -1e-6
        t = np.where(down, (z - centre[2]) / np.where(down, rays[:, 2], -1.0), np.inf)
        t = np.minimum(np.maximum(t, 0.0), reach / np.linalg.norm(rays, axis=1))
        pts.append(centre + t[:, None] * rays)
    proj = survey.frame.to_projected(np.concatenate(pts))
    return np.array([proj[:, 0].min(), proj[:, 1].min(), proj[:, 0].max(), proj[:, 1].max()])


def candidates(mosaic: Mosaic, bounds: tuple[float, float, float, float]) -> list[int]:
    """Views whose footprint meets the box (west, south, east, north)."""
    w, s, e, n = bounds
    f = mosaic.footprints
    hit = (f[:, 0] <= e) & (f[:, 2] >= w) & (f[:, 1] <= n) & (f[:, 3] >= s)
    return [int(i) for i in np.flatnonzero(hit)]


def sample(img: np.ndarray, x: np.ndarray, y: np.ndarray, row: int = 1024) -> np.ndarray:
    """(N, 3) bilinear colours of ``img`` at columns ``x`` and rows ``y`` (cv2.remap, whose maps
    must stay under 32k a side: laid out ``row`` wide)."""
    n = len(x)
    rows = max(1, -(-n // row))
    mx = np.zeros(rows * row, np.float32)
    my = np.zeros(rows * row, np.float32)
    mx[:n], my[:n] = x, y
    out = cv2.remap(
        img, mx.reshape(rows, row), my.reshape(rows, row), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    return out.reshape(-1, img.shape[2])[:n].astype(np.float64)


def best_views(mosaic: Mosaic, e: np.ndarray, n: np.ndarray) -> tuple[list[int], np.ndarray, np.ndarray]:
    """For ground positions (flat arrays): the views that may see them (footprints), and for each
    its scores (K, N; inf where unseen) and whether it sees them (K, N)."""
    survey, dsm = mosaic.survey, mosaic.dsm
    z = dsm.at(e, n)
    xyz = survey.model_from_projected(np.column_stack([e, n, z]))
    cands = candidates(mosaic, (float(e.min()), float(n.min()), float(e.max()), float(n.max())))
    scores = np.full((len(cands), len(e)), np.inf, np.float32)
    seen = np.zeros((len(cands), len(e)), bool)
    for k, p in enumerate(cands):
        _, ok, sc = sees(survey.views[p], dsm, xyz, e, n, z)
        scores[k], seen[k] = sc, ok
    return cands, scores, seen


def labels(mosaic: Mosaic, step: int) -> np.ndarray:
    """The view each place of the map comes from (mostly: seams are blended), every ``step``
    pixels: (rows, cols) view indices, -1 where no photo sees it. For pictures of the seams."""
    e, n = mosaic.grid.centres(0, mosaic.grid.height, 0, mosaic.grid.width, step=step)
    cands, scores, seen = best_views(mosaic, e.ravel(), n.ravel())
    if not cands:
        return np.full(e.shape, -1)
    best = np.asarray(cands)[np.argmin(scores, axis=0)]
    mapped = seen.any(axis=0) & mosaic.dsm.inside(e.ravel(), n.ravel())
    return np.where(mapped, best, -1).reshape(e.shape)


def model_grid(survey: Survey, e: np.ndarray, n: np.ndarray, z: np.ndarray, step: int = 16) -> np.ndarray:
    """Model coordinates (h, w, 3) of a regular window of ground positions (``e``, ``n`` from
    Grid.centres, heights ``z``). A GCP model's frame is the map's CRS shifted: exact. A GPS
    model's (ENU) needs PROJ and the ellipsoid per position, the slowest part of a tile done per
    pixel, so it is done every ``step`` pixels at the window's median height and one metre above
    it, and the pixels are interpolated between the nodes and along the local vertical: the
    change of frame bends by millimetres over kilometres, nothing over a few metres."""
    h, w = e.shape
    if survey.frame.offset is not None or h < 2 or w < 2:
        return survey.model_from_projected(np.column_stack([e.ravel(), n.ravel(), z.ravel()])).reshape(
            h, w, 3
        )
    res_e, res_n = e[0, 1] - e[0, 0], n[1, 0] - n[0, 0]
    rows = np.arange(0, h - 1 + step, step, dtype=np.float64)
    cols = np.arange(0, w - 1 + step, step, dtype=np.float64)
    ne, nn = np.meshgrid(e[0, 0] + cols * res_e, n[0, 0] + rows * res_n)
    h0 = float(np.median(z))
    base = survey.model_from_projected(np.column_stack([ne.ravel(), nn.ravel(), np.full(ne.size, h0)]))
    above = survey.model_from_projected(np.column_stack([ne.ravel(), nn.ravel(), np.full(ne.size, h0 + 1.0)]))
    rr, cc = np.meshgrid(
        np.arange(h, dtype=np.float64) / step, np.arange(w, dtype=np.float64) / step, indexing="ij"
    )
    out = np.empty((h, w, 3))
    for k in range(3):
        a = ndimage.map_coordinates(base[:, k].reshape(ne.shape), [rr, cc], order=1)
        u = ndimage.map_coordinates((above[:, k] - base[:, k]).reshape(ne.shape), [rr, cc], order=1)
        out[..., k] = a + (z - h0) * u
    return out


def edge_ramp(view: View, uv: np.ndarray) -> np.ndarray:
    """A photo's weight near its frame: 1 inside, down to almost nothing at the edge over
    ``EDGE`` of its shorter side, so that where a photo ends inside a seam's blend its colour
    fades out instead of stopping at a straight line (a place only it sees keeps its colour:
    the weights are normalised)."""
    margin = np.minimum.reduce([uv[:, 0], uv[:, 1], view.width - uv[:, 0], view.height - uv[:, 1]])
    return np.clip(margin / (EDGE * min(view.width, view.height)), 1e-3, 1.0)


def render_tile(mosaic: Mosaic, photos: PhotoCache, row0: int, row1: int, col0: int, col1: int) -> np.ndarray:
    """The (row1 - row0, col1 - col0, 4) RGBA uint8 window of the orthophoto."""
    grid, dsm, survey = mosaic.grid, mosaic.dsm, mosaic.survey
    halo = (FEATHER + 1) * COARSE
    # the lattice nodes (global pixel indices, multiples of COARSE) around the window
    kr0, kr1 = math.floor((row0 - halo) / COARSE), math.ceil((row1 + halo) / COARSE) + 1
    kc0, kc1 = math.floor((col0 - halo) / COARSE), math.ceil((col1 + halo) / COARSE) + 1
    ce, cn = grid.centres(kr0 * COARSE, kr1 * COARSE, kc0 * COARSE, kc1 * COARSE, step=COARSE)
    # grid.centres adds half a pixel: a node is the centre of its pixel
    shape_c = ce.shape
    ce_f, cn_f = ce.ravel(), cn.ravel()
    cands, flat_scores, flat_seen = best_views(mosaic, ce_f, cn_f)
    out = np.zeros((row1 - row0, col1 - col0, 4), np.uint8)
    if not cands:
        return out
    scores = flat_scores.reshape(len(cands), *shape_c)
    seen = flat_seen.reshape(len(cands), *shape_c)
    best = np.argmin(scores, axis=0)
    any_seen = seen.any(axis=0)
    size = 2 * FEATHER + 1

    # full-resolution positions of the window
    e, n = grid.centres(row0, row1, col0, col1)
    h, w = e.shape
    e_f, n_f = e.ravel(), n.ravel()
    z = dsm.at(e_f, n_f)
    xyz = model_grid(survey, e, n, z.reshape(h, w)).reshape(-1, 3)
    # where each full pixel falls on the lattice (node (i, j) is pixel (kr0 + i, kc0 + j) * COARSE)
    rr = (np.arange(row0, row1, dtype=np.float32) / COARSE - kr0).astype(np.float32)
    cc = (np.arange(col0, col1, dtype=np.float32) / COARSE - kc0).astype(np.float32)
    map_x, map_y = np.meshgrid(cc, rr)

    acc = np.zeros((h * w, 3), np.float64)
    wsum = np.zeros(h * w, np.float64)
    for k, p in enumerate(cands):
        wins = ((best == k) & any_seen).astype(np.float32)
        if not wins.any():
            continue
        share = cv2.blur(wins, (size, size), borderType=cv2.BORDER_REPLICATE) * seen[k]
        full = cv2.remap(share, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).ravel()
        idx = np.flatnonzero(full > 1e-3)
        if idx.size == 0:
            continue
        view = survey.views[p]
        uv, depth = view.project(xyz[idx])
        ok = in_frame(view, uv, depth)
        idx, uv = idx[ok], uv[ok]
        if idx.size == 0:
            continue
        img = photos.get(view, float(mosaic.scales[p]))
        x, y = to_pixels(view, img, uv)
        colour = sample(img, x, y)
        wk = full[idx].astype(np.float64) * edge_ramp(view, uv)
        acc[idx] += wk[:, None] * colour * mosaic.gains[p][None]
        wsum[idx] += wk
    has = wsum > 0
    rgb = np.zeros((h * w, 3))
    rgb[has] = acc[has] / wsum[has, None]
    alpha = has & dsm.inside(e_f, n_f)
    out[..., :3] = np.clip(np.rint(rgb), 0, 255).astype(np.uint8).reshape(h, w, 3) * alpha.reshape(h, w, 1)
    out[..., 3] = np.where(alpha, 255, 0).astype(np.uint8).reshape(h, w)
    return out
