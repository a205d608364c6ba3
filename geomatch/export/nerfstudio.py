"""nerfstudio's ``transforms.json``, as nerfstudio's own ``colmap_to_json`` writes it.

Poses: COLMAP's world-to-camera inverted to camera-to-world, the camera's y and z axes
negated (OpenCV's right-down-forward to OpenGL's right-up-back), then the world's axes
permuted to nerfstudio's z-up (rows y and z swapped, the new z negated) and that world change
recorded as ``applied_transform``, so that ``ns-train nerfacto --data DIR`` treats the folder
exactly like one made by ``ns-process-data``. Intrinsics use nerfstudio's OPENCV model (fl_x,
fl_y, cx, cy, k1, k2, p1, p2), at the top level when every image shares one camera and per
frame otherwise. Images are copied to ``images/`` (nerfstudio resolves ``file_path`` against
the folder of transforms.json), and the points go to ``sparse_pc.ply`` in nerfstudio's world,
which its splatting methods use as their initial points.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from .source import Source

# nerfstudio's world from COLMAP's: x stays, y <- z, z <- -y (colmap_utils.colmap_to_json)
APPLIED_TRANSFORM = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0]])
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0])


def camera_params(camera: pycolmap.Camera) -> dict[str, Any]:
    """nerfstudio's intrinsics of a COLMAP camera (its parse_colmap_camera_params)."""
    p = [float(v) for v in camera.params]
    name = camera.model.name
    out: dict[str, Any] = {"w": int(camera.width), "h": int(camera.height)}
    if name in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        f, cx, cy, *k = p
        out.update(fl_x=f, fl_y=f, cx=cx, cy=cy)
        k = [*k, 0.0, 0.0][:2]
        out.update(k1=k[0], k2=k[1], p1=0.0, p2=0.0)
    elif name in ("PINHOLE", "OPENCV"):
        fx, fy, cx, cy, *d = p
        d = [*d, 0.0, 0.0, 0.0, 0.0][:4]
        out.update(fl_x=fx, fl_y=fy, cx=cx, cy=cy, k1=d[0], k2=d[1], p1=d[2], p2=d[3])
    else:
        raise ValueError(f"camera model {name} has no nerfstudio equivalent here")
    out["camera_model"] = "OPENCV"
    return out


def camera_to_world(cam_from_world: pycolmap.Rigid3d) -> np.ndarray:
    """nerfstudio's 4x4 ``transform_matrix`` of a COLMAP pose."""
    w2c = np.eye(4)
    w2c[:3, :] = cam_from_world.matrix()
    c2w = np.linalg.inv(w2c)
    c2w[:3, :3] = c2w[:3, :3] @ OPENCV_TO_OPENGL  # columns 1 and 2 negated
    c2w = c2w[[0, 2, 1, 3], :]
    c2w[2, :] *= -1
    return c2w


def _write_points(rec: pycolmap.Reconstruction, path: Path) -> None:
    ids = sorted(rec.points3D)
    xyz = np.array([rec.points3D[i].xyz for i in ids], dtype=float).reshape(-1, 3)
    rgb = np.array([rec.points3D[i].color for i in ids], dtype=np.uint8).reshape(-1, 3)
    xyz = xyz @ APPLIED_TRANSFORM[:, :3].T + APPLIED_TRANSFORM[:, 3]
    lines = [
        "ply",
        "format ascii 1.0",
        f"element vertex {len(ids)}",
        *(f"property float {a}" for a in "xyz"),
        *(f"property uint8 {c}" for c in ("red", "green", "blue")),
        "end_header",
    ]
    rows = (f"{x:.8f} {y:.8f} {z:.8f} {r} {g} {b}" for (x, y, z), (r, g, b) in zip(xyz, rgb, strict=True))
    path.write_text("\n".join([*lines, *rows]) + "\n")


def write(source: Source, dest: Path) -> list[Path]:
    assert source.images is not None  # checked by export()
    rec = pycolmap.Reconstruction(str(source.model))
    dest.mkdir(parents=True, exist_ok=True)
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    shared = len({im.camera_id for im in images}) == 1
    out: dict[str, Any] = camera_params(rec.cameras[images[0].camera_id]) if shared and images else {}
    frames = []
    written: list[Path] = []
    for im in images:
        copy = dest / "images" / im.name
        copy.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(source.images / im.name, copy)
        written.append(copy)
        frame: dict[str, Any] = {
            "file_path": f"images/{im.name}",
            "transform_matrix": camera_to_world(im.cam_from_world()).tolist(),
            "colmap_im_id": int(im.image_id),
        }
        if not shared:
            frame.update(camera_params(rec.cameras[im.camera_id]))
        frames.append(frame)
    out["frames"] = frames
    out["applied_transform"] = APPLIED_TRANSFORM.tolist()
    _write_points(rec, dest / "sparse_pc.ply")
    out["ply_file_path"] = "sparse_pc.ply"
    (dest / "transforms.json").write_text(json.dumps(out, indent=2) + "\n")
    return [dest / "transforms.json", dest / "sparse_pc.ply", *written]
