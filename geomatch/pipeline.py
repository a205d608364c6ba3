"""``geomatch run``: a folder of images to a sparse model, in one process, no servers.

Stages: read metadata -> plan pairs -> match each pair (features once per image, cached; aerial
x ground pairs tiled) -> write each pair into the COLMAP database (consolidated keypoints,
verified geometry, one transaction) -> map -> export. A pair already in the database is not
matched again, so an interrupted run resumes where it stopped and adding images to the folder
matches only the new pairs.
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import time
from collections import OrderedDict
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from . import pairs as pairing
from .colmapdb import ColmapDatabase
from .imageio import image_key, read_image
from .matcher import Matcher, config_from_options
from .metadata import ImageMeta, read_metadata
from .options import DEFAULTS, IMAGE_SUFFIXES
from .retrieval import vlad
from .sfm import reconstruct
from .tiling import match_tiled


class PipelineError(ValueError):
    """Bad input to a run: no images, unknown names, bad pair spec."""


@dataclass
class RunOptions:
    method: str = DEFAULTS["method"]
    resize: int | None = DEFAULTS["resize"]
    device: str = DEFAULTS["device"]
    pairs: str = DEFAULTS["pairs"]
    pairs_list: list[list[str]] | None = None  # explicit pairs override ``pairs``
    aerial_glob: str | None = None
    aerial_names: list[str] | None = None
    tiling: str = DEFAULTS["tiling"]  # auto | on | off
    snap_radius: float = DEFAULTS["snap_radius"]  # px at network resolution; 0 turns consolidation off
    mapper: str = DEFAULTS["mapper"]
    share_camera: bool | None = None  # None: one camera per EXIF device, else per image
    min_model_size: int = 3
    # PnP inliers the incremental mapper needs to register an image
    min_pose_inliers: int = DEFAULTS["min_pose_inliers"]
    matcher: dict[str, Any] = field(default_factory=dict)  # further MatcherConfig / optimizer options
    match_cache: str | None = None  # folder of raw pair matches shared by runs (benchmarks, variants)
    progress: bool = True
    verbose: bool = False  # COLMAP's own log (glog) on stderr; off: a progress bar per stage only


def list_images(folder: Path) -> list[str]:
    if not folder.is_dir():
        raise PipelineError(f"{folder}: not a directory")
    names = sorted(
        str(p.relative_to(folder))
        for p in folder.rglob("*")
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
    )
    if len(names) < 2:
        raise PipelineError(f"{folder}: found {len(names)} image(s); need at least 2")
    return names


def aerial_set(names: list[str], metas: dict[str, ImageMeta], opts: RunOptions) -> set[str]:
    """Explicit names or glob win; otherwise EXIF/XMP decides; silent metadata means ground."""
    if opts.aerial_names is not None:
        unknown = sorted(set(opts.aerial_names) - set(names))
        if unknown:
            raise PipelineError(f"aerial list names images not in the folder: {', '.join(unknown[:5])}")
        return set(opts.aerial_names)
    if opts.aerial_glob is not None:
        return {
            n
            for n in names
            if fnmatch.fnmatch(n, opts.aerial_glob) or fnmatch.fnmatch(Path(n).name, opts.aerial_glob)
        }
    return {n for n in names if metas[n].aerial_hint}


class _Images:
    """Decoded images, a few at a time."""

    def __init__(self, folder: Path, capacity: int = 32) -> None:
        self.folder, self.capacity = folder, capacity
        self._cache: OrderedDict[str, np.ndarray] = OrderedDict()

    def __getitem__(self, name: str) -> np.ndarray:
        if name in self._cache:
            self._cache.move_to_end(name)
            return self._cache[name]
        img = read_image(self.folder / name)
        self._cache[name] = img
        while len(self._cache) > self.capacity:
            self._cache.popitem(last=False)
        return img


def plan_pairs(
    names: list[str], aerial: set[str], opts: RunOptions, matcher: Matcher | None, images: _Images | None
) -> list[pairing.Pair]:
    if opts.pairs_list is not None:
        raw = pairing.explicit(opts.pairs_list, names)
    else:
        kind, k = pairing.parse_spec(opts.pairs)
        if kind == "exhaustive":
            raw = pairing.exhaustive(names)
        elif kind == "sequential":
            raw = pairing.sequential(names, k)
        else:
            assert matcher is not None and images is not None
            raw = pairing.nearest_neighbours(
                global_descriptors(matcher, images, names, opts.progress), names, k
            )
            raw += pairing.cross_view(names, aerial)
    planned = pairing.finalize(raw, aerial, opts.tiling)
    # cache-friendly order: all pairs of one aerial image (its five crops) together
    return sorted(planned, key=lambda p: (not p.tiled, p.name0 if p.aerial_first else p.name1, p.key))


def global_descriptors(
    matcher: Matcher, images: _Images, names: list[str], progress: bool = True
) -> np.ndarray:
    sparse = matcher.derive(method="sparse")
    local = []
    for n in tqdm(names, desc="retrieval", disable=not progress, leave=False):
        feats = sparse.features(images[n])[sparse.config.sparse].sparse
        assert feats is not None
        local.append(feats.descriptors.float().cpu().numpy())
    return vlad(local)


def run(image_dir: str | Path, out: str | Path, opts: RunOptions | None = None) -> dict[str, Any]:
    """The whole pipeline; returns the summary also written to ``out/summary.json``."""
    opts = opts or RunOptions()
    image_dir, out = Path(image_dir), Path(out)
    t_start = time.perf_counter()
    if opts.pairs_list is None:
        pairing.parse_spec(opts.pairs)  # a bad spec fails before any work
    names = list_images(image_dir)
    metas = {n: read_metadata(image_dir / n) for n in names}
    aerial = aerial_set(names, metas, opts)
    out.mkdir(parents=True, exist_ok=True)

    n_entries = len(names) + 5 * len(aerial)
    config = config_from_options(
        method=opts.method,
        resize=opts.resize,
        device=opts.device,
        cache_images=max(16, min(n_entries, 96)),
        **opts.matcher,
    )
    matcher = Matcher(config)
    images = _Images(image_dir)
    planned = plan_pairs(names, aerial, opts, matcher, images)

    timings: dict[str, float] = {"matching": 0.0, "writing": 0.0}
    with ColmapDatabase(out / "database.db") as db:
        ids = {n: db.add_image(n, metas[n], opts.share_camera) for n in names}
        done = db.matched_pairs()
        todo = [p for p in planned if tuple(sorted((ids[p.name0], ids[p.name1]))) not in done]
        bar = tqdm(todo, desc=f"matching ({opts.method})", unit="pair", disable=not opts.progress)
        for p in bar:
            t0 = time.perf_counter()
            a, b = images[p.name0], images[p.name1]
            k0, k1, sc = _match(matcher, p, a, b, opts.match_cache)
            t1 = time.perf_counter()
            w = db.write_pair(
                ids[p.name0],
                ids[p.name1],
                k0,
                k1,
                sc,
                _radius(opts, a),
                _radius(opts, b),
            )
            timings["matching"] += t1 - t0
            timings["writing"] += time.perf_counter() - t1
            bar.set_postfix(matches=w.matches, inliers=w.inliers)
        db_stats = db.stats()
    t_map = time.perf_counter()
    summary = reconstruct(
        out / "database.db",
        image_dir,
        out,
        opts.mapper,
        opts.min_model_size,
        verbose=opts.verbose,
        progress=opts.progress,
        min_pose_inliers=opts.min_pose_inliers,
    )
    timings["mapping"] = time.perf_counter() - t_map
    timings["total"] = time.perf_counter() - t_start
    summary.update(
        method=opts.method,
        pairs=len(planned),
        pairs_matched_now=len(todo),
        tiled_pairs=sum(p.tiled for p in planned),
        aerial=sorted(aerial),
        database=db_stats,
        timings=timings,
        options={k: v for k, v in asdict(opts).items() if k not in ("progress", "verbose", "pairs_list")},
    )
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def _radius(opts: RunOptions, image: np.ndarray) -> float:
    """The snap radius is given in matched (network) pixels: in original pixels it grows with
    the downscale, since a match is no more precise than the resolution it was found at."""
    if opts.snap_radius <= 0:
        return 0.0
    long_side = max(image.shape[:2])
    return opts.snap_radius * (long_side / opts.resize if opts.resize else 1.0)


def _match(
    matcher: Matcher, p: pairing.Pair, a: np.ndarray, b: np.ndarray, cache: str | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    path = None
    if cache:
        h = hashlib.sha256(
            repr((image_key(a), image_key(b), p.tiled, p.aerial_first, matcher.config)).encode()
        )
        path = Path(cache) / f"{h.hexdigest()[:32]}.npz"
        if path.is_file():
            with np.load(path) as z:
                return z["k0"], z["k1"], z["scores"]
    if p.tiled:
        r = match_tiled(matcher, a, b, True) if p.aerial_first else match_tiled(matcher, b, a, False)
        k0, k1, sc = r.keypoints0, r.keypoints1, r.scores
    else:
        m = matcher.match(a, b)
        k0, k1, sc = m.keypoints0, m.keypoints1, m.scores
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, k0=k0, k1=k1, scores=sc)
        tmp.replace(path)
    return k0, k1, sc
