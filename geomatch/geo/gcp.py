"""A model georeferenced by ground control points, and proved by check points.

Why check points: a fit always matches the points it was fitted to (with 3 points almost exactly),
so a survey is judged at points the fit never saw. Each point is placed in the model by
triangulating its pixel observations in the registered photos (a least-squares intersection of
the viewing rays, then the reprojection error of each observation); a point whose observations do
not meet (a mis-clicked target, a wrong photo) is reported and not used. A similarity from the model
to the points' metric frame (gcpfile.GcpFile.frame) is fitted to the control points; the check
points' residuals after it give the check-point RMSE, horizontal and 3D, as survey reports do.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from .gcpfile import MIN_POINTS, ControlPoint, GcpError, GcpFile
from .similarity import Similarity, umeyama

# observations of one point whose rays miss their intersection by more than this many photo pixels
# (the largest reprojection error) do not meet: a target clicked or named wrong in some photo
MAX_REPROJECTION_PX = 5.0
# rays closer to parallel than this place a point badly along them
MIN_RAY_ANGLE_DEG = 1.0
# the bundle adjustment that holds the control points: a Cauchy loss of this scale (photo pixels) on
# every observation, so that a control point surveyed metres off (handheld GPS, a height of 0 over
# dunes) pulls its photos no harder than a wrong tie point, while exact points pull fully
ADJUST_LOSS_PX = 1.0


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
        if self.adjusted and self.similarity_check_rmse is not None:
            h, d3 = self.similarity_check_rmse
            out["check_rmse_similarity_only_m"] = {"horizontal": round(h, 4), "3d": round(d3, 4)}
        return out


def triangulate(
    rec: pycolmap.Reconstruction, point: ControlPoint
) -> tuple[np.ndarray | None, int, float | None, str | None]:
    """(model xyz, observations in registered photos, largest reprojection px, why not placed)."""
    by_name = {im.name: im for im in rec.images.values() if im.has_pose}
    centres, dirs, views = [], [], []
    for o in point.observations:
        im = by_name.get(o.image)
        if im is None:
            continue
        cam = rec.cameras[im.camera_id]
        # geomatch's pixels have centres at integers, COLMAP's at 0.5
        xy = np.array([[o.pixel[0] + 0.5, o.pixel[1] + 0.5]], np.float64)
        ray_cam = np.append(np.asarray(cam.cam_from_img(xy), np.float64).reshape(2), 1.0)
        world_from_cam = im.cam_from_world().inverse()
        d = world_from_cam.rotation.matrix() @ ray_cam
        centres.append(np.asarray(im.projection_center(), np.float64))
        dirs.append(d / np.linalg.norm(d))
        views.append((im, cam, xy[0]))
    if len(views) < 2:
        return None, len(views), None, f"in {len(views)} registered photo(s): a point needs two"
    # the point nearest to every ray: sum over rays of (I - d d^T) (X - c) = 0
    A, b = np.zeros((3, 3)), np.zeros(3)
    for c, d in zip(centres, dirs, strict=True):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    widest = max(
        float(np.degrees(np.arccos(np.clip(abs(d1 @ d2), -1.0, 1.0))))
        for i, d1 in enumerate(dirs)
        for d2 in dirs[i + 1 :]
    )
    if widest < MIN_RAY_ANGLE_DEG:
        return None, len(views), None, f"its rays meet at {widest:.2f} deg: too narrow to place it"
    X = np.linalg.solve(A, b)
    errors = []
    for im, cam, xy in views:
        pc = im.cam_from_world() * X
        if pc[2] <= 0:
            return None, len(views), None, f"it lies behind {im.name}: its observations do not meet"
        proj = np.asarray(cam.img_from_cam(np.asarray(pc, np.float64).reshape(1, 3)), np.float64).reshape(2)
        errors.append(float(np.linalg.norm(proj - xy)))
    worst = max(errors)
    if worst > MAX_REPROJECTION_PX:
        why = f"its observations do not meet: {worst:.1f} px from the point they place"
        return X, len(views), worst, f"{why} (> {MAX_REPROJECTION_PX:g})"
    return X, len(views), worst, None


def choose_checkpoints(names: Sequence[str], spec: Sequence[str] | int) -> set[str]:
    """The check points: the names given, or ``spec`` of the usable points spread over their
    sorted names (the same choice on every run)."""
    if isinstance(spec, int):
        ordered = sorted(names)
        if spec <= 0:
            return set()
        if spec > len(ordered) - MIN_POINTS:
            raise GcpError(
                f"{spec} check points leave fewer than {MIN_POINTS} control points of {len(ordered)}"
            )
        idx = np.linspace(0, len(ordered) - 1, spec + 2)[1:-1].round().astype(int)
        return {ordered[i] for i in idx}
    unknown = sorted(set(spec) - set(names))
    if unknown:
        raise GcpError(f"check points not among the usable GCPs: {', '.join(unknown)}")
    return set(spec)


def georeference(
    rec: pycolmap.Reconstruction, gcps: GcpFile, checkpoints: Sequence[str] | int = 0
) -> GcpReport:
    """Place every usable point in ``rec``, fit the similarity to the control points, report all."""
    results: list[PointResult] = []
    placed: dict[str, np.ndarray] = {}
    for name, p in sorted(gcps.points.items()):
        X, used, reproj, why = triangulate(rec, p)
        results.append(PointResult(name, "unused", len(p.observations), used, why, reproj))
        if why is None and X is not None:
            placed[name] = X
    for name, why in sorted(gcps.unusable.items()):
        results.append(PointResult(name, "unused", 1, 0, why))
    check = choose_checkpoints(list(placed), checkpoints) if checkpoints else set()
    control = sorted(set(placed) - check)
    if len(control) < MIN_POINTS:
        raise GcpError(
            f"{len(control)} control points placed in the model, and georeferencing needs {MIN_POINTS}: "
            + "; ".join(f"{r.name}: {r.reason}" for r in results if r.reason)
        )
    origin = np.mean([gcps.points[n].xyz for n in placed], axis=0)
    sim = umeyama(
        np.stack([placed[n] for n in control]), np.stack([gcps.points[n].xyz - origin for n in control])
    )
    for r in results:
        if r.name in placed:
            r.role = "check" if r.name in check else "control"
            r.residual = sim.apply(placed[r.name][None])[0] - (gcps.points[r.name].xyz - origin)
    return GcpReport(results, sim, origin)


def adjust_to_control(rec: pycolmap.Reconstruction, gcps: GcpFile, report: GcpReport) -> None:
    """Bundle-adjust ``rec`` (already moved by ``report.similarity``) with the control points as
    fixed 3D points seen in their photos, then judge every point again in the adjusted model.

    Why: a similarity moves the model as a whole, while a model from matching alone bends (a dome
    over a flat site, a drift along a flight line) in ways only points on the ground can correct;
    survey software (Metashape's markers, OpenSfM's GCPs) adjusts with them for that reason. On a
    synthetic scene with exact points this cut the check-point RMSE about fourfold. The check
    points take no part: their observations are not added, and they are triangulated afresh in
    the adjusted cameras. The observations are added to the model only for the adjustment and
    removed after it, so the written model holds the run's own keypoints and points only."""
    control = [p.name for p in report.points if p.role == "control"]
    by_name = {im.name: im.image_id for im in rec.images.values() if im.has_pose}
    appended: dict[int, int] = {}
    added: list[int] = []
    for name in control:
        track = pycolmap.Track()
        for o in gcps.points[name].observations:
            iid = by_name.get(o.image)
            if iid is None:
                continue
            pts = rec.images[iid].points2D
            pts.append(pycolmap.Point2D(np.array([o.pixel[0] + 0.5, o.pixel[1] + 0.5])))
            track.add_element(iid, len(pts) - 1)
            appended[iid] = appended.get(iid, 0) + 1
        added.append(rec.add_point3D(gcps.points[name].xyz - report.origin, track))
    config = pycolmap.BundleAdjustmentConfig()
    for iid in by_name.values():
        config.add_image(iid)
    for pid in added:
        config.add_constant_point(pid)
    options = pycolmap.BundleAdjustmentOptions()
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = ADJUST_LOSS_PX
    options.print_summary = False
    loglevel = int(pycolmap.logging.minloglevel)
    pycolmap.logging.minloglevel = max(loglevel, 2)  # Ceres' report is not the user's business
    try:
        pycolmap.create_default_bundle_adjuster(options, config, rec).solve()
    finally:
        pycolmap.logging.minloglevel = loglevel
        for pid in added:
            rec.delete_point3D(pid)
        for iid, n in appended.items():
            for _ in range(n):
                rec.images[iid].points2D.pop()
    report.similarity_check_rmse = report.rmse("check")
    report.adjusted = True
    for r in report.points:
        if r.role in ("control", "check"):
            X, _, reproj, why = triangulate(rec, gcps.points[r.name])
            r.residual = None if X is None else X - (gcps.points[r.name].xyz - report.origin)
            r.reprojection_px, r.reason = reproj, why


def apply_to_model(
    model_dir: Path,
    gcps: GcpFile,
    checkpoints: Sequence[str] | int = 0,
    ply: Path | None = None,
    adjust: bool = True,
) -> dict[str, Any]:
    """Georeference the model in ``model_dir`` (a run's ``sparse/0``) by ``gcps`` and write it back
    (and its points to ``ply``) moved into the GCPs' metric frame minus the report's ``origin``,
    bundle-adjusted with the control points held (``adjust``, adjust_to_control); returns the
    report as a dict.
    A model the points cannot georeference is left as it was, and the dict says why (``error``):
    the model is still the run's result, only not in the survey's coordinates."""
    rec = pycolmap.Reconstruction(str(model_dir))
    try:
        report = georeference(rec, gcps, checkpoints)
    except GcpError as e:
        return {**gcps.summary(), "error": str(e)}
    rec.transform(report.similarity.to_pycolmap())
    if adjust:
        adjust_to_control(rec, gcps, report)
    rec.write_binary(str(model_dir))
    if (model_dir / "cameras.txt").is_file():
        rec.write_text(str(model_dir))
    if ply is not None:
        rec.export_PLY(str(ply))
    return {**report.as_dict(gcps), "frame_of_model": "the GCPs' frame minus origin"}


def georeference_summary(
    summary: dict[str, Any], out: Path, gcps: GcpFile, checkpoints: Sequence[str] | int = 0
) -> None:
    """Georeference a run's or a reconstruct job's model (``out/sparse/0``) by ``gcps`` and record
    it in its ``summary`` (``gcp``). The GCPs win over GPS: the frame the GPS path put the model in
    moves to ``gps_frame_before_gcp``, and the GPS residuals stay in the summary as measured."""
    model = out / "sparse" / "0"
    if not (model / "images.bin").is_file():
        summary["gcp"] = {**gcps.summary(), "error": "no model to georeference"}
        return
    summary["gcp"] = apply_to_model(model, gcps, checkpoints, out / "points.ply")
    if "error" in summary["gcp"]:
        return
    before = {k: summary.pop(k) for k in ("frame", "origin", "ecef_from_enu", "vertical") if k in summary}
    if before:
        summary["gps_frame_before_gcp"] = before
    summary.update(georeferenced=True, frame="GCP")
