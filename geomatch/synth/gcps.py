"""Ground control points of a synthetic scene, with their exact truth: the test of GCP georeferencing.

A survey's GCPs are targets on the ground whose coordinates were measured and whose pixels were
clicked in the photos that see them. Here the targets are points of the ground plane away from the
buildings, their coordinates the scene's own metres moved by :data:`OFFSET` into UTM 32N (the zone
of the scenes' GPS origin), optionally with survey noise, and their pixels the exact projections
in every camera that sees them unoccluded. What a model makes of them can then be judged against
the truth to the millimetre.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .aerial import Scene
from .camera import Camera

CRS = "EPSG:32632"
# scene metres -> easting, northing, height in the file: a place in UTM 32N near the GPS origin
OFFSET = np.array([465000.0, 5247000.0, 408.0])
MARGIN_PX = 8  # a target this close to the border is not clicked


def visible(scene: Scene, cam: Camera, X: np.ndarray) -> np.ndarray | None:
    """The pixel (centres at integers) of world point ``X`` in ``cam``, or None where it is out of
    the image, behind the camera or hidden behind a building."""
    uv, depth = cam.project(X[None])
    if depth[0] <= 0:
        return None
    u, v = uv[0]
    if not (MARGIN_PX <= u <= cam.width - 1 - MARGIN_PX and MARGIN_PX <= v <= cam.height - 1 - MARGIN_PX):
        return None
    return None if scene.hidden(cam.centre, X, float(depth[0])) else uv[0]


def scene_gcps(
    scene: Scene, cams: list[Camera], n: int, seed: int = 0, noise_m: float = 0.0, min_views: int = 2
) -> tuple[str, dict[str, list[float]]]:
    """(the gcp_list.txt text, each point's true easting, northing, height): ``n`` ground points
    seen by at least ``min_views`` cameras each, their coordinates with N(0, ``noise_m``) per axis."""
    rng = np.random.default_rng(seed)
    noise = np.random.default_rng([seed, 1])  # its own stream: noise does not change which points
    lines = [CRS]
    truth: dict[str, list[float]] = {}
    for _ in range(200 * n):
        if len(truth) == n:
            break
        X = np.array([*rng.uniform(-0.7 * scene.extent, 0.7 * scene.extent, 2), 0.0])
        if any(np.all(b.lo[:2] - 0.5 <= X[:2]) and np.all(X[:2] <= b.hi[:2] + 0.5) for b in scene.boxes):
            continue  # at a wall's foot a click is ambiguous
        seen = [(c.name, uv) for c in cams if (uv := visible(scene, c, X)) is not None]
        if len(seen) < min_views:
            continue
        name = f"gcp{len(truth):02d}"
        true = X + OFFSET
        truth[name] = true.tolist()
        measured = true + noise.normal(0.0, noise_m, 3) if noise_m > 0 else true
        e, nn, h = measured
        lines += [f"{e:.4f} {nn:.4f} {h:.4f} {u:.3f} {v:.3f} {image} {name}" for image, (u, v) in seen]
    if len(truth) < n:
        raise ValueError(f"only {len(truth)} of {n} ground points are seen by {min_views} cameras")
    return "\n".join(lines) + "\n", truth


def write_gcps(out: str | Path, scene: Scene, cams: list[Camera], n: int, seed: int, noise_m: float) -> None:
    """``gt/gcp_list.txt`` (what a user hands over) and ``gt/gcps.json`` (the truth)."""
    import json

    text, truth = scene_gcps(scene, cams, n, seed, noise_m)
    gt = Path(out) / "gt"
    gt.mkdir(parents=True, exist_ok=True)
    (gt / "gcp_list.txt").write_text(text)
    (gt / "gcps.json").write_text(
        json.dumps({"crs": CRS, "noise_m": noise_m, "truth": truth}, indent=1) + "\n"
    )
