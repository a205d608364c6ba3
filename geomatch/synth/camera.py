"""The synthetic scenes' pinhole cameras as COLMAP stores them, and the conversions of their
rotations that the ground-truth model (quaternions) and the drone's XMP (gimbal angles) need.

World frame: metres, z up (East-North-Up outdoors). Camera frame: COLMAP's (x right, y down, z forward);
poses are cam_from_world.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Camera:
    name: str
    K: np.ndarray  # 3x3
    R: np.ndarray  # cam_from_world rotation (COLMAP: x right, y down, z forward)
    t: np.ndarray  # cam_from_world translation
    width: int
    height: int
    aerial: bool

    @property
    def centre(self) -> np.ndarray:
        return -self.R.T @ self.t

    def project(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (pixel centres at integers) and depths of world points (N, 3)."""
        Xc = X @ self.R.T + self.t
        uv = Xc @ self.K.T
        return uv[:, :2] / uv[:, 2:3] - 0.5, Xc[:, 2]


def look_at(
    centre: np.ndarray, target: np.ndarray, up: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world looking from ``centre`` at ``target``; ``up`` is the world direction that
    appears upwards in the image (default: +z, or +y when looking straight down)."""
    f = target - centre
    f = f / np.linalg.norm(f)
    if up is None:
        up = np.array([0.0, 0.0, 1.0]) if abs(f[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    R = np.stack([r, d, f])
    return R, -R @ centre


def rotmat_to_qvec(R: np.ndarray) -> np.ndarray:
    """Hamilton quaternion (w, x, y, z), COLMAP's convention."""
    K = (
        np.array(
            [
                [R[0, 0] - R[1, 1] - R[2, 2], 0, 0, 0],
                [R[1, 0] + R[0, 1], R[1, 1] - R[0, 0] - R[2, 2], 0, 0],
                [R[2, 0] + R[0, 2], R[2, 1] + R[1, 2], R[2, 2] - R[0, 0] - R[1, 1], 0],
                [R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], R[0, 0] + R[1, 1] + R[2, 2]],
            ]
        )
        / 3.0
    )
    vals, vecs = np.linalg.eigh(K)
    q = vecs[[3, 0, 1, 2], np.argmax(vals)]
    return q if q[0] >= 0 else -q


def gimbal_angles(R: np.ndarray) -> tuple[float, float, float]:
    """DJI's gimbal pitch, yaw and roll (degrees) of a camera ``R`` (world -> camera, world ENU,
    camera x right, y down, z forward). Pitch: the optical axis above the horizon (-90 nadir).
    Yaw: clockwise from north, of the image's top-forward direction (the optical axis for a
    level view, the image top for a nadir one: where the drone heads). Roll: positive when the
    image's right side is down. metadata.gimbal_rotation is the inverse."""
    pitch = float(np.degrees(np.arcsin(np.clip(R[2, 2], -1, 1))))
    heading = R[2, :2] - R[1, :2]  # forward minus down, horizontal: the heading at any pitch
    yaw = float(np.degrees(np.arctan2(heading[0], heading[1])))
    roll = float(np.degrees(np.arctan2(-R[0, 2], -R[1, 2]))) if abs(R[2, 2]) < 0.999 else 0.0
    return pitch, yaw, roll
