"""Each track's observations aligned on the original photos before mapping.

Why: the matcher places its points at the network's input size (640 px by default), so on a
1536 px photo a point is known to a network pixel, 2.4 photo pixels; SIFT detects at the photo's own
size and places its points more precisely, and camera errors follow the points. Refining each pair
on its own would give one keypoint a different position in each of its pairs, while COLMAP links
observations into tracks by keypoint: so the refinement is per track. A track is a connected set of
keypoints joined by the verified inlier matches that reach the mapper; its reference observation
(the one matched to most others of the track) stays where it is, and every observation matched
directly to the reference moves to where the reference's patch lands in its photo: least-squares
matching (features/subpixel.py) at the photo's own resolution, each warp started from the affine map
of that pair's other matches around the point. A keypoint belongs to one track, so it moves once and
keeps one position in all of its pairs. Where a track holds two keypoints of one photo (scene points
chained by a wrong match) those keypoints stay where they are; the track's other photos are aligned.

Two observations of one point found at 640 px can be several photo pixels apart on a 2000 px photo
(a network pixel is about three of them), beyond what a Gauss-Newton alignment on lightly smoothed
photos reaches: a first alignment on the photos at half size brings them within its reach. A point
is kept where it converged within ``max_shift`` of where it started with a correlation of
``min_ncc`` or more; elsewhere it keeps the network's placing.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pycolmap
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..features.subpixel import SubpixelOptions, gradient_maps, refine_on_maps
from ..imageio import WORKING_SIDE, read_gray
from ..memory import ByteLRU
from . import pair_threads
from .colmapdb import COLMAP_OFFSET

UNUSABLE = (pycolmap.TwoViewGeometryConfiguration.UNDEFINED, pycolmap.TwoViewGeometryConfiguration.DEGENERATE)


@dataclass(frozen=True)
class TrackRefineOptions:
    radius: int = 12  # patch half-size in photo pixels
    sigma: float = 1.0  # Gaussian pre-smoothing, photo pixels
    max_shift: float = 2.5  # photo pixels a point may move; farther means it converged elsewhere
    min_ncc: float = 0.9
    iterations: int = 15  # Gauss-Newton steps a pass at most
    # a first alignment on the photos at half size, smoothed this much more (photo pixels; 0: no
    # such pass), brings points from up to coarse_max_shift into the fine one's reach; they are then
    # accepted by the fine alignment's NCC and max_shift counted from where the coarse one left them
    coarse_sigma: float = 0.0
    coarse_max_shift: float = 8.0
    coarse_min_ncc: float = 0.5
    neighbour_radius: float = 100.0  # photo pixels: the scale of the neighbours' weights
    max_track: int = 64  # observations; a larger component is several scene points chained together
    images_mb: float = 512.0  # decoded photos held at once
    # photos with a longer side beyond this are aligned at this size (photo pixels above are
    # working pixels then): the matcher finds its points at the network's 640 px, so at 2000 a
    # point is already placed to a fraction of a network pixel, and a 12 MP original costs four
    # times the decoding, smoothing and memory of its half-size copy for no gain in the cameras
    # (docs/benchmarks.md, "Drone surveys beside COLMAP SIFT")
    max_side: int | None = WORKING_SIDE
    workers: int = 0  # pairs aligned at once; 0: sfm.pair_threads()


# A survey's photos (every one aerial) see the ground from one height, so two views of a point differ
# by little more than a turn and a shift in the image plane: a point may come from farther (the coarse
# pass, max_shift) and a lower correlation still means the same spot; six steps a pass keep the cost
# near the ground settings'. On the drone surveys this aligns more of the observations and brings
# the cameras closer to their GPS fixes; on the ground scenes, whose pairs are wide-baseline
# perspective views, such settings lose pose accuracy, so they keep the defaults (the figures:
# docs/benchmarks.md, "Drone surveys beside COLMAP SIFT" for the surveys, "Real photographs with
# surveyed cameras, beside COLMAP SIFT" for the ground scenes).
SURVEY = TrackRefineOptions(max_shift=4.0, min_ncc=0.6, iterations=6, coarse_sigma=3.0)


@dataclass
class Tracks:
    """Keypoints as nodes 0..N-1 (image by image), the verified inlier matches as edges."""

    image_ids: list[int]
    offsets: np.ndarray  # node of each image's first keypoint; offsets[-1] = N
    edges: np.ndarray  # (E, 2) node pairs, first node in the lower image id

    def image_of(self, nodes: np.ndarray) -> np.ndarray:
        return np.asarray(self.image_ids)[np.searchsorted(self.offsets, nodes, side="right") - 1]


def read_tracks(db: pycolmap.Database) -> tuple[Tracks, dict[int, np.ndarray]]:
    """The tracks the mapper will see, and each image's keypoint rows (COLMAP's convention)."""
    ids = sorted(im.image_id for im in db.read_all_images())
    empty = np.zeros((0, 2), np.float32)
    keypoints = {i: db.read_keypoints(i) if db.exists_keypoints(i) else empty for i in ids}
    offsets = np.cumsum([0] + [len(keypoints[i]) for i in ids])
    start = dict(zip(ids, offsets[:-1], strict=False))
    pair_ids, geometries = db.read_two_view_geometries()
    edges = []
    for pair_id, g in zip(pair_ids, geometries, strict=True):
        m = np.asarray(g.inlier_matches, np.int64).reshape(-1, 2)
        if g.config in UNUSABLE or not len(m):
            continue
        a, b = pycolmap.pair_id_to_image_pair(pair_id)
        edges.append(np.stack([m[:, 0] + start[a], m[:, 1] + start[b]], 1))
    e = np.concatenate(edges) if edges else np.zeros((0, 2), np.int64)
    return Tracks(ids, offsets, e), keypoints


def components(tracks: Tracks, max_track: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each node's track (label), whether that track is of a size to refine (two to ``max_track``
    keypoints), and whether the node is its photo's only keypoint in the track."""
    n = int(tracks.offsets[-1])
    e = tracks.edges
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    _, label32 = connected_components(graph, directed=False)
    label = label32.astype(np.int64)  # label * n_images below passes int32 on a large survey
    size = np.bincount(label)
    n_images = len(tracks.image_ids)
    slot = np.searchsorted(tracks.image_ids, tracks.image_of(np.arange(n)))
    _, where, count = np.unique(label * n_images + slot, return_inverse=True, return_counts=True)
    sized = (size >= 2) & (size <= max_track)
    return label, sized, count[where] == 1


def references(tracks: Tracks, max_track: int) -> np.ndarray:
    """The reference node of each node's track, or -1 where the node is not refined: a single
    keypoint, a track too long, or one of two or more keypoints of one photo in its track.

    A track that holds several keypoints of one photo chains scene points together through a wrong
    match (on a drone survey such keypoints lie hundreds of pixels apart); which of them is the
    reference's point is not known, so they stay where they are, while the photos that hold one
    keypoint of the track are aligned on the reference chosen among those (the mapper splits the
    chain itself). Leaving such a track wholly alone kept the network's placing on a large share of
    a survey's keypoints (docs/benchmarks.md, "Drone surveys beside COLMAP SIFT", the survey track
    refinement).
    """
    n = int(tracks.offsets[-1])
    ref = np.full(n, -1, np.int64)
    if not len(tracks.edges):
        return ref
    e = tracks.edges
    label, sized, unique = components(tracks, max_track)
    ok = sized[label] & unique
    # a track needs two such keypoints: the reference and one to move
    ok &= np.bincount(label[ok], minlength=len(sized))[label] >= 2
    degree = np.bincount(e.ravel(), minlength=n)
    nodes = np.flatnonzero(ok)
    order = nodes[np.lexsort((nodes, -degree[nodes], label[nodes]))]  # by track, most matched first
    first = np.ones(len(order), bool)
    first[1:] = label[order][1:] != label[order][:-1]
    head = np.full(len(sized), -1, np.int64)
    head[label[order][first]] = order[first]
    ref[ok] = head[label[ok]]
    return ref


def tasks(tracks: Tracks, ref: np.ndarray) -> np.ndarray:
    """(K, 2) (reference node, node to move): the edges that touch their track's reference."""
    e = tracks.edges
    a_ref = (ref[e[:, 0]] == e[:, 0]) & (ref[e[:, 1]] >= 0)
    b_ref = (ref[e[:, 1]] == e[:, 1]) & (ref[e[:, 0]] >= 0)
    return np.concatenate([e[a_ref], e[b_ref][:, ::-1]])


def _by_pair(tracks: Tracks, todo: np.ndarray) -> Iterator[tuple[int, int, np.ndarray]]:
    """Tasks grouped by (reference image, other image), reference images in order (one decoded
    photo serves all of its partners)."""
    ia, ib = tracks.image_of(todo[:, 0]), tracks.image_of(todo[:, 1])
    order = np.lexsort((ib, ia))
    todo, ia, ib = todo[order], ia[order], ib[order]
    cut = np.flatnonzero((np.diff(ia) != 0) | (np.diff(ib) != 0)) + 1
    for chunk in np.split(np.arange(len(todo)), cut):
        if len(chunk):
            yield int(ia[chunk[0]]), int(ib[chunk[0]]), todo[chunk]


def refine_tracks(database: Path, image_dir: Path, opts: TrackRefineOptions | None = None) -> dict[str, Any]:
    """Move the keypoints of ``database`` (in place) onto their tracks' references; returns counts
    for the summary.

    One torch thread per pair, and pairs side by side on the cores (Python threads: torch releases
    the GIL in its kernels): the alignment is many small batches of element-wise work, for which a
    second OpenMP thread gains little and, beside other busy processes, makes it many times slower.
    Each observation is moved by one pair only, so the result does not depend on which pair
    finishes first."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return _refine_tracks(database, image_dir, opts)
    finally:
        torch.set_num_threads(threads)


def _refine_tracks(database: Path, image_dir: Path, opts: TrackRefineOptions | None) -> dict[str, Any]:
    opts = opts or TrackRefineOptions()
    t0 = time.perf_counter()
    lsm = SubpixelOptions(
        radius=opts.radius,
        sigma=opts.sigma,
        max_shift=opts.max_shift,
        min_ncc=opts.min_ncc,
        neighbour_radius=opts.neighbour_radius,
        tolerance=1e-2,
        iterations=opts.iterations,
    )
    db = pycolmap.Database.open(str(database))
    try:
        tracks, keypoints = read_tracks(db)
        names = {im.image_id: im.name for im in db.read_all_images()}
        ref = references(tracks, opts.max_track)
        todo = tasks(tracks, ref)
        start = dict(zip(tracks.image_ids, tracks.offsets[:-1], strict=False))
        xy = {
            i: torch.from_numpy(np.array(k[:, :2], np.float32) - COLMAP_OFFSET) for i, k in keypoints.items()
        }
        coarse = SubpixelOptions(
            radius=max(2, opts.radius // 2),
            sigma=opts.coarse_sigma / 2,
            max_shift=opts.coarse_max_shift / 2,
            min_ncc=opts.coarse_min_ncc,
            neighbour_radius=opts.neighbour_radius / 2,
            tolerance=1e-2,
            iterations=opts.iterations,
        )
        photos: ByteLRU[int, tuple[torch.Tensor, torch.Tensor | None]] = ByteLRU(
            opts.images_mb, lambda t: sum(m.numel() * m.element_size() for m in t if m is not None)
        )
        photos_lock = threading.Lock()

        scales: dict[int, torch.Tensor] = {}  # working px per photo px, (x, y), once read

        def photo(i: int) -> tuple[torch.Tensor, torch.Tensor | None]:
            """The photo's smoothed luminance and its gradients, (3, H, W), and the same at half size
            for the coarse pass (None without one), prepared once from one read of the photo."""
            with photos_lock:
                maps = photos.get(i)
                if maps is None:
                    raw, scale = read_gray(image_dir / names[i], opts.max_side)
                    scales[i] = torch.tensor(scale, dtype=torch.float32)
                    half = None
                    if opts.coarse_sigma > 0:
                        h, w = raw.shape
                        # even sides, so that the half-size photo is exactly half (see halved)
                        small = cv2.resize(
                            raw[: h - h % 2, : w - w % 2], (w // 2, h // 2), interpolation=cv2.INTER_AREA
                        )
                        half = gradient_maps(torch.from_numpy(cv2.GaussianBlur(small, (0, 0), coarse.sigma)))
                    gray = cv2.GaussianBlur(raw, (0, 0), opts.sigma) if opts.sigma > 0 else raw
                    maps = (gradient_maps(torch.from_numpy(gray)), half)
                    photos.put(i, maps)
                return maps

        def working(p: torch.Tensor, i: int) -> torch.Tensor:
            return (p + 0.5) * scales[i] - 0.5  # pixel centres at integers on both sizes

        def photo_px(p: torch.Tensor, i: int) -> torch.Tensor:
            return (p + 0.5) / scales[i] - 0.5

        def halved(p: torch.Tensor) -> torch.Tensor:
            return (p + 0.5) / 2 - 0.5  # pixel centres at integers on both sizes

        moved = np.zeros(int(tracks.offsets[-1]), bool)
        new_xy = {i: v.clone() for i, v in xy.items()}
        e = tracks.edges
        ea, eb = tracks.image_of(e[:, 0]), tracks.image_of(e[:, 1])
        # each image pair's edges, lower image id first (read_tracks writes them so): found once,
        # not by a pass over all edges per pair
        width = int(eb.max(initial=0)) + 1
        key = ea.astype(np.int64) * width + eb
        order = np.argsort(key, kind="stable")
        keys, first = np.unique(key[order], return_index=True)
        blocks = dict(zip(keys.tolist(), np.split(order, first[1:]) if len(order) else [], strict=True))

        def align(job: tuple[int, int, np.ndarray]) -> tuple[int, np.ndarray, torch.Tensor, torch.Tensor]:
            """One pair's observations: (the other image, their nodes, where they go, aligned?)."""
            ia, ib, pair_tasks = job
            # the pair's verified matches, oriented reference image -> other, start each warp
            pair_edges = e[blocks[min(ia, ib) * width + max(ia, ib)]]
            ends = (0, 1) if ia < ib else (1, 0)
            na = pair_edges[:, ends[0]] - start[ia]
            nb = pair_edges[:, ends[1]] - start[ib]
            (maps_a, half_a), (maps_b, half_b) = photo(ia), photo(ib)
            pa = working(xy[ia][pair_tasks[:, 0] - start[ia]], ia)
            pb = working(xy[ib][pair_tasks[:, 1] - start[ib]], ib)
            around = (working(xy[ia][na], ia), working(xy[ib][nb], ib))
            if half_a is not None and half_b is not None:
                near, got = refine_on_maps(
                    half_a[0], half_b, halved(pa), halved(pb), coarse, (halved(around[0]), halved(around[1]))
                )
                # what the coarse pass could not align starts the fine one where it was
                pb = torch.where(got[:, None], (near + 0.5) * 2 - 0.5, pb)
            out, ok = refine_on_maps(maps_a[0], maps_b, pa, pb, lsm, around)
            return ib, pair_tasks[:, 1], photo_px(out, ib), ok

        shifts: list[np.ndarray] = []
        workers = opts.workers or pair_threads()
        with ThreadPoolExecutor(max_workers=workers) as pool:
            for ib, nodes, out, ok in pool.map(align, _by_pair(tracks, todo)):
                idx = nodes[ok.numpy()]
                new_xy[ib][idx - start[ib]] = out[ok]
                moved[idx] = True
                shifts.append((out[ok] - xy[ib][idx - start[ib]]).norm(dim=1).numpy())
        for i in tracks.image_ids:
            if len(keypoints[i]) and moved[start[i] : start[i] + len(keypoints[i])].any():
                rows = np.array(keypoints[i], np.float32, copy=True)
                rows[:, :2] = new_xy[i].numpy() + COLMAP_OFFSET
                db.update_keypoints(i, rows)
    finally:
        db.close()
    shift = np.concatenate(shifts) if shifts else np.zeros(0)
    return {
        "tracks": len(np.unique(ref[ref >= 0])),
        "observations_to_align": len(todo),
        "moved": int(moved.sum()),
        "median_shift_px": float(np.median(shift)) if len(shift) else 0.0,
        "seconds": time.perf_counter() - t0,
    }
