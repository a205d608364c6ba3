"""``geomatch eval``: a run's model against a ground-truth COLMAP model, printed and saved."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pycolmap

from .metrics import AUC_THRESHOLDS, evaluate


@dataclass
class EvalResult:
    metrics: dict[str, Any]

    def table(self) -> str:
        m = self.metrics
        head = "| registered | 3D points | mean track length | mean reproj. error px | " + " | ".join(
            f"AUC@{t:g} deg" for t in AUC_THRESHOLDS
        )
        row = (
            f"| {m['registered']}/{m['images']} | {m['points3D']} | {m['mean_track_length']:.2f} "
            f"| {m['mean_reprojection_error']:.3f} | "
            + " | ".join(f"{m[f'auc@{t:g}']:.1f}" for t in AUC_THRESHOLDS)
        )
        lines = [head + " |", "|" + "---|" * (4 + len(AUC_THRESHOLDS)), row + " |"]
        if m.get("aligned"):
            lines.append(
                "after alignment to ground truth: median rotation error "
                f"{m['median_rotation_error_deg']:.3f} deg, "
                f"median position error {m['median_position_error']:.3f} (max {m['max_position_error']:.3f}) "
                "ground-truth units"
            )
        else:
            lines.append(
                "could not align the model to ground truth (too few registered images agree with it)"
            )
        return "\n".join(lines)


def load_model(folder: Path) -> pycolmap.Reconstruction:
    if not folder.is_dir():
        raise ValueError(f"{folder}: no such model folder")
    try:
        return pycolmap.Reconstruction(str(folder))
    except Exception as e:  # pycolmap raises plain RuntimeError/ValueError on unreadable models
        raise ValueError(f"{folder}: not a readable COLMAP model ({e})") from None


def evaluate_run(out: Path, gt: Path) -> EvalResult:
    """Evaluate ``out/sparse/0``; a run that produced no model scores zero with every image unregistered."""
    gt_rec = load_model(gt)
    model = out / "sparse" / "0"
    rec = load_model(model) if model.is_dir() else pycolmap.Reconstruction()
    metrics = evaluate(rec, gt_rec)
    summary = out / "summary.json"
    if summary.is_file():
        metrics["run"] = {
            k: v for k, v in json.loads(summary.read_text()).items() if k in ("method", "timings")
        }
    (out / "eval.json").write_text(json.dumps(metrics, indent=2) + "\n")
    return EvalResult(metrics)
