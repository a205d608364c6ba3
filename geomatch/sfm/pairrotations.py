"""The relative rotations of a database's verified pairs: what the view-graph check judges.

Each pair's rotations come from its verified inliers: an essential matrix on normalised
coordinates (each image's COLMAP camera, distortion included) with RANSAC and the cheirality
check, COLMAP's own two-view pose, and the homography's decompositions; a pair keeps all the
distinct candidates, since on a flat site with little parallax one estimator alone can pick the
wrong solution for a right pair.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
import pycolmap

from ..imageio import working_scale
from . import pair_threads


def rotation_angle(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def candidate_rotations(
    cam0: pycolmap.Camera,
    cam1: pycolmap.Camera,
    kp0: np.ndarray,
    kp1: np.ndarray,
    geometry: pycolmap.TwoViewGeometry,
) -> list[np.ndarray]:
    """The rotations R (x1 ~ R x0 + t) a pair's inliers admit: the essential matrix's (OpenCV),
    COLMAP's own two-view pose, and the homography's decompositions. One estimate is not enough:
    aerial x ground pairs see a mostly flat site with little parallax, where each estimator alone
    picks a wrong solution on some right pairs; among all the candidates a right pair has one
    close to the truth, and the loop and tree checks pick it."""
    m = geometry.inlier_matches
    p0, p1 = kp0[m[:, 0]].astype(np.float64), kp1[m[:, 1]].astype(np.float64)
    n0 = np.asarray(cam0.cam_from_img(p0), np.float64)
    n1 = np.asarray(cam1.cam_from_img(p1), np.float64)
    focal = float(np.mean([cam0.mean_focal_length(), cam1.mean_focal_length()]))
    # the thresholds are in working pixels (imageio.WORKING_SIDE): on a 4000 px original one photo
    # pixel is a fraction of the points' precision, and a RANSAC that finds few inliers at it runs
    # all its iterations (as it did on brighton's originals, slowing the view graph)
    side = max(cam0.width, cam0.height, cam1.width, cam1.height)
    focal /= working_scale(side)
    out: list[np.ndarray] = []
    # USAC rather than plain RANSAC: with a calibration from EXIF only part of the verified inliers
    # fit an essential matrix at one pixel, so plain RANSAC ran all its iterations on every pair;
    # USAC's local optimisation stops early, and the candidates it gives are as near the peer's
    # model (docs/benchmarks.md, "Drone surveys", "Where the time goes")
    E, mask = cv2.findEssentialMat(n0, n1, np.eye(3), cv2.USAC_DEFAULT, 0.999, 1.0 / focal)
    if E is not None and E.shape == (3, 3):
        n, R, _, _ = cv2.recoverPose(E, n0, n1, np.eye(3), mask=mask)
        if n >= 8:
            out.append(R)
    # sets geometry.cam2_from_cam1 on the caller's copy read from the database; nothing is written
    if (
        pycolmap.estimate_two_view_geometry_pose(
            cam0, kp0.astype(np.float64), cam1, kp1.astype(np.float64), geometry
        )
        and geometry.cam2_from_cam1 is not None  # what a successful estimate sets
    ):
        out.append(geometry.cam2_from_cam1.rotation.matrix())
    H, _ = cv2.findHomography(n0, n1, cv2.RANSAC, 2.0 / focal)
    if H is not None:
        out.extend(cv2.decomposeHomographyMat(H, np.eye(3))[1])
    unique: list[np.ndarray] = []
    for R in out:
        if all(rotation_angle(R.T @ U) > 0.5 for U in unique):
            unique.append(np.asarray(R, np.float64))
    return unique


def verified_rotations(
    db: pycolmap.Database, min_inliers: int
) -> tuple[dict[tuple[int, int], list[np.ndarray]], dict[tuple[int, int], int]]:
    """Candidate rotations and inlier counts of the verified pairs, keyed (i, j) with i < j."""
    images = {im.image_id: im for im in db.read_all_images()}
    cameras = {c.camera_id: c for c in db.read_all_cameras()}
    keypoints: dict[int, np.ndarray] = {}

    def kp(i: int) -> np.ndarray:
        if i not in keypoints:
            keypoints[i] = db.read_keypoints(i)[:, :2]
        return keypoints[i]

    jobs: list[
        tuple[int, int, pycolmap.TwoViewGeometry, pycolmap.Camera, pycolmap.Camera, np.ndarray, np.ndarray]
    ] = []
    pair_ids, geometries = db.read_two_view_geometries()
    for pid, g in zip(pair_ids, geometries, strict=True):
        if len(g.inlier_matches) < min_inliers:
            continue
        a, b = pycolmap.pair_id_to_image_pair(pid)
        jobs.append((a, b, g, cameras[images[a].camera_id], cameras[images[b].camera_id], kp(a), kp(b)))
    # one pair's RANSACs run single-threaded in OpenCV and release the GIL: the pairs go side by
    # side on the cores (each RANSAC seeds its own generator, so the result does not depend on it)
    with ThreadPoolExecutor(max_workers=pair_threads()) as pool:
        found = list(pool.map(lambda j: candidate_rotations(j[3], j[4], j[5], j[6], j[2]), jobs))
    out: dict[tuple[int, int], list[np.ndarray]] = {}
    inliers: dict[tuple[int, int], int] = {}
    for (a, b, g, *_), rs in zip(jobs, found, strict=True):
        if rs:
            key = (min(a, b), max(a, b))
            out[key] = rs if a < b else [R.T for R in rs]
            inliers[key] = len(g.inlier_matches)
    return out, inliers
