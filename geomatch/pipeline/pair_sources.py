"""The pairs a plan draws from, and the planned pair itself: which image pairs to match, and
which of them to tile.

Specs: ``exhaustive``; ``sequential:K`` (each image with the next K in name order, as video or a
flight line is numbered); ``retrieval:K`` (each image with its K nearest neighbours by a global
descriptor, see retrieval.py); or an explicit list. Global descriptors do not bridge the
air-to-ground gap (that is the problem tiling solves), so ``retrieval:K`` keeps every
aerial x ground pair as a candidate instead of trusting the ranking across views. A pair with
exactly one aerial image is tiled when tiling is ``auto`` or ``on``. ``gps:K`` pairs each image
with its K nearest by GPS position (how a drone project of thousands of images stays
near-linear in pairs); parts join into a union with ``+`` (``gps:10+retrieval:5``).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from ..options import TILING, PairSpecError


@dataclass(frozen=True)
class Pair:
    name0: str
    name1: str
    tiled: bool = False  # exactly one side is aerial and tiling applies
    aerial_first: bool = True  # for tiled pairs: which side is aerial
    # an aerial side: a drone's heading is arbitrary, so the pair is matched at the best quarter
    # turn (geomatch.matching.rotation)
    rotate: bool = False
    # each image's quarter turn (np.rot90) into the project's frame when the plan decided both
    # (turns.image_turns, a survey): the pair is matched with both turned so, unprobed
    turns: tuple[int, int] | None = None
    # what the pair's matcher depends on besides the pair (matching.variants.for_pair), decided by
    # the plan with it: the project has aerial images; every image of it is aerial (a survey)
    aerial_project: bool = False
    survey: bool = False

    @property
    def key(self) -> tuple[str, str]:
        return (self.name0, self.name1)


def exhaustive(names: Sequence[str]) -> list[tuple[str, str]]:
    return [(names[i], names[j]) for i in range(len(names)) for j in range(i + 1, len(names))]


def sequential(names: Sequence[str], k: int) -> list[tuple[str, str]]:
    return [(names[i], names[j]) for i in range(len(names)) for j in range(i + 1, min(len(names), i + k + 1))]


def nearest_neighbours(descriptors: np.ndarray, names: Sequence[str], k: int) -> list[tuple[str, str]]:
    """Each image with its k most similar (cosine) others; symmetric pairs counted once."""
    d = np.asarray(descriptors, np.float64)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    sim = d @ d.T
    np.fill_diagonal(sim, -np.inf)
    out: set[tuple[int, int]] = set()
    for i in range(len(names)):
        for j in np.argsort(-sim[i], kind="stable")[: min(k, len(names) - 1)]:
            out.add((min(i, int(j)), max(i, int(j))))
    return [(names[i], names[j]) for i, j in sorted(out)]


def footprint_overlap(polygons: Sequence[np.ndarray]) -> np.ndarray:
    """(N, N) share of the smaller of two ground footprints (convex polygons, counter-clockwise,
    east-north) that the other covers, estimated from points spread over each footprint (its
    centroid and three rings towards its outline): max(part of i in j, part of j in i)."""
    rings = (1 / 3, 2 / 3, 0.98)
    samples = []
    for poly in polygons:
        c = poly.mean(0)
        samples.append(np.concatenate([c[None], *(c + a * (poly - c) for a in rings)]))
    S = np.stack(samples)  # (N, P, 2): every footprint has the same vertex count
    pts = S.reshape(-1, 2)
    inside = np.empty((len(polygons), S.shape[1], len(polygons)), bool)  # [i, sample, j]
    for j, poly in enumerate(polygons):  # one polygon at a time keeps memory at (N * P, M)
        poly = np.asarray(poly, np.float64)
        e = np.roll(poly, -1, axis=0) - poly
        rel = pts[:, None, :] - poly[None]
        inside[:, :, j] = ((e[:, 0] * rel[..., 1] - e[:, 1] * rel[..., 0]) >= 0).all(-1).reshape(S.shape[:2])
    part = inside.mean(1)  # part[i, j]: share of i's samples inside j
    return np.maximum(part, part.T)


def gps_neighbours(
    names: Sequence[str],
    enu: Mapping[str, np.ndarray],
    k: int,
    unlocated_all: bool = True,
    footprints: Mapping[str, np.ndarray] | None = None,
) -> list[tuple[str, str]]:
    """Each image with a fix paired with its k nearest others by horizontal (east-north)
    distance; symmetric pairs counted once. ``enu``: where each image is, or better where it
    looks (gps.look_point: an oblique's footprint lies ahead of it); only east and north count,
    because what decides overlap from the air is the ground footprint, which height above the
    ground does not move (a drone 40 m above a ground camera sees what it sees). Images
    without a fix are paired with every other image when ``unlocated_all`` (nothing says
    where they are), else left to the other parts
    of the plan (``gps:K+retrieval:K``: retrieval pairs them).

    ``footprints`` (gps.footprints: the ground each aerial image sees, from its gimbal and
    height): between two images that both have one, the K "nearest" are those sharing most
    ground (footprint_overlap), distance breaking ties; an oblique's footprint is a trapezoid
    reaching far ahead, which no single point stands for."""
    located = [n for n in names if n in enu]
    out: set[tuple[str, str]] = set()
    if len(located) > 1:
        xy = np.stack([np.asarray(enu[n], np.float64)[:2] for n in located])
        d = np.linalg.norm(xy[:, None] - xy[None], axis=2)
        np.fill_diagonal(d, np.inf)
        overlap = np.zeros_like(d)
        fp = footprints or {}
        with_fp = [i for i, n in enumerate(located) if n in fp]
        if len(with_fp) > 1:
            ov = footprint_overlap([fp[located[i]] for i in with_fp])
            overlap[np.ix_(with_fp, with_fp)] = ov
        np.fill_diagonal(overlap, -1.0)
        for i, a in enumerate(located):
            order = np.lexsort((d[i], -overlap[i]))  # most shared ground first, then nearest
            for j in order[: min(k, len(located) - 1)]:
                b = located[int(j)]
                out.add((a, b) if a < b else (b, a))
    if unlocated_all:
        for a in names:
            if a not in enu:
                out.update((a, b) if a < b else (b, a) for b in names if b != a)
    return sorted(out)


# ``auto``: up to AUTO_EXHAUSTIVE_MAX images every pair (a pair of every two costs little, and no
# overlap is missed), except that when every image has a ground footprint (DJI XMP: gimbal and
# height) the pairs sharing less than AUTO_MIN_OVERLAP of it are left out (each image keeps its
# AUTO_NEAREST nearest all the same); beyond it, with a GPS fix on at least AUTO_GPS_SHARE of the
# images, each image with its AUTO_GPS_K nearest by position or shared ground, as COLMAP's spatial
# matcher and OpenDroneMap pair a flight (the images without a fix are paired with every image).
# AUTO_MIN_OVERLAP keeps every strongly verified pair of a real survey where a larger share loses
# some (docs/pipeline.md, "The default plan")
AUTO_EXHAUSTIVE_MAX = 30
AUTO_MIN_OVERLAP = 0.1
AUTO_NEAREST = 3
AUTO_GPS_SHARE = 0.9
AUTO_GPS_K = 12


def auto_pairs(
    names: Sequence[str],
    enu: Mapping[str, np.ndarray],
    footprints: Mapping[str, np.ndarray] | None = None,
) -> tuple[list[tuple[str, str]], str]:
    """What ``auto`` plans for these images: the pairs, and the plan in words (for summary.json)."""
    n = len(names)
    share = len(set(enu) & set(names)) / max(n, 1)
    if n > AUTO_EXHAUSTIVE_MAX and share >= AUTO_GPS_SHARE:
        return gps_neighbours(names, enu, AUTO_GPS_K, footprints=footprints), f"gps:{AUTO_GPS_K}"
    fp = footprints or {}
    if n > 2 and all(x in fp for x in names) and all(x in enu for x in names):
        ov = footprint_overlap([fp[x] for x in names])
        shared = [
            (names[i], names[j]) for i in range(n) for j in range(i + 1, n) if ov[i, j] >= AUTO_MIN_OVERLAP
        ]
        nearest = gps_neighbours(names, enu, AUTO_NEAREST, footprints=footprints)
        plan = f"footprints sharing >= {AUTO_MIN_OVERLAP:g} + gps:{AUTO_NEAREST}"
        return sorted({(a, b) if a < b else (b, a) for a, b in shared + nearest}), plan
    return exhaustive(names), "exhaustive"


def cross_view(names: Sequence[str], aerial: set[str]) -> list[tuple[str, str]]:
    a = [n for n in names if n in aerial]
    g = [n for n in names if n not in aerial]
    return [(x, y) if x < y else (y, x) for x in a for y in g]


def explicit(pairs: Iterable[Sequence[str]], names: Sequence[str]) -> list[tuple[str, str]]:
    known = set(names)
    out = []
    for p in pairs:
        if len(p) != 2:
            raise PairSpecError(f"a pair has two image names, got {list(p)!r}")
        a, b = str(p[0]), str(p[1])
        for n in (a, b):
            if n not in known:
                raise PairSpecError(f"pair ({a}, {b}) names {n!r}, which is not among the images")
        if a == b:
            raise PairSpecError(f"pair ({a}, {b}) matches an image with itself")
        out.append((a, b))
    return out


def read_pairs_file(text: str) -> list[list[str]]:
    """hloc/COLMAP pairs format: one pair per line, two names separated by whitespace."""
    rows = [line.split() for line in text.splitlines() if line.strip() and not line.startswith("#")]
    return rows


def finalize(
    raw: Iterable[tuple[str, str]], aerial: set[str], tiling: str = "auto", survey: bool = False
) -> list[Pair]:
    """Drop duplicates (either order), mark tiled pairs. ``tiling``: auto | on | off.

    ``on`` tiles the first image of every pair that has no aerial side designated (forced);
    ``auto`` tiles exactly the aerial x ground pairs. Every pair records whether its project has
    aerial images (``aerial``: the project's) and is a ``survey`` (every image aerial).
    """

    if tiling not in TILING:
        raise PairSpecError(f"tiling must be auto, on or off, not {tiling!r}")
    seen: set[frozenset[str]] = set()
    out = []
    for a, b in raw:
        key = frozenset((a, b))
        if key in seen or a == b:
            continue
        seen.add(key)
        a_air, b_air = a in aerial, b in aerial
        turn = a_air or b_air
        if tiling == "off":
            pair = Pair(a, b, rotate=turn)
        elif a_air != b_air:
            pair = Pair(a, b, tiled=True, aerial_first=a_air, rotate=turn)
        elif tiling == "on":
            pair = Pair(a, b, tiled=True, aerial_first=True, rotate=turn)
        else:
            pair = Pair(a, b, rotate=turn)
        out.append(replace(pair, aerial_project=bool(aerial), survey=survey))
    return out


def with_turns(planned: Iterable[Pair], turns: Mapping[str, int]) -> list[Pair]:
    """The plan with each plain pair of two images whose quarter turn into the project's frame
    is known (``turns``, image -> np.rot90 turns) matched with both turned so, unprobed."""
    out = []
    for p in planned:
        if not p.tiled and p.name0 in turns and p.name1 in turns:
            p = replace(p, rotate=True, turns=(turns[p.name0], turns[p.name1]))
        out.append(p)
    return out
