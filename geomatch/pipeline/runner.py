"""``geomatch run``: a folder of images to a sparse model, in one process, no servers: the
in-process runner of the pipeline's stages, which the service's job steps (workers/jobs.py) run
queued. Prepare (metadata, aerial images, plan, registration: prepare.py) -> match each pair
(features once per image, cached; aerial x ground pairs tiled: match_pairs.py) -> write it into the
COLMAP database (consolidated keypoints, verified geometry, one transaction: database.py) -> map,
georeference, report (reconstruction.py). A pair already in the database is not matched again, so
an interrupted run resumes where it stopped and adding images to the folder matches only the new
pairs.
"""

from __future__ import annotations

import dataclasses
import queue
import threading
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

from tqdm import tqdm

from ..features.store import run_feature_store
from ..geo.gcpfile import GcpError, read_gcp_file
from ..imagefolder import PipelineError, list_images
from ..matching.matcher import Matcher
from ..matching.stored import build_matcher
from ..memory import cache_budget, return_freed_memory
from ..options import DEFAULTS, parse_plan, resolve
from ..sfm.colmapdb import ColmapDatabase, PairWrite
from . import aerial, database, match_pairs
from .database import PairMatches
from .orthomap import add_map
from .outputs import finish
from .prepare import frames, plan_project, register
from .project import PlanRequest, ProjectImages
from .reconstruction import ControlPoints, map_project, mapping_settings


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
    # drop verified pairs whose relative rotation breaks the view graph's loops (geomatch.sfm.viewgraph)
    loop_check: bool = True
    # drop verified pairs whose relative rotation disagrees with the tree of the strongest pairs:
    # repeated and symmetric structure (geomatch.sfm.viewgraph)
    tree_check: bool = True
    # align each track's points on the original photos before mapping (geomatch.sfm.trackrefine):
    # the matcher places them at the network's input size
    track_refine: bool = True
    # images with EXIF GPS: pose priors in the database, the model moved into ENU metres
    georeference: bool = True
    # ground control points (OpenDroneMap's gcp_list.txt): the model is moved into their frame
    # (geomatch.geo.gcp), over the GPS georeferencing; ``checkpoints``: the points held out of the
    # fit to judge it, by name, or how many (0: none)
    gcp: str | None = None
    checkpoints: list[str] | int = 0
    # the map after mapping (geomatch.ortho): on / off, and its pixel in metres (0: the survey's GSD)
    ortho: str = DEFAULTS["ortho"]
    ortho_gsd: float = DEFAULTS["ortho_gsd"]
    matcher: dict[str, Any] = field(default_factory=dict)  # further MatcherConfig / optimizer options
    progress: bool = True
    verbose: bool = False  # COLMAP's own log (glog) on stderr; off: a progress bar per stage only

    @classmethod
    def of(cls, values: Mapping[str, Any], **fields: Any) -> RunOptions:
        """From option values by name (``geomatch.options``: the CLI's flags, a job's options) as
        ``options.resolve`` makes them (resize 0: full size, camera: share_camera); the names
        that are no field here (the optimizer's, the backbones') go to ``matcher``."""
        own = {f.name for f in dataclasses.fields(cls)}
        resolved = resolve(values)
        matcher = {k: v for k, v in resolved.items() if k not in own}
        return cls(**{k: v for k, v in resolved.items() if k in own}, matcher=matcher, **fields)


class PairWriter:
    """The run's pairs into its COLMAP database on a thread of their own, in the order matched.

    Why: a pair's write is mostly COLMAP's verification (RANSAC in pycolmap, which releases the
    GIL) and the matcher does not keep both cores busy, so the write of one pair overlaps the
    matching of the next; the queue holds a few pairs' matches, so memory stays bounded. Only this
    thread touches the database while it runs. A failed write stops the run with its error at
    the next pair, and the pairs written before it stay written (the run resumes there)."""

    QUEUE_PAIRS = 4

    def __init__(self, database: Path, radius: float, resize: int | None) -> None:
        self.database, self.radius, self.resize = database, radius, resize
        self.seconds = 0.0  # the writes' own time; they overlap the matching
        self.last: PairWrite | None = None
        self._queue: queue.Queue[tuple[int, int, PairMatches] | None] = queue.Queue(self.QUEUE_PAIRS)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="pair-writer", daemon=True)

    def __enter__(self) -> PairWriter:
        self._thread.start()
        return self

    def put(self, id0: int, id1: int, matches: PairMatches) -> None:
        self._raise()
        self._queue.put((id0, id1, matches))

    def __exit__(self, *exc: object) -> None:
        self._queue.put(None)
        self._thread.join()
        if exc[0] is None:
            self._raise()

    def _raise(self) -> None:
        if self._error is not None:
            raise self._error

    def _run(self) -> None:
        with ColmapDatabase(self.database) as db:
            while (item := self._queue.get()) is not None:
                if self._error is not None:
                    continue  # drained so that the producer never blocks on a dead writer
                try:
                    t0 = time.perf_counter()
                    self.last = database.write(db, *item, self.radius, self.resize)
                    self.seconds += time.perf_counter() - t0
                except BaseException as e:  # handed to the matching thread, which raises it
                    self._error = e


def pair_timing_summary(pair_seconds: dict[str, list[float]]) -> dict[str, float]:
    """Mean seconds of a tiled and of a plain pair matched in this run, and their ratio: the
    cost of tiling as a user of a mixed project sees it (features reused across partners count
    for the pair that computed them, as in any run)."""
    out: dict[str, float] = {}
    for kind, secs in pair_seconds.items():
        if secs:
            out[f"{kind}_pair_mean"] = sum(secs) / len(secs)
    if "tiled_pair_mean" in out and "plain_pair_mean" in out and out["plain_pair_mean"] > 0:
        out["tiled_over_plain"] = out["tiled_pair_mean"] / out["plain_pair_mean"]
    return out


def run(
    image_dir: str | Path,
    out: str | Path,
    opts: RunOptions | None = None,
    match: match_pairs.MatchPair = match_pairs.match,
) -> dict[str, Any]:
    """The whole pipeline; returns the summary also written to ``out/summary.json``. ``match``:
    how each pair is matched (a benchmark passes one that reads stored matches back)."""
    opts = opts or RunOptions()
    image_dir, out = Path(image_dir), Path(out)
    t_start = time.perf_counter()
    if opts.pairs_list is None:
        parse_plan(opts.pairs)  # a bad spec fails before any work
    names = list_images(image_dir)
    images = ProjectImages.read(image_dir, names, opts.georeference)
    control = _control_points(opts.gcp, opts.checkpoints, images) if opts.gcp else None
    captures = aerial.captures(names, opts.aerial_names, opts.aerial_glob)
    out.mkdir(parents=True, exist_ok=True)

    budget = cache_budget()  # GEOMATCH_CACHE_MB, as a worker's job thread
    matcher = build_matcher(
        run_feature_store(out / "features"),
        method=opts.method,
        resize=opts.resize,
        device=opts.device,
        **{"cache_features_mb": budget.features_mb, "cache_anchors_mb": budget.anchors_mb, **opts.matcher},
    )
    decoded = frames(image_dir, budget.images_mb)
    t_plan = time.perf_counter()
    request = PlanRequest(opts.pairs, opts.pairs_list, opts.tiling)
    plan = plan_project(images, captures, request, partial(_built, matcher), decoded, opts.progress)
    plan.write(out / "plan.json")

    timings: dict[str, float] = {"plan": time.perf_counter() - t_plan, "matching": 0.0, "writing": 0.0}
    pair_seconds: dict[str, list[float]] = {"tiled": [], "plain": []}
    ids = register(out / "database.db", images, opts.share_camera)
    with ColmapDatabase(out / "database.db") as db:
        todo = database.unmatched(db, ids, plan.pairs)
    bar = tqdm(todo, desc=f"matching ({opts.method})", unit="pair", disable=not opts.progress)
    with PairWriter(out / "database.db", opts.snap_radius, matcher.config.resize) as writer:
        for p in bar:
            t0 = time.perf_counter()
            m = match(matcher, p, decoded[p.name0], decoded[p.name1])
            m = m.in_photo_pixels(decoded.to_photo(p.name0), decoded.to_photo(p.name1))
            match_s = time.perf_counter() - t0
            timings["matching"] += match_s
            pair_seconds["tiled" if p.tiled else "plain"].append(match_s)
            writer.put(ids[p.name0], ids[p.name1], m)
            if writer.last is not None:
                bar.set_postfix(matches=writer.last.matches, inliers=writer.last.inliers)
    timings["writing"] = writer.seconds
    # the matcher's caches (GEOMATCH_CACHE_MB) are not needed by the mapper, whose memory grows
    # with the project: emptied and handed back, they do not add to a large survey's peak
    matcher.clear_caches()
    decoded.clear()
    del matcher, decoded  # the networks and whatever else the matcher holds go too
    return_freed_memory()
    timings.update(pair_timing_summary(pair_seconds))
    fields = {
        "image_dir": str(image_dir.resolve()),  # where ``geomatch export`` finds the images
        "method": opts.method,
        "pairs_matched_now": len(todo),
        "timings": timings,
        "options": {k: v for k, v in asdict(opts).items() if k not in ("progress", "verbose", "pairs_list")},
    }
    settings = mapping_settings(asdict(opts), plan, opts.verbose, opts.progress)
    summary = map_project(out / "database.db", images, plan, out, settings, control, fields)
    summary = add_map(out, summary, image_dir, opts.ortho, opts.ortho_gsd)
    summary["timings"]["total"] = time.perf_counter() - t_start
    return finish(out, summary)


def _built(matcher: Matcher) -> Matcher:
    return matcher


def _control_points(path: str, checkpoints: list[str] | int, images: ProjectImages) -> ControlPoints:
    """The run's GCP file, checked against its images here: a file it cannot use stops the run
    before any work."""
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise PipelineError(f"GCP file {path}: {e}") from None
    try:
        read_gcp_file(text, images.sizes())
    except GcpError as e:
        raise PipelineError(f"GCP file {path}: {e}") from None
    return ControlPoints(text, checkpoints)
