"""``geomatch demo``: the README's main job. Renders a synthetic air-to-ground scene with ground
truth, runs the whole pipeline on it and evaluates the model, with nothing but the installed package.
"""

from __future__ import annotations

import time
from pathlib import Path

from .eval.evaluate import evaluate_run
from .options import DEFAULTS
from .pipeline import RunOptions, run
from .synth.aerial import write_scene


def _pair_costs(t: dict[str, float]) -> str:
    if "tiled_over_plain" not in t:
        return ""
    return (
        f": {t['tiled_pair_mean']:.1f}s a tiled pair, {t['plain_pair_mean']:.1f}s a plain one, "
        f"{t['tiled_over_plain']:.1f}x"
    )


def run_demo(
    out: Path,
    n_aerial: int = 2,
    n_ground: int = 4,
    seed: int = 0,
    method: str = DEFAULTS["method"],
    resize: int = DEFAULTS["resize"],
    verbose: bool = False,
) -> int:
    t0 = time.perf_counter()
    scene = out / "scene"
    print(f"geomatch demo: rendering {n_aerial} aerial + {n_ground} ground images (seed {seed}) -> {scene}")
    write_scene(scene, n_aerial, n_ground, seed)
    aerial = [n for n in (scene / "aerial.txt").read_text().split() if n]
    print(f"running the pipeline ({method}, aerial x ground pairs tiled) -> {out / 'run'}")
    summary = run(
        scene / "images",
        out / "run",
        RunOptions.of(
            {"method": method, "resize": resize},
            aerial_names=aerial,
            verbose=verbose,
        ),
    )
    print("evaluating against the ground truth poses")
    result = evaluate_run(out / "run", scene / "gt")
    print(result.table())
    t = summary["timings"]
    res = out / "run"
    print(
        f"demo done in {time.perf_counter() - t0:.0f}s (matching {t['matching']:.0f}s over "
        f"{summary['pairs']} pairs, {summary['tiled_pairs']} tiled{_pair_costs(t)}; "
        f"mapping {t['mapping']:.1f}s). "
        f"Model: {res / 'sparse' / '0'}, {res / 'points.ply'}; database: {res / 'database.db'}"
    )
    m = result.metrics
    if m["correct"] < m["images"]:
        print(
            f"note: {m['images'] - m['registered']} image(s) not registered and "
            f"{m['registered'] - m['correct']} registered but wrongly placed (see docs/pipeline.md)"
        )
    return 0
