"""A run's model read for mapping: registered cameras and 3D points, in the projected CRS the
map is drawn in.

The CRS is the one the ``odm`` / ``laz`` exports write the point cloud in (``export.georef``), so
that the orthophoto, the DSM and the LAZ of one run lie on each other in WebODM. The map grid is
north-up in that CRS while the cameras live in the model's frame (ENU metres around the first
fix, or the GCP frame minus its mean): a ground position goes back into the model's frame exactly
(:meth:`Survey.model_from_projected`) before it is projected into a photo. A model without
georeferencing has no CRS and no known "down": it is refused with a clear message (an orthophoto
in a guessed frame would be a map of nowhere, and a wrong CRS puts it somewhere wrong).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
import pyproj
from scipy.spatial import cKDTree

from ..export.georef import WGS84, ModelFrame, model_frame

MIN_DOWN = 0.5  # sin(30 deg): a photo looking at least this far below the horizon sees the ground
# a surface point lies within this many flight heights (the cameras' median height over the points'
# median) of the nearest camera across, and within one flight height of the median ground up or
# down: what a survey's photos map. Beyond it are the low-parallax points a sparse model triangulates
# far out (brighton_beach_full: 1 % of 7,334 points 60-670 m below the ground and up to 450 m out
# from cameras 85 m apart flying 45 m up), over which the DSM spread to 577 x 503 m and the photos'
# edges smeared across it
REACH_FLIGHTS = 2.0


class OrthoError(ValueError):
    """The run cannot give a map (no model, no georeferencing, no photos, no points)."""


@dataclass(frozen=True)
class View:
    """A registered photo: its pose (cam_from_world in the model frame), its camera, its centre
    in the projected CRS (easting, northing, height)."""

    name: str
    R: np.ndarray  # 3x3
    t: np.ndarray  # 3
    camera: pycolmap.Camera
    centre: np.ndarray  # projected

    @property
    def width(self) -> int:
        return int(self.camera.width)

    @property
    def height(self) -> int:
        return int(self.camera.height)

    @property
    def focal(self) -> float:
        return float(self.camera.mean_focal_length())

    def project(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Model points (N, 3) -> COLMAP pixels (N, 2; pixel centres at .5) and depths (N)."""
        xc = np.asarray(xyz, np.float64) @ self.R.T + self.t
        uv = self.camera.img_from_cam(xc, check_cheirality=False)
        return np.asarray(uv, np.float64).reshape(-1, 2), xc[:, 2]


@dataclass(frozen=True)
class Survey:
    frame: ModelFrame
    views: list[View]
    points: np.ndarray  # (N, 3) projected: easting, northing, height
    colours: np.ndarray  # (N, 3) uint8

    @property
    def crs(self) -> pyproj.CRS:
        return self.frame.crs

    def model_from_projected(self, p: np.ndarray) -> np.ndarray:
        """(N, 3) projected -> model coordinates: the inverse of ``ModelFrame.to_projected``."""
        p = np.asarray(p, np.float64).reshape(-1, 3)
        if self.frame.offset is not None:
            return p - self.frame.offset
        assert self.frame.enu is not None
        to_wgs = pyproj.Transformer.from_crs(self.frame.crs, WGS84, always_xy=True)
        lon, lat = to_wgs.transform(p[:, 0], p[:, 1])
        return self.frame.enu.from_geodetic(np.asarray(lat), np.asarray(lon), p[:, 2])


def good_points(rec: pycolmap.Reconstruction) -> tuple[np.ndarray, np.ndarray]:
    """The model's points that a surface can rest on: seen by two photos or more (every COLMAP
    point is) with a reprojection error under three times the model's median (a loose cut:
    the DSM's own outlier test does the rest)."""
    ids = list(rec.points3D)
    if not ids:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    xyz = np.array([rec.points3D[i].xyz for i in ids], np.float64).reshape(-1, 3)
    rgb = np.array([rec.points3D[i].color for i in ids], np.uint8).reshape(-1, 3)
    err = np.array([rec.points3D[i].error for i in ids], np.float64)
    keep = err <= 3.0 * max(float(np.median(err)), 0.25)
    return xyz[keep], rgb[keep]


def read_survey(model: Path, summary: dict[str, object]) -> Survey:
    """The registered cameras and good points of the model at ``model`` (COLMAP binary), in the
    frame ``summary`` (the run's summary.json) says the model is in."""
    frame = model_frame(summary)
    if frame is None:
        raise OrthoError(
            "the map needs a georeferenced model (photos with GPS fixes, or ground control points): "
            "this model's frame is arbitrary, so it has no CRS and no known down"
        )
    rec = pycolmap.Reconstruction(str(model))
    views = []
    for im in sorted(rec.images.values(), key=lambda i: i.name):
        if not im.has_pose:
            continue
        pose = im.cam_from_world()
        R = np.asarray(pose.rotation.matrix(), np.float64)
        t = np.asarray(pose.translation, np.float64)
        centre = frame.to_projected((-R.T @ t)[None])[0]
        views.append(View(im.name, R, t, rec.cameras[im.camera_id], centre))
    if not views:
        raise OrthoError("the model has no registered photo")
    down = np.array([-v.R[2, 2] for v in views])  # the optical axis' downward share (model z: up)
    if np.mean(down > MIN_DOWN) < 0.5:
        raise OrthoError(
            "the photos do not look down (fewer than half point 30 degrees or more below the "
            "horizon): a map needs an aerial survey"
        )
    xyz, rgb = good_points(rec)
    points = frame.to_projected(xyz)
    keep = within_reach(points, np.array([v.centre for v in views]))
    points, rgb = points[keep], rgb[keep]
    if len(points) < 3:
        raise OrthoError(f"the model has {len(points)} 3D points under its photos: too few for a surface")
    return Survey(frame, views, points, rgb)


def within_reach(points: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Which of ``points`` (projected, up the third axis) lie where the photos taken from
    ``centres`` map the ground (REACH_FLIGHTS); all of them when the cameras are not above the
    points' median (then there is no flight height to judge by)."""
    if not len(points):
        return np.zeros(0, bool)
    ground = float(np.median(points[:, 2]))
    flight = float(np.median(centres[:, 2])) - ground
    if not flight > 0:
        return np.ones(len(points), bool)
    across, _ = cKDTree(centres[:, :2]).query(points[:, :2])
    return (np.abs(points[:, 2] - ground) <= flight) & (across <= REACH_FLIGHTS * flight)


def open_survey(run: Path) -> Survey:
    """The survey of a run folder (``geomatch run``'s OUT, or a service's model folder)."""
    summary_path = run / "summary.json"
    model = run / "sparse" / "0"
    if not summary_path.is_file():
        raise OrthoError(f"{run} is not a run folder (no summary.json): make one with `geomatch run`")
    if not (model / "images.bin").is_file():
        raise OrthoError(f"{run} has no model ({model} is missing: no image was registered)")
    summary = json.loads(summary_path.read_text())
    return read_survey(model, summary)
