"""What LightGlue's adaptive depth/width pruning, and the fused attention, buy in speed, side by side.

    python bench/lightglue_pruning.py --images ../shared/data/real/sacre_coeur --sizes 640,1024

Features are extracted once per image (ALIKED, as for the anchors); then every pair is matched by
LightGlue with each setting in turn, interleaved pair by pair so that both settings see the same
machine load. Prints pairs/s per setting and the speed ratio against full strength (no pruning).
The accuracy side of the trade-off is in the quality benches (``bench/quality_pose.py`` with
``--variants "sparse;sparse lightglue_depth_confidence=0.95 lightglue_width_confidence=0.99"``).
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from pathlib import Path

import torch
from common import print_table

from geomatch import Matcher, MatcherConfig, read_image
from geomatch.features.lightglue import LightGlueMatcher

# (depth confidence, width confidence, fused attention); the last row is kornia's own attention
# (einsum cross-attention, flash backend off), without the fused blocks
SETTINGS = {
    "full (depth -1, width -1)": (-1.0, -1.0, True),
    "LightGlue defaults (0.95, 0.99)": (0.95, 0.99, True),
    "depth only (0.95, -1)": (0.95, -1.0, True),
    "full, kornia's attention": (-1.0, -1.0, False),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", type=Path, required=True)
    ap.add_argument("--sizes", default="640,1024")
    ap.add_argument("--pairs", type=int, default=20, help="at most this many pairs of the folder")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    names = sorted(p for p in args.images.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    pairs = list(itertools.combinations(range(len(names)), 2))[: args.pairs]
    rows = []
    for size in (int(s) for s in args.sizes.split(",")):
        m = Matcher(MatcherConfig(method="sparse", resize=size, device=args.device))
        feats = [m.features(read_image(p))["aliked"].sparse for p in names]
        nets = {
            k: LightGlueMatcher("aliked", m.device, 0.1, d, w, fused=f) for k, (d, w, f) in SETTINGS.items()
        }
        for net in nets.values():  # warm-up
            net.match(feats[0], feats[1])
        spent = dict.fromkeys(nets, 0.0)
        counts = dict.fromkeys(nets, 0)
        for i, j in pairs:
            for k, net in nets.items():
                t0 = time.perf_counter()
                r = net.match(feats[i], feats[j])
                if m.device.type == "cuda":
                    torch.cuda.synchronize()
                spent[k] += time.perf_counter() - t0
                counts[k] += int(r.idx_a.numel())
        full = next(iter(SETTINGS))
        for k in nets:
            rows.append(
                {
                    "size": size,
                    "setting": k,
                    "pairs_per_s": len(pairs) / spent[k],
                    "speed_vs_full": spent[full] / spent[k],
                    "matches": counts[k] / len(pairs),
                }
            )
            print(json.dumps(rows[-1]), flush=True)
    columns = [
        ("px", "size", "d"),
        ("LightGlue setting", "setting", "s"),
        ("pairs/s", "pairs_per_s", ".2f"),
        ("speed vs full", "speed_vs_full", ".2f"),
        ("matches", "matches", ".0f"),
    ]
    print_table(f"{args.images.name}: {len(pairs)} pairs, LightGlue only, {args.device}", columns, rows)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
