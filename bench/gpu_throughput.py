"""Pairs per second over a whole image set, per method and size, with stage shares and peak memory.

    python bench/gpu_throughput.py [--images DIR] [--sizes 640,1024] [--pairs N] [--device auto]
                                   [--methods "sparse,dense,geo,geo anchors_suffice=0"] [--plot PNG]
                                   [--lightglue-batches 1,4,16]

What a worker does on a project: every pair of a folder matched by one ``Matcher`` in one
process, each image's features computed once and then taken from the byte-bounded cache (the
default ``cache_features_mb``; an image evicted from it is extracted again, and the extraction
count says so). Unlike ``pair_speed.py``, which isolates one warm pair, this is the steady state
the GPU targets are stated in: pairs/s, the share of each stage in the wall time, the
CUDA peak allocation (or the process's peak RSS on the CPU), and the device's name.

Each (size, method) runs in a fresh subprocess so its peaks are its own; the networks are loaded
and run once on the first pair before timing (a worker loads them once), then the caches are
emptied so feature extraction is timed as it happens in a job. On CUDA every stage ends with a
synchronisation (``matching.config.StageTimer``), so the shares are the device's work, not launch times.
A second table times LightGlue alone (the ``sparse`` anchors' network, fixed depth and width) over
the same pairs with every image's features computed beforehand: one pair at a time through
``LightGlueMatcher.match`` (kornia's forward), then ``match_batch`` over chunks of 1, 4, 16 pairs
(``--lightglue-batches``), each chunk one padded and masked forward pass, with the CUDA peak of
each. The matches per pair are printed beside the rates: they are the same in every column.
``--methods ""`` runs that table alone; ``--sizes 320 --pairs 16 --device cpu`` is a CPU smoke check.

Default images: ../shared/data/real/sacre_coeur (10 photos, 45 pairs), else five package-shipped
photos warped twice each (not a real project: no image is shared between pairs).
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import time
from collections.abc import Callable
from itertools import combinations
from pathlib import Path

from common import parse_args_or_run_row, parse_method, run_rows

HERE = Path(__file__).resolve().parent
DEFAULT_SET = HERE.parent.parent / "shared" / "data" / "real" / "sacre_coeur"
# timer names of Matcher.match grouped into the columns of the table and the plot
STAGES: dict[str, tuple[str, ...]] = {
    "features": ("features0", "features1"),
    "LightGlue": ("anchors", "dense_lightglue"),
    "guided NN": ("seed", "guided"),  # a survey pair's seed F and guided pass (matching.guided.match_guided)
    "dense coarse": ("dense_coarse",),
    "optimizer": ("optimizer",),
    "refine": ("refine", "subpixel"),
    "merge": ("merge",),
}
SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp"}
# the worker row that times LightGlue alone, batched (lightglue_worker)
LG_BATCH = "lightglue-batch"


def _load_pairs(images: str | None, n_pairs: int) -> list[tuple[object, object]]:
    from geomatch import read_image
    from geomatch.synth.photos import warped_pair

    if images:
        paths = sorted(p for p in Path(images).iterdir() if p.suffix.lower() in SUFFIXES)
        ims = [read_image(p) for p in paths]
        pairs = [(ims[i], ims[j]) for i, j in combinations(range(len(ims)), 2)]
    else:
        pairs = []
        for name in ("astronaut", "coffee", "chelsea", "rocket", "retina"):
            for seed in (0, 1):
                w = warped_pair(name, seed=seed, strength=0.2)
                pairs.append((w.image0, w.image1))
    return pairs[:n_pairs] if n_pairs > 0 else pairs


def worker(args: argparse.Namespace) -> None:
    if args.method == LG_BATCH:
        lightglue_worker(args)
        return
    import torch

    from geomatch import Matcher
    from geomatch.matching.matcher import config_from_options, resolve_device
    from geomatch.matching.variants import light_matcher

    device = resolve_device(args.device)
    pairs = _load_pairs(args.images, args.pairs)
    method, options = parse_method(args.method)
    m = Matcher(config_from_options(method=method, resize=args.size, device=str(device), **options))
    m.match(*pairs[0])  # networks loaded and run once, not timed
    # light_first's matcher is derived (matching.variants.light_matcher) and extracts and caches on its own
    light = light_matcher(m) if m.config.light_first else None
    m.clear_caches()
    m.extract_calls = 0
    if light is not None:
        light.clear_caches()
        light.extract_calls = 0
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
    stage = dict.fromkeys(STAGES, 0.0)
    matches = 0
    t0 = time.perf_counter()
    for a, b in pairs:
        r = m.match(a, b)
        matches += len(r)
        for col, keys in STAGES.items():
            stage[col] += sum(r.timings.get(k, 0.0) for k in keys)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    wall = time.perf_counter() - t0
    if device.type == "cuda":
        name = torch.cuda.get_device_name(device)
        cuda_peak = torch.cuda.max_memory_allocated(device) / 2**20
    else:
        name = f"CPU {platform.processor() or platform.machine()}, {torch.get_num_threads()} threads"
        cuda_peak = 0.0
    out = {
        "device": name,
        "size": args.size,
        "method": args.method,
        "pairs": len(pairs),
        "wall_s": wall,
        "pairs_per_s": len(pairs) / wall,
        "stage_s": stage,
        "other_s": max(0.0, wall - sum(stage.values())),
        "extractions": m.extract_calls + (light.extract_calls if light is not None else 0),
        "matches_per_pair": matches / len(pairs),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "cuda_peak_mb": cuda_peak,
    }
    print("RESULT " + json.dumps(out), flush=True)


def lightglue_worker(args: argparse.Namespace) -> None:
    """LightGlue's pairs/s on precomputed features: ``match`` per pair, then ``match_batch`` per
    chunk of each batch size, the chunk as one forward pass (budget set to hold it)."""
    import torch

    from geomatch import Matcher
    from geomatch.features.base import SparseMatch
    from geomatch.features.lightglue import LightGlueMatcher
    from geomatch.features.lightglue_batch import pair_bytes
    from geomatch.matching.matcher import config_from_options, resolve_device

    device = resolve_device(args.device)
    pairs = _load_pairs(args.images, args.pairs)
    m = Matcher(config_from_options(method="sparse", resize=args.size, device=str(device)))
    lg = m.sparse_matcher
    assert isinstance(lg, LightGlueMatcher) and lg.batches, (
        "the sparse anchors' LightGlue runs at fixed depth and width"
    )
    feats = []
    for a, b in pairs:
        fa, fb = m.features(a)[m.config.sparse].sparse, m.features(b)[m.config.sparse].sparse
        assert fa is not None and fb is not None
        feats.append((fa, fb))
    counts = [f.keypoints.shape[0] for pair in feats for f in pair]
    heads = lg.net.conf.num_heads

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    def timed(run: Callable[..., list[SparseMatch]], *run_args: object) -> tuple[float, float, float]:
        """(pairs/s, matches per pair, CUDA peak MB) of ``run(*run_args)``, which returns the matches."""
        sync()
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        t0 = time.perf_counter()
        matches = run(*run_args)
        sync()
        wall = time.perf_counter() - t0
        peak = torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda" else 0.0
        return len(feats) / wall, sum(len(r.idx_a) for r in matches) / len(feats), peak

    def one_at_a_time() -> list[SparseMatch]:
        return [lg.match(a, b) for a, b in feats]

    def in_chunks(size: int) -> list[SparseMatch]:
        budget = size * pair_bytes(max(counts), max(counts), heads)  # each chunk one forward pass
        return [r for i in range(0, len(feats), size) for r in lg.match_batch(feats[i : i + size], budget)]

    lg.match_batch(feats[:2])  # kernels loaded once, the masked ones included, not timed
    lg.match(*feats[0])
    columns = {"match": timed(one_at_a_time)}
    for size in (int(s) for s in args.lightglue_batches.split(",")):
        columns[str(size)] = timed(in_chunks, size)
    if device.type == "cuda":
        name = torch.cuda.get_device_name(device)
    else:
        name = f"CPU {platform.processor() or platform.machine()}, {torch.get_num_threads()} threads"
    out = {
        "device": name,
        "size": args.size,
        "method": LG_BATCH,
        "pairs": len(feats),
        "keypoints": [min(counts), sum(counts) / len(counts), max(counts)],
        "pairs_per_s": {k: v[0] for k, v in columns.items()},
        "matches_per_pair": {k: v[1] for k, v in columns.items()},
        "cuda_peak_mb": {k: v[2] for k, v in columns.items()},
    }
    print("RESULT " + json.dumps(out), flush=True)


def print_lightglue_table(rows: list[dict]) -> None:
    cols = list(rows[0]["pairs_per_s"])
    names = ["match" if c == "match" else f"batch {c}" for c in cols]
    print(f"\nLightGlue alone, features precomputed; pairs/s (matches per pair), {rows[0]['device']}\n")
    head = ["px", "pairs", "keypoints min/mean/max", *names, "CUDA peak MB " + "/".join(cols)]
    print("| " + " | ".join(head) + " |")
    print("|---|---:|---|" + "---:|" * len(cols) + "---|")
    for r in rows:
        kmin, kmean, kmax = r["keypoints"]
        cells = [f"{r['pairs_per_s'][c]:.2f} ({r['matches_per_pair'][c]:.0f})" for c in cols]
        peaks = "/".join(f"{r['cuda_peak_mb'][c]:.0f}" for c in cols)
        print(
            f"| {r['size']} | {r['pairs']} | {kmin}/{kmean:.0f}/{kmax} | "
            + " | ".join(cells)
            + f" | {peaks} |"
        )


def plot(rows: list[dict], path: Path) -> None:
    """Seconds per pair, stacked by stage: where the time of a pair goes, per size and method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [f"{r['method']} @ {r['size']}" for r in rows]
    cols = [*STAGES, "other"]
    fig, ax = plt.subplots(figsize=(9, 0.5 * len(rows) + 1.5))
    left = [0.0] * len(rows)
    for col in cols:
        widths = [(r["stage_s"].get(col, r["other_s"] if col == "other" else 0.0)) / r["pairs"] for r in rows]
        ax.barh(labels, widths, left=left, label=col)
        left = [a + b for a, b in zip(left, widths, strict=True)]
    ax.invert_yaxis()
    ax.set_xlabel("seconds per pair (stacked by stage)")
    ax.set_title(f"{rows[0]['device']}: {rows[0]['pairs']} pairs, features cached per image")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", default=str(DEFAULT_SET) if DEFAULT_SET.is_dir() else None)
    ap.add_argument("--sizes", default="640,1024")
    # a row may carry matcher options after its method: "geo anchors_suffice=0" is geo's full method
    # on every pair (the default geo answers strong pairs from their anchors alone)
    ap.add_argument("--methods", default="sparse,dense,geo,geo anchors_suffice=0")
    ap.add_argument("--pairs", type=int, default=0, help="first N pairs only (0: all)")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--plot", type=Path, default=HERE / "out" / "gpu_throughput.png")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument(
        "--lightglue-batches",
        default="1,4,16",
        help="pairs per LightGlue forward pass in its own table ('': none)",
    )
    args = parse_args_or_run_row(ap, worker)
    extra = [
        "--pairs",
        str(args.pairs),
        "--device",
        args.device,
        "--lightglue-batches",
        args.lightglue_batches,
    ]
    if args.images:
        extra += ["--images", args.images]
    rows = run_rows(__file__, args.sizes, args.methods, extra) if args.methods else []
    lg_rows = run_rows(__file__, args.sizes, LG_BATCH, extra) if args.lightglue_batches else []
    if rows:
        print_pipeline_table(rows, args)
    if lg_rows:
        print_lightglue_table(lg_rows)
    if args.json:
        args.json.write_text(json.dumps(rows + lg_rows, indent=1))


def print_pipeline_table(rows: list[dict], args: argparse.Namespace) -> None:
    print(f"\n{rows[0]['device']}; images: {args.images or 'warped package photos'}\n")
    cols = [*STAGES, "other"]
    head = ["px", "method", "pairs", "pairs/s", *cols, "extractions", "peak RSS MB", "CUDA peak MB"]
    print("| " + " | ".join(head) + " |")
    print("|---|---|---:|---:|" + "---:|" * (len(cols) + 3))
    for r in rows:
        shares = [r["stage_s"].get(c, r["other_s"] if c == "other" else 0.0) / r["wall_s"] for c in cols]
        print(
            f"| {r['size']} | {r['method']} | {r['pairs']} | {r['pairs_per_s']:.2f} | "
            + " | ".join(f"{100 * s:.0f}%" for s in shares)
            + f" | {r['extractions']} | {r['peak_rss_mb']:.0f} | {r['cuda_peak_mb']:.0f} |"
        )
    plot(rows, args.plot)
    print(f"\nplot: {args.plot}")


if __name__ == "__main__":
    main()
