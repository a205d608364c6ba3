"""Per-stage time and peak memory of one pair, at 640 and 1024 px, for every method, beside
COLMAP's own SIFT extraction and matching of the same pair (the peer, at the photos' own size up
to 1600 px, timed in the same run: the "x peer" column).

    python bench/pair_speed.py [--images A B] [--sizes 640,1024] [--repeat 3] [--device cpu]

Each (size, method) runs in a fresh subprocess so its peak resident memory (ru_maxrss; on CUDA
also torch's peak allocation) is its own. A run matches the pair once cold (features extracted)
and ``--repeat`` times warm (features cached, as for every pair after an image's first); the
stage times are the medians of the warm runs, "features/img" comes from the cold run. The
default pair is the LightGlue example pair from ../shared/data when present, else a
package-shipped photo warped by a homography.
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path

import numpy as np
from common import parse_args_or_run_row, parse_method, run_rows

HERE = Path(__file__).resolve().parent
DEFAULT_PAIR = HERE.parent.parent / "shared" / "data" / "real" / "lightglue_pair"
STAGES = ("anchors", "dense_coarse", "optimizer", "refine", "merge")
PEER = "colmap-sift"


def worker(args: argparse.Namespace) -> None:
    import torch

    from geomatch import Matcher, MatcherConfig, read_image
    from geomatch.matching.variants import for_pair
    from geomatch.synth.photos import warped_pair

    if args.images:
        a, b = read_image(args.images[0]), read_image(args.images[1])
    else:
        p = warped_pair("retina", seed=1, strength=0.2)
        a, b = p.image0, p.image1
    if args.method == PEER:
        peer_worker(a, b, args)
        return
    method, overrides = parse_method(args.method)
    # the pair as `geomatch run` matches a plain pair of a ground-only project: under auto, the
    # light anchors (matching.variants.for_pair); every other method is itself
    m = for_pair(
        Matcher(MatcherConfig(method=method, resize=args.size, device=args.device, **overrides)), tiled=False
    )
    m.match(a, b)  # load the networks (not timed: a worker loads them once)
    m.clear_caches()
    t0 = time.perf_counter()
    cold = m.match(a, b)
    cold_total = time.perf_counter() - t0
    warm = []
    for _ in range(args.repeat):
        m.clear_caches(features=False)  # warm = features cached, every matching stage run
        t0 = time.perf_counter()
        r = m.match(a, b)
        warm.append((time.perf_counter() - t0, r.timings))
    stage = {s: float(np.median([w[1].get(s, 0.0) for w in warm])) for s in STAGES}
    out = {
        "size": args.size,
        "method": args.method,
        "features_per_image": (cold.timings["features0"] + cold.timings["features1"]) / 2,
        "cold_pair": cold_total,
        "warm_pair": float(np.median([w[0] for w in warm])),
        **stage,
        "matches": len(cold),
        "candidates": cold.stats.get("candidates", 0),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "cuda_peak_mb": torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_available() else 0.0,
    }
    print("RESULT " + json.dumps(out))


def peer_worker(a: np.ndarray, b: np.ndarray, args: argparse.Namespace) -> None:
    """COLMAP SIFT on the pair at the photos' own size (up to 1600 px): every pair of a COLMAP
    project is "cold" (extraction once per image, then matching), so its warm pair is its matching."""
    from peer_colmap import sift_pair

    sift_pair(a, b)  # the first call pays pycolmap's own start-up, as the networks' loading above
    runs = [sift_pair(a, b) for _ in range(max(args.repeat, 1))]
    cold = float(np.median([r[2] for r in runs]))
    out = {"size": args.size, "method": PEER, "features_per_image": 0.0, "cold_pair": cold, "warm_pair": cold}
    out.update({s: 0.0 for s in STAGES})
    out.update(matches=len(runs[0][0]), candidates=0, cuda_peak_mb=0.0)
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print("RESULT " + json.dumps(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", nargs=2, default=None)
    ap.add_argument("--sizes", default="640,1024")
    ap.add_argument(
        "--methods",
        default=f"{PEER},auto,sparse,dense,concat,geo-noanchor,geo,geo anchors_suffice=0",
        help="comma-separated 'METHOD [option=value ...]' rows; the peer's row gives the x peer column",
    )
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", type=Path, default=None)
    args = parse_args_or_run_row(ap, worker)
    if args.images is None and DEFAULT_PAIR.is_dir():
        args.images = [str(p) for p in sorted(DEFAULT_PAIR.iterdir())[:2]]
    extra = ["--repeat", str(args.repeat), "--device", args.device]
    if args.images:
        extra += ["--images", *args.images]
    rows = run_rows(__file__, args.sizes, args.methods, extra)
    print(
        f"\npair: {args.images or 'warped scikit-image retina'}; device {args.device}; "
        f"stage times are medians of {args.repeat} warm runs (features cached)\n"
    )
    print(
        "| px | method | features/img s | anchors s | dense coarse s | optimizer s | refine s "
        "| warm pair s | cold pair s | cold pair x peer | optimizer share (cold) | matches | peak RSS MB |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    peer = {r["size"]: r["cold_pair"] for r in rows if r["method"] == PEER}
    for r in rows:
        share = r["optimizer"] / r["cold_pair"] if r["cold_pair"] else 0.0
        ratio = f"{r['cold_pair'] / peer[r['size']]:.2f}" if r["size"] in peer else "-"
        name = "COLMAP SIFT (peer, own size)" if r["method"] == PEER else r["method"]
        print(
            f"| {r['size']} | {name} | {r['features_per_image']:.2f} | {r['anchors']:.2f} "
            f"| {r['dense_coarse']:.2f} | {r['optimizer']:.2f} | {r['refine']:.2f} | {r['warm_pair']:.2f} "
            f"| {r['cold_pair']:.2f} | {ratio} | {100 * share:.0f}% | {r['matches']} "
            f"| {r['peak_rss_mb']:.0f} |"
        )
    print("\n| px | geo / dense, warm pair | geo / dense, cold pair | geo / sparse, cold pair |")
    print("|---|---:|---:|---:|")
    for size in sorted({r["size"] for r in rows}):
        by = {r["method"]: r for r in rows if r["size"] == size}
        if {"geo", "dense", "sparse"} <= set(by):
            g, d, s = by["geo"], by["dense"], by["sparse"]
            print(
                f"| {size} | {g['warm_pair'] / d['warm_pair']:.2f} | {g['cold_pair'] / d['cold_pair']:.2f} "
                f"| {g['cold_pair'] / s['cold_pair']:.2f} |"
            )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
