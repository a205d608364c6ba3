"""``geomatch export``: every format written from a real run and read back by its consumer's
library (pycolmap, h5py) or by a reader that follows the consumer's published format.

The run is the session's one run of the small scene (tests/small_scene.py, tests/conftest.py's
``small_run``: 2 aerial + 4 ground, 640 px, georeferenced), copied once here since the exports
are written into the run's folder.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pycolmap
import pytest

from geomatch.cli import main
from geomatch.export import FORMATS
from geomatch.sfm.colmapdb import COLMAP_OFFSET  # the database side of the convention

from .loaded_modules import loaded_after
from .small_scene import copy_of_run

MAP_FORMATS = ("orthophoto", "dsm", "map-preview")  # the map's files, which a run makes on request
# nerfstudio's world from COLMAP's, as its colmap_to_json writes it: (x, y, z) -> (x, z, -y)
NERFSTUDIO_APPLIED = [[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0]]


@pytest.fixture(scope="module")
def run_dir(small_run: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return copy_of_run(small_run, tmp_path_factory.mktemp("export") / "run")


@pytest.fixture(scope="module")
def rec(run_dir: Path) -> pycolmap.Reconstruction:
    r = pycolmap.Reconstruction(str(run_dir / "sparse" / "0"))
    assert r.num_reg_images() >= 3 and r.num_points3D() > 100  # a model worth exporting
    return r


@pytest.fixture(scope="module")
def exported(run_dir: Path) -> dict[str, Path]:
    """Each format exported once by the command, as a user runs it (no --images: the run's folder)."""
    out = {}
    for fmt in FORMATS:
        if fmt in MAP_FORMATS:  # the map's files: this run made none (tests/test_ortho.py has them)
            assert main(["export", str(run_dir), "--format", fmt]) == 2, fmt
            continue
        assert main(["export", str(run_dir), "--format", fmt]) == 0, fmt
        out[fmt] = run_dir / "export" / fmt
    return out


def registered(rec: pycolmap.Reconstruction) -> list[pycolmap.Image]:
    return sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)


def read_ply(path: Path) -> tuple[dict[str, int], np.ndarray]:
    """A PLY reader that follows the published format: the header's elements and properties,
    then the vertices (binary little-endian or ASCII) as a structured array."""
    types = {"float": "f4", "float32": "f4", "double": "f8", "float64": "f8", "uchar": "u1", "uint8": "u1"}
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    assert header[0] == "ply"
    fmt = header[1].split()[1]
    counts: dict[str, int] = {}
    fields: list[tuple[str, str]] = []
    for line in header:
        parts = line.split()
        if parts[0] == "element":
            counts[parts[1]] = int(parts[2])
        elif parts[0] == "property":
            fields.append((parts[2], types[parts[1]]))
    if fmt == "binary_little_endian":
        dtype = np.dtype([(n, "<" + t) for n, t in fields])
        assert len(data) - end == counts["vertex"] * dtype.itemsize  # nothing missing, nothing extra
        return counts, np.frombuffer(data[end:], dtype)
    assert fmt == "ascii"
    rows = [ln.split() for ln in data[end:].decode("ascii").splitlines() if ln.strip()]
    assert len(rows) == counts["vertex"]
    table = np.zeros(len(rows), np.dtype([(n, t) for n, t in fields]))
    for i, (n, _) in enumerate(fields):
        table[n] = [r[i] for r in rows]
    return counts, table


# -- the command ---------------------------------------------------------------------------------
@pytest.mark.unit
def test_export_of_a_folder_without_a_model_fails_clearly(tmp_path: Path, capsys) -> None:
    assert main(["export", str(tmp_path), "--format", "ply"]) == 2
    assert "not a run folder" in capsys.readouterr().err
    (tmp_path / "summary.json").write_text(json.dumps({"registered": 0}))
    assert main(["export", str(tmp_path), "--format", "nerfstudio"]) == 2
    assert "has no model" in capsys.readouterr().err
    assert not (tmp_path / "export").exists()  # nothing half-written


@pytest.mark.pipeline
def test_export_prints_what_it_wrote_and_honours_to(run_dir: Path, rec, tmp_path: Path, capsys) -> None:
    dest = tmp_path / "text"
    assert main(["export", str(run_dir), "--format", "colmap-text", "--to", str(dest)]) == 0
    printed = capsys.readouterr().out
    assert str(dest) in printed and "images.txt" in printed
    assert {"cameras.txt", "images.txt", "points3D.txt"} <= {p.name for p in dest.iterdir()}
    # exporting again replaces the folder whole: a stray file from before is gone
    (dest / "stray.txt").write_text("x")
    assert main(["export", str(run_dir), "--format", "colmap-text", "--to", str(dest)]) == 0
    assert not (dest / "stray.txt").exists() and (dest / "images.txt").is_file()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left


@pytest.mark.pipeline
def test_export_needs_the_images_it_copies(run_dir: Path, tmp_path: Path, capsys) -> None:
    missing = tmp_path / "gone"
    args = ["export", str(run_dir), "--format", "openmvs", "--to", str(tmp_path / "o")]
    assert main([*args, "--images", str(missing)]) == 2
    assert "needs the run's images" in capsys.readouterr().err and not (tmp_path / "o").exists()


@pytest.mark.pipeline
def test_unknown_format_is_refused_by_the_parser(run_dir: Path, capsys) -> None:
    with pytest.raises(SystemExit) as e:
        main(["export", str(run_dir), "--format", "obj"])
    assert e.value.code == 2 and "invalid choice" in capsys.readouterr().err


# -- nerfstudio ----------------------------------------------------------------------------------
@pytest.mark.pipeline
def test_nerfstudio_round_trip(exported, rec, run_dir: Path) -> None:
    """Undo nerfstudio's convention from what the file itself says (``applied_transform``, as
    nerfstudio's dataparser reads it) and land on pycolmap's poses."""
    d = exported["nerfstudio"]
    t = json.loads((d / "transforms.json").read_text())
    images = registered(rec)
    assert [f["file_path"] for f in t["frames"]] == [f"images/{im.name}" for im in images]
    assert t["applied_transform"] == NERFSTUDIO_APPLIED  # nerfstudio's z-up world, not ours
    applied = np.vstack([np.array(t["applied_transform"]), [0, 0, 0, 1]])
    image_dir = Path(json.loads((run_dir / "summary.json").read_text())["image_dir"])
    for frame, im in zip(t["frames"], images, strict=True):
        c2w = np.linalg.inv(applied) @ np.array(frame["transform_matrix"])  # back to COLMAP's world
        assert np.allclose(c2w[3], [0, 0, 0, 1])
        centre = c2w[:3, 3]
        assert np.abs(centre - im.projection_center()).max() < 1e-6
        # OpenGL camera: x right, y up, z back; COLMAP's (OpenCV): x right, y down, z forward
        r_world_from_cam = c2w[:3, :3] @ np.diag([1.0, -1.0, -1.0])
        r_cam_from_world = im.cam_from_world().rotation.matrix()
        assert np.abs(r_world_from_cam.T - r_cam_from_world).max() < 1e-6
        assert (d / frame["file_path"]).read_bytes() == (image_dir / im.name).read_bytes()
    # intrinsics: the camera is SIMPLE_RADIAL (f, cx, cy, k); nerfstudio's OPENCV equivalent
    cams = {im.camera_id for im in images}
    for frame, im in zip(t["frames"], images, strict=True):
        k = t if len(cams) == 1 else frame
        cam = rec.cameras[im.camera_id]
        f, cx, cy, k1 = cam.params
        assert k["camera_model"] == "OPENCV" and (k["w"], k["h"]) == (cam.width, cam.height)
        assert (k["fl_x"], k["fl_y"], k["cx"], k["cy"], k["k1"]) == pytest.approx((f, f, cx, cy, k1))
        assert k["k2"] == k["p1"] == k["p2"] == 0.0
    assert ("fl_x" in t) == (len(cams) == 1)


@pytest.mark.pipeline
def test_nerfstudio_cameras_look_at_the_points(exported, rec) -> None:
    """In nerfstudio's world and camera convention the points a camera sees lie at negative z
    (OpenGL looks down -z) and project where COLMAP's keypoints are: the file is usable, not only
    invertible."""
    d = exported["nerfstudio"]
    t = json.loads((d / "transforms.json").read_text())
    counts, pts = read_ply(d / "sparse_pc.ply")
    assert counts["vertex"] == rec.num_points3D()
    applied = np.vstack([np.array(t["applied_transform"]), [0, 0, 0, 1]])
    ids = sorted(rec.points3D)
    xyz_ns = np.array([[p["x"], p["y"], p["z"]] for p in pts])
    xyz_colmap = np.array([rec.points3D[i].xyz for i in ids])
    assert np.abs(xyz_ns - (xyz_colmap @ applied[:3, :3].T + applied[:3, 3])).max() < 1e-4
    by_name = {im.name: im for im in rec.images.values()}
    for frame in t["frames"]:
        im = by_name[frame["file_path"].removeprefix("images/")]
        k = t if "fl_x" in t else frame
        w2c = np.linalg.inv(np.array(frame["transform_matrix"]))
        checked = 0
        for p2d in im.points2D:
            if not p2d.has_point3D():
                continue
            x_ns = rec.points3D[p2d.point3D_id].xyz @ applied[:3, :3].T + applied[:3, 3]
            x_cam = w2c[:3, :3] @ x_ns + w2c[:3, 3]
            assert x_cam[2] < 0
            u, v = x_cam[0] / -x_cam[2], -x_cam[1] / -x_cam[2]  # OpenGL -> image plane, y down
            r2 = u * u + v * v
            u, v = u * (1 + k["k1"] * r2), v * (1 + k["k1"] * r2)
            px = np.array([k["fl_x"] * u + k["cx"], k["fl_y"] * v + k["cy"]])
            # the model's reprojection error, not a convention: the largest over all observations
            # is 3.24-3.37 px over tests/small_scene.py's 9 mappings; bound at 1.5 times the worst
            assert np.abs(px - p2d.xy).max() < 5.0
            checked += 1
        assert checked > 10


# -- colmap-text ---------------------------------------------------------------------------------
@pytest.mark.pipeline
def test_colmap_text_reads_back_in_pycolmap(exported, rec) -> None:
    d = exported["colmap-text"]
    assert {"cameras.txt", "images.txt", "points3D.txt"} <= {p.name for p in d.iterdir()}
    assert not list(d.glob("*.bin"))  # text only: whatever reads it below read the text
    back = pycolmap.Reconstruction(str(d))
    assert back.num_reg_images() == rec.num_reg_images() and back.num_points3D() == rec.num_points3D()
    assert back.num_cameras() == rec.num_cameras()
    for im in registered(rec):
        other = back.images[im.image_id]
        assert other.name == im.name
        m0, m1 = im.cam_from_world().matrix(), other.cam_from_world().matrix()
        assert np.abs(m0 - m1).max() < 1e-6
    for pid, p in rec.points3D.items():
        assert np.abs(back.points3D[pid].xyz - p.xyz).max() < 1e-6


# -- ply -----------------------------------------------------------------------------------------
@pytest.mark.pipeline
def test_ply_has_every_point_with_its_colour(exported, rec) -> None:
    counts, pts = read_ply(exported["ply"] / "points.ply")
    assert counts == {"vertex": rec.num_points3D()}
    assert {"x", "y", "z", "red", "green", "blue"} <= set(pts.dtype.names)
    got = sorted(zip(pts["x"], pts["y"], pts["z"], pts["red"], pts["green"], pts["blue"], strict=True))
    # sorted on the float32 values the PLY holds: two points whose coordinates differ below float32
    # precision would otherwise sort in a different order on each side
    want = sorted((*p.xyz.astype(np.float32), *p.color) for p in rec.points3D.values())
    assert np.allclose(np.array(got, float), np.array(want, float), atol=1e-4)


# -- hloc ----------------------------------------------------------------------------------------
def names_to_pair(name0: str, name1: str) -> str:
    """hloc's pair key, written again here from hloc's documentation (hloc.utils.io)."""
    return f"{name0.replace('/', '-')}_{name1.replace('/', '-')}"


def hloc_matches(f: h5py.File, name0: str, name1: str) -> np.ndarray:
    """hloc.utils.io.get_matches: the key in either order, matches0 turned into index pairs."""
    key, reverse = names_to_pair(name0, name1), False
    if key not in f:
        key, reverse = names_to_pair(name1, name0), True
    m = f[key]["matches0"][()]
    idx = np.where(m != -1)[0]
    pairs = np.stack([idx, m[idx]], -1)
    return np.flip(pairs, -1) if reverse else pairs


@pytest.mark.pipeline
def test_hloc_files_reproduce_the_databases_verified_matches(exported, run_dir: Path) -> None:
    d = exported["hloc"]
    db = pycolmap.Database.open(str(run_dir / "database.db"))
    try:
        names = {im.image_id: im.name for im in db.read_all_images()}
        pair_ids, geometries = db.read_two_view_geometries()
        with h5py.File(d / "features.h5", "r") as feats, h5py.File(d / "matches.h5", "r") as matches:
            assert set(feats) == set(names.values())
            for image_id, name in names.items():
                kp = feats[name]["keypoints"][()]
                colmap_kp = db.read_keypoints(image_id)[:, :2]
                assert kp.shape == colmap_kp.shape and kp.dtype == np.float32
                assert np.abs(kp + COLMAP_OFFSET - colmap_kp).max() < 1e-4  # hloc adds 0.5 into COLMAP
                assert feats[name]["scores"].shape == (len(kp),)
                cam = db.read_camera(db.read_image(image_id).camera_id)
                assert list(feats[name]["image_size"][()]) == [cam.width, cam.height]
            # one group per pair with a two-view geometry (a verified pair without inliers has none)
            assert len(matches) == len(pair_ids) > 0
            total = 0
            for pair_id, tvg in zip(pair_ids, geometries, strict=True):
                a, b = pycolmap.pair_id_to_image_pair(pair_id)
                want = np.asarray(tvg.inlier_matches).reshape(-1, 2)
                g = matches[names_to_pair(names[a], names[b])]
                assert g["matches0"].shape == (len(feats[names[a]]["keypoints"]),)
                assert g["matching_scores0"].shape == g["matches0"].shape
                got = hloc_matches(matches, names[a], names[b])
                assert sorted(map(tuple, got)) == sorted(map(tuple, want))
                # and from the other side, as hloc asks when the pair is listed reversed
                assert sorted(map(tuple, hloc_matches(matches, names[b], names[a]))) == sorted(
                    map(tuple, want[:, ::-1])
                )
                total += len(want)
            assert total == db.num_inlier_matches() > 0
    finally:
        db.close()
    lines = (d / "pairs.txt").read_text().splitlines()
    assert len(lines) == len(pair_ids) and all(len(ln.split(" ")) == 2 for ln in lines)
    assert {tuple(ln.split(" ")) for ln in lines} == {
        tuple(names[i] for i in pycolmap.pair_id_to_image_pair(p)) for p in pair_ids
    }


# -- openmvs -------------------------------------------------------------------------------------
@pytest.mark.pipeline
def test_openmvs_folder_is_undistorted(exported, rec) -> None:
    d = exported["openmvs"]
    und = pycolmap.Reconstruction(str(d / "sparse"))
    assert und.num_reg_images() == rec.num_reg_images() and und.num_points3D() == rec.num_points3D()
    assert {c.model.name for c in und.cameras.values()} == {"PINHOLE"}
    import cv2

    for im in registered(und):
        picture = cv2.imread(str(d / "images" / im.name))
        cam = und.cameras[im.camera_id]
        assert picture is not None and picture.shape[:2] == (cam.height, cam.width), im.name
    assert (d / "stereo").is_dir()


@pytest.mark.unit
def test_exports_import_no_torch() -> None:
    """The service's API process builds the exports it serves, and it never loads torch."""
    exports = (
        "geomatch.export, geomatch.export.nerfstudio, geomatch.export.colmap_text, "
        "geomatch.export.ply, geomatch.export.hloc, geomatch.export.openmvs, geomatch.export.odm, "
        "geomatch.export.laz"
    )
    assert loaded_after(exports, ("torch", "cv2")) == []
