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
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from .gcpfile import MIN_POINTS, ControlPoint, GcpError, GcpFile, degenerate
from .gcpreport import Accuracy, GcpReport, GeoreferenceError, PointResult, failed
from .georef import GNSS_VERTICAL_FACTOR
from .similarity import umeyama

# observations of one point whose rays miss their intersection by more than this many photo pixels
# (the largest reprojection error) do not meet: a target clicked or named wrong in some photo
MAX_REPROJECTION_PX = 5.0
# rays closer to parallel than this place a point badly along them
MIN_RAY_ANGLE_DEG = 1.0
# no survey places a target better than this (RTK on a painted target, and the click on it): however
# well a handful of points happen to fit, the adjustment never holds them tighter
MIN_ACCURACY_M = 0.02
# control heights closer together than this are one height written for all of them
SAME_HEIGHT_M = 0.001
# a control point's prior enters the bundle adjustment through two constant virtual cameras this many
# sigmas away from it (east and north of it, looking at it): 1 px in them is 1 sigma, and the
# perspective's bend over a few sigmas of offset is a few parts in a thousand of the prior's weight
PRIOR_OBSERVER_SIGMAS = 1000.0
# the photos' observations are weighed at the model's own reprojection noise, never below this (a
# model of exact synthetic pixels would otherwise weigh every prior at nothing)
MIN_PIXEL_SIGMA = 0.1
# a fit whose control points miss by more than this share of their own spread explains nothing:
# the clicks and the survey describe different places (names swapped over the whole file, a wrong
# coordinate system), and writing the model in that frame would call a wrong model georeferenced
MAX_CONTROL_RMSE_SHARE = 0.5


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
        shown = ", ".join(n if len(n) <= 40 else n[:37] + "..." for n in unknown[:10])
        more = f" and {len(unknown) - 10} more" if len(unknown) > 10 else ""
        raise GcpError(f"check points not among the usable GCPs: {shown}{more}")
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
        raise GeoreferenceError(
            f"{len(control)} control points placed in the model, and georeferencing needs {MIN_POINTS}: "
            + "; ".join(f"{r.name}: {r.reason}" for r in results if r.reason),
            results,
        )
    surveyed = np.stack([gcps.points[n].xyz for n in control])
    in_model = np.stack([placed[n] for n in control])
    why = degenerate(surveyed)
    if why is not None:
        raise GeoreferenceError(f"the {len(control)} control points cannot fix the model: {why}", results)
    why = degenerate(in_model, min_spread=0.0)
    if why is not None:
        raise GeoreferenceError(f"the control points as the photos place them: {why}", results)
    origin = np.mean([gcps.points[n].xyz for n in placed], axis=0)
    sim = umeyama(in_model, surveyed - origin)
    finite = np.isfinite(sim.R).all() and np.isfinite(sim.t).all()
    if not (finite and np.isfinite(sim.scale) and sim.scale > 0):
        raise GeoreferenceError(
            f"the similarity to the control points has no finite scale ({sim.scale})", results
        )
    for r in results:
        if r.name in placed:
            r.role = "check" if r.name in check else "control"
            r.residual = sim.apply(placed[r.name][None])[0] - (gcps.points[r.name].xyz - origin)
    report = GcpReport(results, sim, origin)
    spread = float(np.sqrt(np.mean(np.sum((surveyed - surveyed.mean(axis=0)) ** 2, axis=1))))
    rmse = report.rmse("control")
    if rmse is None or not np.isfinite(rmse[1]) or rmse[1] > MAX_CONTROL_RMSE_SHARE * spread:
        for r in results:
            r.role, r.residual = "unused", None
            r.reason = r.reason or "not used: the control points do not fit the model"
        shown = "not finite" if rmse is None or not np.isfinite(rmse[1]) else f"{rmse[1]:.3g} m"
        raise GeoreferenceError(
            f"the control points do not fit the model: their RMSE is {shown} over a spread of {spread:.3g} m "
            "(names or coordinates that do not belong to the clicks?)",
            results,
        )
    return report


def estimate_accuracy(report: GcpReport, gcps: GcpFile) -> Accuracy:
    """How well the control points were surveyed, horizontal and vertical, from their own residuals
    after the similarity: the sum of squared residuals over the redundancy of each component (the
    count of residuals less the share the 7 parameters absorbed, 1 - leverage per residual), as
    a variance-component estimate does.

    Why: ODM's gcp_list.txt says nothing of its points' accuracy, and files range from RTK
    centimetres to a handheld fix averaged over minutes with every height 0.0; holding the latter
    as exact bends the photos' geometry to fit the survey's noise. Horizontal and vertical apart:
    a height of 0.0 everywhere over dunes is metres off while the same points' eastings and
    northings are good to a metre. The residuals also hold the model's own error, so over a bent
    model the points are weighed a little looser than their survey: the adjustment then gives
    way to the photos, which is the side to err on."""
    names = [p.name for p in report.points if p.role == "control" and p.residual is not None]
    v = np.stack([r.residual for r in report.points if r.name in names and r.residual is not None])
    fitted = np.stack([gcps.points[n].xyz - report.origin for n in names]) + v
    c = fitted - fitted.mean(axis=0)
    # d(residual) / d(scale, rotation, translation) at the fit, about the points' centroid
    J = np.zeros((3 * len(names), 7))
    for i, ci in enumerate(c):
        J[3 * i : 3 * i + 3, 0] = ci
        J[3 * i : 3 * i + 3, 1:4] = -np.array([[0, -ci[2], ci[1]], [ci[2], 0, -ci[0]], [-ci[1], ci[0], 0]])
        J[3 * i : 3 * i + 3, 4:7] = np.eye(3)
    leverage = np.einsum("ij,ji->i", J, np.linalg.pinv(J.T @ J) @ J.T)
    redundancy = np.clip(1.0 - leverage, 0.0, 1.0).reshape(-1, 3)
    r_h, r_v = float(redundancy[:, :2].sum()), float(redundancy[:, 2].sum())
    # under half a residual's worth of redundancy the component says nothing (3 points: 2 in all)
    est_h = float(np.sqrt((v[:, :2] ** 2).sum() / r_h)) if r_h >= 0.5 else None
    est_v = float(np.sqrt((v[:, 2] ** 2).sum() / r_v)) if r_v >= 0.5 else None
    h = est_h if est_h is not None else est_v
    vert = est_v if est_v is not None else h
    horizontal = max(h if h is not None else MIN_ACCURACY_M, MIN_ACCURACY_M)
    vertical = max(vert if vert is not None else MIN_ACCURACY_M, MIN_ACCURACY_M)
    heights = [float(gcps.points[n].xyz[2]) for n in names]
    note = None
    if max(heights) - min(heights) < SAME_HEIGHT_M:
        # one height for every point (0.0 in files whose heights nobody surveyed): the similarity
        # lays the model's plane through them and the residuals say nothing of the vertical, which
        # is then no better than the horizontal of a GNSS fix
        vertical = max(vertical, GNSS_VERTICAL_FACTOR * horizontal)
        note = f"every control point's height is {heights[0]:g}: not surveyed"
    return Accuracy(horizontal, vertical, "estimated", est_h, est_v, note)


def given_accuracy(metres: float | tuple[float, float]) -> Accuracy:
    """The user's accuracy (one value for both components, or horizontal and vertical), held as
    given: a surveyor who states it knows the instrument."""
    h, v = (metres, metres) if isinstance(metres, float | int) else metres
    if not (h > 0 and v > 0 and np.isfinite(h) and np.isfinite(v)):
        raise GcpError(f"a GCP accuracy must be a positive number of metres, not {metres}")
    return Accuracy(float(h), float(v), "given")


def _rotation_looking_along(axis: int) -> np.ndarray:
    """cam_from_world rotation of a camera looking along -``axis`` (0: x, 1: y) of the world, its
    image x along the other horizontal axis and its image y vertical (right-handed)."""
    if axis == 0:  # looks west: image x = north, image y = down
        return np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])
    return np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # looks south


def _add_prior_observers(
    work: pycolmap.Reconstruction, xyz: np.ndarray, acc: Accuracy, pixel_sigma: float, track: pycolmap.Track
) -> None:
    """Two constant cameras that see ``xyz`` at their principal point, one east and one north of
    it, in which one sigma of the point's prior is ``pixel_sigma`` pixels (the photos' own noise):
    together a Gaussian prior on the point's position (horizontal sigma on x and y, vertical on z)
    weighed against the photos' observations as a weighted adjustment weighs them, in the only
    residual pycolmap's bundle adjuster takes from Python, the reprojection error. Both see z, so
    their vertical focal length is 1/sqrt(2) of one sigma's."""
    distance = PRIOR_OBSERVER_SIGMAS * max(acc.horizontal, acc.vertical)
    fx, fy = distance * pixel_sigma / acc.horizontal, distance * pixel_sigma / (acc.vertical * np.sqrt(2.0))
    for axis in (0, 1):
        # a trivial rig takes the camera's id and a trivial frame the image's: ids free in all
        cam_id = max([*work.cameras, *work.rigs], default=0) + 1
        work.add_camera_with_trivial_rig(
            pycolmap.Camera(
                camera_id=cam_id, model="PINHOLE", width=1000, height=1000, params=[fx, fy, 500.0, 500.0]
            )
        )
        R = _rotation_looking_along(axis)
        centre = np.asarray(xyz, np.float64) + distance * np.eye(3)[axis]
        image_id = max([*work.images, *work.frames], default=0) + 1
        image = pycolmap.Image(
            name=f"prior {image_id}",
            keypoints=np.array([[500.0, 500.0]]),
            camera_id=cam_id,
            image_id=image_id,
        )
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(R), (-R @ centre).reshape(3, 1))
        work.add_image_with_trivial_frame(image, pose)
        track.add_element(image_id, 0)


def adjust_to_control(
    rec: pycolmap.Reconstruction,
    gcps: GcpFile,
    report: GcpReport,
    accuracy: float | tuple[float, float] | None = None,
) -> None:
    """Bundle-adjust ``rec`` (already moved by ``report.similarity``) with each control point a
    3D point seen in its photos and held near its surveyed position by a prior of the points'
    accuracy (``accuracy`` metres, one value or horizontal and vertical, else estimate_accuracy),
    then judge every point again in the adjusted model.

    Why: a similarity moves the model as a whole, while a model from matching alone bends (a dome
    over a flat site, a drift along a flight line) in ways only points on the ground can correct;
    survey software (Metashape's markers, OpenSfM's GCPs) adjusts with them for that reason, each
    weighed by its accuracy. Held as exact, metre-level points (averaged handheld GPS, heights of
    0.0) bent a model so that the clicks of points outside the fit no longer met (7.7 px on copr);
    as priors they move the model only as far as the photos allow, and exact points still pull
    it onto them. The check points take no part: their observations are not added, and they are
    triangulated afresh in the adjusted cameras. The adjustment runs on a copy that holds the
    points, their clicks and the prior's cameras, and only the cameras, poses and 3D points come
    back, so the written model holds the run's own keypoints and points only."""
    acc = given_accuracy(accuracy) if accuracy is not None else estimate_accuracy(report, gcps)
    control = [p.name for p in report.points if p.role == "control"]
    work = pycolmap.Reconstruction(rec)
    # the photos' noise per axis: a 2D Gaussian's mean error norm is sqrt(pi / 2) of its sigma
    pixel_sigma = max(float(rec.compute_mean_reprojection_error()) / np.sqrt(np.pi / 2), MIN_PIXEL_SIGMA)
    by_name = {im.name: im.image_id for im in work.images.values() if im.has_pose}
    real_cameras = {im.camera_id for im in work.images.values() if im.has_pose}
    first_virtual = max([*work.images, *work.frames], default=0) + 1
    for name in control:
        track = pycolmap.Track()
        for o in gcps.points[name].observations:
            iid = by_name.get(o.image)
            if iid is None:
                continue
            pts = work.images[iid].points2D
            pts.append(pycolmap.Point2D(np.array([o.pixel[0] + 0.5, o.pixel[1] + 0.5])))
            track.add_element(iid, len(pts) - 1)
        surveyed = gcps.points[name].xyz - report.origin
        _add_prior_observers(work, surveyed, acc, pixel_sigma, track)
        # starts where its clicks meet, not at the survey: the prior, not the start, pulls it there
        placed, *_ = triangulate(work, gcps.points[name])
        work.add_point3D(surveyed if placed is None else placed, track)
    config = pycolmap.BundleAdjustmentConfig()
    for im in work.images.values():
        if not im.has_pose:
            continue
        config.add_image(im.image_id)
        if im.image_id >= first_virtual:
            config.set_constant_rig_from_world_pose(im.frame_id)
            config.set_constant_cam_intrinsics(im.camera_id)
    options = pycolmap.BundleAdjustmentOptions()
    # squared residuals: a prior is Gaussian only under a squared loss, and the model's tie points
    # passed the mapper's reprojection filter already
    options.ceres.loss_function_type = pycolmap.LossFunctionType.TRIVIAL
    options.print_summary = False
    loglevel = int(pycolmap.logging.minloglevel)
    pycolmap.logging.minloglevel = max(loglevel, 2)  # Ceres' report is not the user's business
    try:
        pycolmap.create_default_bundle_adjuster(options, config, work).solve()
    finally:
        pycolmap.logging.minloglevel = loglevel
    for cid in real_cameras:
        rec.cameras[cid].params = list(work.cameras[cid].params)
    for fid, frame in rec.frames.items():
        if frame.has_pose:
            frame.rig_from_world = work.frames[fid].rig_from_world
    for pid, point in rec.points3D.items():
        point.xyz = work.points3D[pid].xyz
    report.similarity_check_rmse = report.rmse("check")
    report.adjusted = True
    report.accuracy = acc
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
    accuracy: float | tuple[float, float] | None = None,
) -> dict[str, Any]:
    """Georeference the model in ``model_dir`` (a run's ``sparse/0``) by ``gcps`` and write it back
    (and its points to ``ply``) moved into the GCPs' metric frame minus the report's ``origin``,
    bundle-adjusted with the control points held to ``accuracy`` metres or to what their residuals
    say (``adjust``, adjust_to_control); returns the report as a dict.
    A model the points cannot georeference is left as it was, and the dict says why (``error``):
    the model is still the run's result, only not in the survey's coordinates."""
    rec = pycolmap.Reconstruction(str(model_dir))
    try:
        report = georeference(rec, gcps, checkpoints)
    except GeoreferenceError as e:
        return failed(gcps, str(e), e.points)
    except GcpError as e:
        return failed(gcps, str(e))
    rec.transform(report.similarity.to_pycolmap())
    if adjust:
        adjust_to_control(rec, gcps, report, accuracy)
    why = _not_finite(rec, report)
    if why is not None:  # nothing written: the model on disk stays in the mapping's frame
        for r in report.points:
            r.role, r.residual = "unused", None
        return failed(
            gcps, f"the georeferenced model is not finite ({why}): it was left as mapped", report.points
        )
    rec.write_binary(str(model_dir))
    if (model_dir / "cameras.txt").is_file():
        rec.write_text(str(model_dir))
    if ply is not None:
        rec.export_PLY(str(ply))
    return {**report.as_dict(gcps), "frame_of_model": "the GCPs' frame minus origin"}


def _not_finite(rec: pycolmap.Reconstruction, report: GcpReport) -> str | None:
    """What of a moved model is NaN or infinite, None when every number is finite: checked before
    it is written, since a model of NaN cameras called georeferenced is worse than none."""
    for r in report.points:
        if r.residual is not None and not np.isfinite(r.residual).all():
            return f"the residual of {r.name}"
    for frame in rec.frames.values():
        if frame.has_pose and not np.isfinite(np.asarray(frame.rig_from_world.matrix())).all():
            return "a camera pose"
    for cam in rec.cameras.values():
        if not np.isfinite(np.asarray(cam.params, np.float64)).all():
            return "a camera's intrinsics"
    if rec.points3D:
        xyz = np.stack([np.asarray(p.xyz, np.float64) for p in rec.points3D.values()])
        if not np.isfinite(xyz).all():
            return "the 3D points"
    return None


def georeference_summary(
    summary: dict[str, Any],
    out: Path,
    gcps: GcpFile,
    checkpoints: Sequence[str] | int = 0,
    accuracy: float | tuple[float, float] | None = None,
) -> None:
    """Georeference a run's or a reconstruct job's model (``out/sparse/0``) by ``gcps`` and record
    it in its ``summary`` (``gcp``). The GCPs win over GPS: the frame the GPS path put the model in
    moves to ``gps_frame_before_gcp``, and the GPS residuals stay in the summary as measured."""
    model = out / "sparse" / "0"
    if not (model / "images.bin").is_file():
        summary["gcp"] = failed(gcps, "no model to georeference")
        return
    summary["gcp"] = apply_to_model(model, gcps, checkpoints, out / "points.ply", accuracy=accuracy)
    if "error" in summary["gcp"]:
        return
    before = {k: summary.pop(k) for k in ("frame", "origin", "ecef_from_enu", "vertical") if k in summary}
    if before:
        summary["gps_frame_before_gcp"] = before
    summary.update(georeferenced=True, frame="GCP")
