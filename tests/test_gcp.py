"""Ground control points: an OpenDroneMap gcp_list.txt read with every flaw reported by line or
point, and a model georeferenced by its control points and judged at check points the fit never saw,
against a synthetic model whose true frame is known exactly."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from geomatch.geo.gcp import MAX_REPROJECTION_PX, adjust_to_control, choose_checkpoints, georeference
from geomatch.geo.gcpfile import GcpError, read_gcp_file

pytestmark = pytest.mark.unit

UTM11 = "+proj=utm +zone=11 +ellps=WGS84 +datum=WGS84 +units=m +no_defs"
SIZES = {"a.jpg": (1600, 1067), "b.jpg": (1600, 1067), "c.jpg": (1600, 1067)}


def _line(x: float, y: float, z: float, px: float, py: float, image: str, name: str) -> str:
    return f"{x}\t{y}\t{z}\t{px}\t{py}\t{image}\t{name}"


GOOD = [
    _line(235269.88, 3811198.11, 0.0, 100, 200, "a.jpg", "gcp01"),
    _line(235269.88, 3811198.11, 0.0, 150, 210, "b.jpg", "gcp01"),
    _line(235262.54, 3811203.50, 0.0, 300, 400, "a.jpg", "gcp02"),
    _line(235262.54, 3811203.50, 0.0, 320, 410, "c.jpg", "gcp02"),
    _line(235250.00, 3811210.00, 1.5, 500, 600, "b.jpg", "gcp03"),
    _line(235250.00, 3811210.00, 1.5, 520, 610, "c.jpg", "gcp03"),
]


def test_a_well_formed_file_gives_its_points_in_metres() -> None:
    g = read_gcp_file("\n".join([UTM11, *GOOD, "# a comment", ""]), SIZES)
    assert sorted(g.points) == ["gcp01", "gcp02", "gcp03"]
    assert g.problems == [] and g.unusable == {}
    assert np.allclose(g.points["gcp03"].xyz, [235250.0, 3811210.0, 1.5])
    assert [o.image for o in g.points["gcp01"].observations] == ["a.jpg", "b.jpg"]


def test_epsg_codes_and_wgs84_are_understood_and_degrees_become_utm_metres() -> None:
    assert read_gcp_file("\n".join(["EPSG:32611", *GOOD]), SIZES).frame.to_epsg() == 32611
    wgs = [
        _line(-119.8790, 34.4140, 2.0, 10, 10, "a.jpg", "p1"),
        _line(-119.8790, 34.4140, 2.0, 20, 20, "b.jpg", "p1"),
        _line(-119.8780, 34.4140, 2.0, 30, 30, "a.jpg", "p2"),
        _line(-119.8780, 34.4140, 2.0, 40, 40, "b.jpg", "p2"),
        _line(-119.8790, 34.4150, 2.0, 50, 50, "a.jpg", "p3"),
        _line(-119.8790, 34.4150, 2.0, 60, 60, "c.jpg", "p3"),
    ]
    g = read_gcp_file("\n".join(["WGS84", *wgs]), SIZES)
    assert g.frame.to_epsg() == 32611  # the UTM zone of Goleta, California
    east = g.points["p2"].xyz - g.points["p1"].xyz
    north = g.points["p3"].xyz - g.points["p1"].xyz
    # 0.001 deg of longitude at 34.4 deg N is ~92 m, of latitude ~111 m; UTM's grid north is
    # turned from true north by a degree or two this far from the zone's central meridian
    assert 90 < np.linalg.norm(east[:2]) < 94 and 110 < np.linalg.norm(north[:2]) < 112
    assert abs(east[:2] @ north[:2]) / (np.linalg.norm(east[:2]) * np.linalg.norm(north[:2])) < 0.01
    assert east[0] > 90 and north[1] > 110


def test_each_bad_line_is_named_and_the_rest_is_used() -> None:
    lines = [
        UTM11,
        *GOOD,
        "235260.0 3811200.0 0.0 12.5",  # line 8: too few fields
        _line(235260.0, 3811200.0, 0.0, 10, 10, "missing.jpg", "gcp04"),  # line 9
        _line(235260.0, 3811200.0, 0.0, 1700, 10, "a.jpg", "gcp04"),  # line 10: x beyond 1600
        _line(235240.0, 3811220.0, 0.0, 10, 10, "a.jpg", "gcp05"),  # line 11: one photo only
    ]
    g = read_gcp_file("\n".join(lines), SIZES)
    assert sorted(g.points) == ["gcp01", "gcp02", "gcp03"]
    text = "\n".join(g.problems)
    assert "line 8: expected 'x y z px py image [name]'" in text
    assert "line 9: gcp04: image 'missing.jpg' is not in the project" in text
    assert "line 10: gcp04: pixel (1700, 10) is outside a.jpg (1600x1067)" in text
    assert "gcp05: seen in one photo only (line 11)" in text
    assert g.unusable["gcp05"].startswith("seen in one photo only")


def test_an_unknown_coordinate_system_refuses_the_file_naming_line_1() -> None:
    with pytest.raises(GcpError, match=r"line 1: unknown coordinate system 'EPSG:999999'"):
        read_gcp_file("\n".join(["EPSG:999999", *GOOD]), SIZES)


def test_earth_centred_coordinates_are_refused_and_degrees_out_of_range_named() -> None:
    with pytest.raises(GcpError, match=r"line 1: .*not a map projection"):
        read_gcp_file("EPSG:4978\n" + _line(4e6, 1e6, 4.8e6, 10, 10, "a.jpg", "g1"), SIZES)
    lines = [
        _line(-117.2 + k * 1e-4, 32.8 + (k == 2) * 1e-4, 0.0, 10 + k, 10, im, f"g{k}")
        for k in range(3)
        for im in ("a.jpg", "b.jpg")
    ]
    lines.append(_line(200.0, 32.8, 0.0, 10, 10, "a.jpg", "far"))
    g = read_gcp_file("\n".join(["WGS84", *lines]), SIZES)
    assert sorted(g.points) == ["g0", "g1", "g2"]
    assert any("far: (200, 32.8) is not a longitude and latitude" in p for p in g.problems)
    assert all(np.isfinite(p.xyz).all() for p in g.points.values())


def test_a_file_with_fewer_than_three_usable_points_is_refused_with_the_reason() -> None:
    with pytest.raises(GcpError, match=r"leaves 2 usable points.*gcp03: seen in one photo only"):
        read_gcp_file("\n".join([UTM11, *GOOD[:5]]), SIZES)


def test_check_points_by_count_are_spread_and_the_same_every_time() -> None:
    names = [f"gcp{i:02d}" for i in range(9)]
    assert choose_checkpoints(names, 3) == {"gcp02", "gcp04", "gcp06"}
    assert choose_checkpoints(names, ["gcp01"]) == {"gcp01"}
    with pytest.raises(GcpError, match="fewer than 3 control points"):
        choose_checkpoints(names, 7)
    with pytest.raises(GcpError, match="not among the usable GCPs: gcp99"):
        choose_checkpoints(names, ["gcp99"])


# -- georeferencing against a model whose true frame is known --------------------------------------
TRUE_SCALE = 3.7
TRUE_R = Rotation.from_euler("zyx", [40, 5, -3], degrees=True).as_matrix()
TRUE_T = np.array([235200.0, 3811150.0, 12.0])


def _model() -> pycolmap.Reconstruction:
    opts = pycolmap.SyntheticDatasetOptions()
    opts.num_rigs, opts.num_frames_per_rig, opts.num_points3D = 1, 6, 60
    return pycolmap.synthesize_dataset(opts)


def _gcp_text(rec: pycolmap.Reconstruction, n: int, noise_m: float = 0.0, shift: str | None = None) -> str:
    """``n`` of the model's 3D points seen in 3+ photos as GCPs in UTM 11N: their true coordinates
    (plus noise), their exact pixels (COLMAP's centre at 0.5 made integer); ``shift`` moves that
    point's first observation by 40 px."""
    rng = np.random.default_rng(0)
    lines = [UTM11]
    chosen = [p for _, p in sorted(rec.points3D.items()) if p.track.length() >= 3][:n]
    assert len(chosen) == n
    for k, p in enumerate(chosen):
        name = f"gcp{k:02d}"
        world = TRUE_SCALE * TRUE_R @ p.xyz + TRUE_T + rng.normal(0, noise_m, 3)
        for j, el in enumerate(p.track.elements):
            im = rec.images[el.image_id]
            x, y = im.points2D[el.point2D_idx].xy - 0.5
            if name == shift and j == 0:
                x += 40.0
            lines.append(_line(world[0], world[1], world[2], x, y, im.name, name))
    return "\n".join(lines)


def _sizes(rec: pycolmap.Reconstruction) -> dict[str, tuple[int, int]]:
    return {
        im.name: (rec.cameras[im.camera_id].width, rec.cameras[im.camera_id].height)
        for im in rec.images.values()
    }


def test_exact_control_points_place_the_check_points_exactly() -> None:
    rec = _model()
    g = read_gcp_file(_gcp_text(rec, 7), _sizes(rec))
    report = georeference(rec, g, ["gcp01", "gcp05"])
    roles = {p.name: p.role for p in report.points}
    assert roles["gcp01"] == roles["gcp05"] == "check"
    assert sum(r == "control" for r in roles.values()) == 5
    check = report.rmse("check")
    assert check is not None and check[1] < 1e-6
    assert report.similarity.scale == pytest.approx(TRUE_SCALE, rel=1e-9)
    assert all(p.reprojection_px is not None and p.reprojection_px < 1e-6 for p in report.points)


def test_surveyed_noise_shows_at_the_check_points() -> None:
    rec = _model()
    g = read_gcp_file(_gcp_text(rec, 9, noise_m=0.02), _sizes(rec))
    report = georeference(rec, g, 3)
    horizontal, full = report.rmse("check")  # type: ignore[misc]
    # 2 cm per axis on every point: the check points are off by about that, never by metres
    assert 0.001 < horizontal < 0.08 and horizontal <= full < 0.1


def test_a_point_whose_observations_do_not_meet_is_reported_and_left_out() -> None:
    rec = _model()
    g = read_gcp_file(_gcp_text(rec, 6, shift="gcp02"), _sizes(rec))
    report = georeference(rec, g)
    bad = next(p for p in report.points if p.name == "gcp02")
    assert (
        bad.role == "unused" and bad.reprojection_px is not None and bad.reprojection_px > MAX_REPROJECTION_PX
    )
    assert bad.reason is not None and "do not meet" in bad.reason
    control = report.rmse("control")
    assert control is not None and control[1] < 1e-6  # the other five fit exactly
    summary = report.as_dict(g)
    assert summary["control_rmse_3d_m"] < 1e-6 and "check_rmse_3d_m" not in summary


def _bend(rec: pycolmap.Reconstruction, k: float) -> None:
    """Bow the model: z grows with the squared distance from its centre, cameras and points alike
    (a few pixels of reprojection error at the control points); no similarity undoes it, and an
    adjustment that holds the surveyed points brings the model back onto them."""
    pts = np.stack([p.xyz for p in rec.points3D.values()])
    mid = pts.mean(axis=0)
    extent = float(np.ptp(pts[:, :2], axis=0).max())

    def bent(x: np.ndarray) -> np.ndarray:
        d2 = float(np.sum((x[:2] - mid[:2]) ** 2))
        return x + np.array([0.0, 0.0, k * d2 / extent])

    for p in rec.points3D.values():
        p.xyz = bent(np.asarray(p.xyz))
    for frame in rec.frames.values():
        pose = frame.rig_from_world
        centre = -(pose.rotation.matrix().T @ pose.translation)
        pose.translation = -(pose.rotation.matrix() @ bent(centre))
        frame.rig_from_world = pose


def test_the_adjustment_holding_the_control_points_undoes_a_bend_a_similarity_cannot() -> None:
    rec = _model()
    g = read_gcp_file(_gcp_text(rec, 10), _sizes(rec))  # surveyed on the true, unbent site
    keypoints = {iid: im.num_points2D() for iid, im in rec.images.items()}
    n_points = rec.num_points3D()
    _bend(rec, 0.004)
    report = georeference(rec, g, 3)
    rec.transform(report.similarity.to_pycolmap())
    before = report.rmse("check")
    adjust_to_control(rec, g, report)
    after = report.rmse("check")
    assert before is not None and after is not None and report.adjusted
    assert after[1] < before[1] / 3, (before, after)
    # the control points' observations were lent to the adjustment and taken back: the model
    # holds its own keypoints and points only
    assert {iid: im.num_points2D() for iid, im in rec.images.items()} == keypoints
    assert rec.num_points3D() == n_points
    assert report.as_dict(g)["check_rmse_similarity_only_m"]["3d"] == round(before[1], 4)
