"""Match pictures: both images side by side, matches as lines coloured by score.

At most ``max_lines`` lines are drawn (evenly spread over the score range): a picture with
thousands of lines shows nothing; the title gives the full count.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .matching.matcher import MatchResult


def draw_matches(
    image0: np.ndarray,
    image1: np.ndarray,
    result: MatchResult,
    max_lines: int = 300,
    height: int = 600,
    caption: str | None = None,
) -> np.ndarray:
    """RGB uint8 canvas; scores map through the turbo colour map (blue low, red high). The title
    is ``caption``, else the method and the count."""
    s0, s1 = height / image0.shape[0], height / image1.shape[0]
    a = cv2.resize(image0, (max(1, round(image0.shape[1] * s0)), height), interpolation=cv2.INTER_AREA)
    b = cv2.resize(image1, (max(1, round(image1.shape[1] * s1)), height), interpolation=cv2.INTER_AREA)
    gap = 10
    canvas = np.full((height, a.shape[1] + gap + b.shape[1], 3), 255, np.uint8)
    canvas[:, : a.shape[1]] = a
    canvas[:, a.shape[1] + gap :] = b
    n = len(result)
    if n:
        order = np.argsort(result.scores)
        if n > max_lines:
            order = order[np.linspace(0, n - 1, max_lines).astype(int)]
        scores = result.scores[order]
        lo, hi = float(scores.min()), float(scores.max())
        norm = ((scores - lo) / (hi - lo + 1e-9) * 255).astype(np.uint8)
        colors = cv2.applyColorMap(norm[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1]
        p0 = (result.keypoints0[order] + 0.5) * s0
        p1 = (result.keypoints1[order] + 0.5) * s1 + np.array([a.shape[1] + gap, 0])
        for q0, q1, c in zip(p0, p1, colors, strict=True):
            color = tuple(int(v) for v in c)
            x0, y0 = (round(v * 16) for v in q0)
            x1, y1 = (round(v * 16) for v in q1)
            cv2.line(canvas, (x0, y0), (x1, y1), color, 1, cv2.LINE_AA, shift=4)
            cv2.circle(canvas, (x0, y0), 2 * 16, color, -1, cv2.LINE_AA, shift=4)
            cv2.circle(canvas, (x1, y1), 2 * 16, color, -1, cv2.LINE_AA, shift=4)
    label = (caption or f"{result.method}: {n} matches") + (f" ({max_lines} drawn)" if n > max_lines else "")
    (tw, th), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.6, 1)
    cv2.rectangle(canvas, (0, 0), (tw + 16, th + 16), (0, 0, 0), -1)
    cv2.putText(canvas, label, (8, th + 8), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    return canvas


def save_matches(
    path: str | Path, image0: np.ndarray, image1: np.ndarray, result: MatchResult, caption: str | None = None
) -> None:
    canvas = draw_matches(image0, image1, result, caption=caption)
    if not cv2.imwrite(str(path), cv2.cvtColor(canvas, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {path}")
