"""``geomatch eval``: a run's models against a ground-truth COLMAP model, printed and saved.

Every model the run exported (``sparse/0`` the largest, then ``sparse/1`` ...) is judged on its own
(aligned to the ground truth separately, see metrics.py); pose AUC and the SfM statistics are those
of ``sparse/0``, the model a user gets. The result goes to ``OUT/eval.json`` and, when the run has a
``summary.json``, under its ``ground_truth`` key, so a run's summary tells how many of its cameras
are right and not only how many are registered.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pycolmap

from . import pairtruth
from .metrics import AUC_THRESHOLDS, correctness, evaluate

# the keys of a model's result that summary.json carries (the rest stays in eval.json)
SUMMARY_KEYS = (
    "registered",
    "correct",
    "images",
    "aligned",
    "extent",
    "position_threshold",
    "wrong",
    "pairs",
)


@dataclass
class EvalResult:
    metrics: dict[str, Any]

    def table(self) -> str:
        m = self.metrics
        head = (
            "| correct | registered | 3D points | mean track length | mean reproj. error px | "
            + " | ".join(f"AUC@{t:g} deg" for t in AUC_THRESHOLDS)
        )
        row = (
            f"| {m['correct']}/{m['images']} | {m['registered']}/{m['images']} | {m['points3D']} "
            f"| {m['mean_track_length']:.2f} | {m['mean_reprojection_error']:.3f} | "
            + " | ".join(f"{m[f'auc@{t:g}']:.1f}" for t in AUC_THRESHOLDS)
        )
        lines = [head + " |", "|" + "---|" * (5 + len(AUC_THRESHOLDS)), row + " |"]
        lines.append(
            f"correct {m['correct']}/{m['images']} (registered {m['registered']}/{m['images']}): "
            f"rotation error <= {m['rotation_threshold_deg']:g} deg and position error <= "
            f"{m['position_threshold']:.2f} (5% of the scene extent {m['extent']:.1f}) after a robust "
            "similarity alignment to the ground truth"
        )
        if m.get("aligned"):
            lines.append(
                f"median rotation error {m['median_rotation_error_deg']:.3f} deg, median position error "
                f"{m['median_position_error']:.3f} (max {m['max_position_error']:.3f}) ground-truth units"
            )
        else:
            lines.append("could not align the model to ground truth (fewer than 3 registered images agree)")
        for name, err in m["wrong"].items():
            lines.append(
                f"  wrong: {name} "
                + (
                    "(not alignable)"
                    if err is None
                    else f"{err['rotation_deg']:.1f} deg, {err['position']:.2f} off"
                )
            )
        pairs = m.get("pairs")
        if pairs:
            lines.append(
                f"wrong verified pairs (ground truth's epipolar geometry): {pairs['wrong_pairs']} of "
                f"{pairs['verified_pairs']}, {pairs['wrong_pairs_admitted']} of them reached the mapper; "
                f"right pairs dropped: {pairs['right_pairs_dropped']}"
            )
        for other in m.get("other_models", []):
            lines.append(
                f"{other['model']}: correct {other['correct']}/{other['images']} "
                f"(registered {other['registered']}/{other['images']})"
            )
        return "\n".join(lines)


def load_model(folder: Path) -> pycolmap.Reconstruction:
    if not folder.is_dir():
        raise ValueError(f"{folder}: no such model folder")
    try:
        return pycolmap.Reconstruction(str(folder))
    except Exception as e:  # pycolmap raises plain RuntimeError/ValueError on unreadable models
        raise ValueError(f"{folder}: not a readable COLMAP model ({e})") from None


def exported_models(out: Path) -> list[Path]:
    """``sparse/0``, ``sparse/1`` ... as sfm/mapping.py exports them, largest first."""
    sparse = out / "sparse"
    if not sparse.is_dir():
        return []
    return sorted((d for d in sparse.iterdir() if d.is_dir() and d.name.isdigit()), key=lambda d: int(d.name))


def evaluate_run(out: Path, gt: Path) -> EvalResult:
    """Evaluate every exported model; a run without a model scores zero with every image unregistered."""
    gt_rec = load_model(gt)
    models = exported_models(out)
    rec = load_model(models[0]) if models else pycolmap.Reconstruction()
    metrics = evaluate(rec, gt_rec)
    metrics["model"] = "sparse/0"
    metrics["other_models"] = [
        {"model": f"sparse/{d.name}", **correctness(load_model(d), gt_rec)} for d in models[1:]
    ]
    summary = out / "summary.json"
    s = json.loads(summary.read_text()) if summary.is_file() else {}
    if (out / "database.db").is_file():
        graph = s.get("view_graph") or {}
        dropped = [d["pair"] for d in graph.get("dropped", []) + graph.get("tree_dropped", [])]
        metrics["pairs"] = pairtruth.summary(pairtruth.judge_pairs(out / "database.db", gt_rec, dropped))
    if s:
        metrics["run"] = {k: v for k, v in s.items() if k in ("method", "timings")}
        s["ground_truth"] = {
            "gt": str(gt),
            **{k: metrics[k] for k in SUMMARY_KEYS if k in metrics},
            "other_models": [
                {k: o[k] for k in ("model", *SUMMARY_KEYS) if k in o} for o in metrics["other_models"]
            ],
        }
        summary.write_text(json.dumps(s, indent=2) + "\n")
    (out / "eval.json").write_text(json.dumps(metrics, indent=2) + "\n")
    return EvalResult(metrics)
