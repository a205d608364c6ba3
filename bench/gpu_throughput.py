"""Pairs per second over a whole image set, per method and size, with stage shares and peak memory.

    python bench/gpu_throughput.py [--images DIR] [--sizes 640,1024] [--pairs N] [--device auto]
                                   [--methods "sparse,dense,geo,geo anchors_suffice=0"] [--plot PNG]

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
Default images: ../shared/data/real/sacre_coeur (10 photos, 45 pairs), else five package-shipped
photos warped twice each (not a real project: no image is shared between pairs).
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import time
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
    args = parse_args_or_run_row(ap, worker)
    extra = ["--pairs", str(args.pairs), "--device", args.device]
    if args.images:
        extra += ["--images", args.images]
    rows = run_rows(__file__, args.sizes, args.methods, extra)
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
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
