"""``geomatch run``: a folder of images to a sparse model, in one process, no servers.

A loop over the pipeline's stages (the same functions the worker steps call): read
metadata -> plan pairs -> match each pair (features once per image, cached; aerial x ground pairs
tiled) -> write each pair into the COLMAP database (consolidated keypoints, verified geometry, one
transaction) -> map -> export. A pair already in the database is not matched again, so an
interrupted run resumes where it stopped and adding images to the folder matches only the new
pairs.
"""

from __future__ import annotations

import dataclasses
import queue
import threading
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from tqdm import tqdm

from . import capture, dbwrite, pairstep, planning, rundir
from .features.store import run_feature_store
from .geo import gcp as gcpgeo
from .geo import gps as gpsfix
from .geo.gcpfile import GcpError, GcpFile, read_gcp_file
from .imagefolder import Images
from .imagefolder import PipelineError as PipelineError  # a run's bad input
from .imagefolder import list_images as list_images
from .imageio import WORKING_SIDE
from .matching.matcher import config_from_options
from .matching.stored import stored
from .memory import return_freed_memory
from .metadata import read_metadata
from .options import DEFAULTS, cache_budget, parse_plan, resolve
from .report import survey_report
from .sfm import mapping
from .sfm.colmapdb import ColmapDatabase, PairWrite
from .sfm.upright import image_up


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
        self._queue: queue.Queue[tuple[int, int, pairstep.PairMatches] | None] = queue.Queue(self.QUEUE_PAIRS)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="pair-writer", daemon=True)

    def __enter__(self) -> PairWriter:
        self._thread.start()
        return self

    def put(self, id0: int, id1: int, matches: pairstep.PairMatches) -> None:
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
                    self.last = dbwrite.write(db, *item, self.radius, self.resize)
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
    match: pairstep.MatchPair = pairstep.match,
) -> dict[str, Any]:
    """The whole pipeline; returns the summary also written to ``out/summary.json``. ``match``:
    how each pair is matched (a benchmark passes one that reads stored matches back)."""
    opts = opts or RunOptions()
    image_dir, out = Path(image_dir), Path(out)
    t_start = time.perf_counter()
    if opts.pairs_list is None:
        parse_plan(opts.pairs)  # a bad spec fails before any work
    names = list_images(image_dir)
    metas = {n: read_metadata(image_dir / n) for n in names}
    fixes = gpsfix.fixes(names, metas) if opts.georeference else None
    gcps = _gcp_file(opts.gcp, metas) if opts.gcp else None  # a bad file fails before any work
    captured = capture.captures(names, opts.aerial_names, opts.aerial_glob)
    aerial = capture.aerial_set(captured, metas, fixes.enu if fixes is not None else None)
    out.mkdir(parents=True, exist_ok=True)

    budget = cache_budget()  # GEOMATCH_CACHE_MB, as a worker's job thread
    config = config_from_options(
        method=opts.method,
        resize=opts.resize,
        device=opts.device,
        **{"cache_features_mb": budget.features_mb, "cache_anchors_mb": budget.anchors_mb, **opts.matcher},
    )
    matcher = stored(config, run_feature_store(out / "features"))
    # photos beyond the working size are matched at it (imageio.WORKING_SIDE), their matches
    # written in the photos' own pixels
    images = Images(image_dir, budget.images_mb, WORKING_SIDE)
    t_plan = time.perf_counter()
    planned = planning.plan(
        image_dir,
        names,
        aerial,
        opts.pairs,
        opts.pairs_list,
        opts.tiling,
        matcher,
        images,
        opts.progress,
        fixes=fixes,
        metas=metas,
    )

    timings: dict[str, float] = {"plan": time.perf_counter() - t_plan, "matching": 0.0, "writing": 0.0}
    pair_seconds: dict[str, list[float]] = {"tiled": [], "plain": []}
    with ColmapDatabase(out / "database.db") as db:
        ids = dbwrite.register(db, names, metas, opts.share_camera)
    priors = gpsfix.write_pose_priors(out / "database.db", ids, fixes) if fixes is not None else 0
    with ColmapDatabase(out / "database.db") as db:
        todo = dbwrite.unmatched(db, ids, planned)
    bar = tqdm(todo, desc=f"matching ({opts.method})", unit="pair", disable=not opts.progress)
    survey = aerial >= set(names)  # every image aerial: the survey pairs' matcher (pairstep.match)
    with PairWriter(out / "database.db", opts.snap_radius, matcher.config.resize) as writer:
        for p in bar:
            t0 = time.perf_counter()
            m = match(matcher, p, images[p.name0], images[p.name1], bool(aerial), survey)
            m = m.in_photo_pixels(images.to_photo(p.name0), images.to_photo(p.name1))
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
    images.clear()
    del matcher, images  # the networks and whatever else the matcher holds go too
    return_freed_memory()
    with ColmapDatabase(out / "database.db") as db:
        db_stats = db.stats()
    t_map = time.perf_counter()
    summary = mapping.reconstruct(
        out / "database.db",
        image_dir,
        out,
        opts.mapper,
        opts.min_model_size,
        min_pose_inliers=opts.min_pose_inliers,
        verbose=opts.verbose,
        progress=opts.progress,
        loop_check=opts.loop_check,
        tree_check=opts.tree_check,
        track_refine=opts.track_refine,
        gps=fixes,
        tiled=any(p.tiled for p in planned),
        up=image_up(metas, survey),
        survey=survey,
    )
    summary["pose_priors"] = priors
    if gcps is not None and opts.gcp:
        gcpgeo.georeference_summary(summary, out, gcps, opts.checkpoints)
        # kept beside summary.json: the exports place the points by it (export/gcpjson.py)
        (out / "gcp_list.txt").write_text(Path(opts.gcp).read_text())
    timings["mapping"] = time.perf_counter() - t_map
    timings["total"] = time.perf_counter() - t_start
    timings.update(pair_timing_summary(pair_seconds))
    summary.update(
        image_dir=str(image_dir.resolve()),  # where ``geomatch export`` finds the images
        method=opts.method,
        pairs=len(planned),
        pair_plan="explicit list"
        if opts.pairs_list is not None
        else planning.plan_in_words(opts.pairs, names, fixes, metas),
        pairs_matched_now=len(todo),
        tiled_pairs=sum(p.tiled for p in planned),
        aerial=sorted(aerial),
        database=db_stats,
        timings=timings,
        options={k: v for k, v in asdict(opts).items() if k not in ("progress", "verbose", "pairs_list")},
    )
    summary["report"] = survey_report(summary)
    rundir.write_outputs(out, summary)
    return summary


def _gcp_file(path: str, metas: Mapping[str, Any]) -> GcpFile:
    """The run's GCP file checked against its images; a file it cannot use stops the run here."""
    sizes = {name: (m.width, m.height) for name, m in metas.items()}
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise PipelineError(f"GCP file {path}: {e}") from None
    try:
        return read_gcp_file(text, sizes)
    except GcpError as e:
        raise PipelineError(f"GCP file {path}: {e}") from None
