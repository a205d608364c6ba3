"""What a georeferencing by ground control points reports: each point's result (placed, used as
control or check, or why not), the accuracy the adjustment weighed the points at, the whole report
as summary.json's ``gcp``, and a failure recorded the same way (geo.gcp makes them)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .gcpfile import GcpError, GcpFile
from .similarity import Similarity


@dataclass
class PointResult:
    name: str
    role: str  # control | check | unused
    observations: int  # in the file
    used: int  # in registered photos
    reason: str | None = None  # why unused
    reprojection_px: float | None = None  # largest, of the triangulated point
    residual: np.ndarray | None = None  # (3,) metres, fitted model minus the surveyed point

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "name": self.name,
            "role": self.role,
            "observations": self.observations,
            "observations_registered": self.used,
        }
        if self.reason is not None:
            out["reason"] = self.reason
        if self.reprojection_px is not None:
            out["reprojection_px"] = round(self.reprojection_px, 3)
        if self.residual is not None:
            dx, dy, dz = (float(v) for v in self.residual)
            out.update(dx_m=round(dx, 4), dy_m=round(dy, 4), dz_m=round(dz, 4))
            out["horizontal_m"] = round(float(np.hypot(dx, dy)), 4)
            out["3d_m"] = round(float(np.linalg.norm(self.residual)), 4)
        return out


@dataclass(frozen=True)
class Accuracy:
    """The control points' standard deviation per axis, metres: what the adjustment weighs them by.

    ``estimated_*``: what their residuals after the similarity say (None where they say nothing:
    too few points for that component); ``horizontal``/``vertical`` are what was used (the estimate
    above the floor, or the user's)."""

    horizontal: float
    vertical: float
    source: str  # "given" | "estimated"
    estimated_horizontal: float | None = None
    estimated_vertical: float | None = None
    note: str | None = None  # why the estimate was overruled

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "horizontal": round(self.horizontal, 4),
            "vertical": round(self.vertical, 4),
            "source": self.source,
        }
        for key, v in (
            ("estimated_horizontal", self.estimated_horizontal),
            ("estimated_vertical", self.estimated_vertical),
        ):
            if v is not None:
                out[key] = round(v, 4)
        if self.note is not None:
            out["note"] = self.note
        return out


@dataclass
class GcpReport:
    """``similarity``: model -> the file's metric frame minus ``origin`` (the points' mean), kept
    small so that a model written in it keeps its precision in float32 viewers."""

    points: list[PointResult]
    similarity: Similarity
    origin: np.ndarray
    # the check-point RMSE (horizontal, 3D) after the similarity alone, before the adjustment
    similarity_check_rmse: tuple[float, float] | None = None
    adjusted: bool = False
    # the control points' standard deviation per axis (horizontal, vertical) the adjustment held them
    # to, and whether it was given by the user or estimated from their residuals
    accuracy: Accuracy | None = None

    def rmse(self, role: str) -> tuple[float, float] | None:
        """(horizontal, 3D) root mean square residual of the points of ``role``, metres."""
        res = [p.residual for p in self.points if p.role == role and p.residual is not None]
        if not res:
            return None
        r = np.stack(res)
        return float(np.sqrt(np.mean(np.sum(r[:, :2] ** 2, axis=1)))), float(
            np.sqrt(np.mean(np.sum(r**2, axis=1)))
        )

    def as_dict(self, gcps: GcpFile) -> dict[str, Any]:
        out: dict[str, Any] = {
            **gcps.summary(),
            "origin": [float(v) for v in self.origin],
            "points": [p.as_dict() for p in self.points],
        }
        for role in ("control", "check"):
            r = self.rmse(role)
            if r is not None:
                out[f"{role}_rmse_horizontal_m"], out[f"{role}_rmse_3d_m"] = round(r[0], 4), round(r[1], 4)
        out["bundle_adjusted"] = self.adjusted
        if self.accuracy is not None:
            out["accuracy_m"] = self.accuracy.as_dict()
        if self.adjusted and self.similarity_check_rmse is not None:
            h, d3 = self.similarity_check_rmse
            out["check_rmse_similarity_only_m"] = {"horizontal": round(h, 4), "3d": round(d3, 4)}
        return out


class GeoreferenceError(GcpError):
    """The points cannot georeference the model; ``points`` says what became of each."""

    def __init__(self, message: str, points: Sequence[PointResult]) -> None:
        super().__init__(message)
        self.points = list(points)


def failed(gcps: GcpFile | None, error: str, points: Sequence[PointResult] | None = None) -> dict[str, Any]:
    """The summary's ``gcp`` when the points did not georeference the model: the file's summary,
    ``error``, and ``points`` in the shape of a georeferenced one (a dict per point, with its role
    and why it was not used), so that every reader (the reports, the console) reads one shape."""
    if points is None:
        points = []
        if gcps is not None:
            points = [
                PointResult(
                    name, "unused", len(p.observations), 0, "not placed: the model was not georeferenced"
                )
                for name, p in sorted(gcps.points.items())
            ] + [PointResult(name, "unused", 1, 0, why) for name, why in sorted(gcps.unusable.items())]
    for p in points:
        if p.reason is None:
            p.reason = "not used: the points did not georeference the model"
    base = gcps.summary() if gcps is not None else {}
    return {**base, "points": [p.as_dict() for p in points], "error": error}
