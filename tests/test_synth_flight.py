"""Synthetic survey flights: the photos say what a drone's would (GPS, XMP headings that flip
between lines), the ground truth is a COLMAP model of the same poses, and the renders agree with
it and with themselves whatever the tile cache holds."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from geomatch.geo.gps import fixes
from geomatch.metadata import read_metadata
from geomatch.synth.flight import write_flight
from geomatch.synth.flightplan import FOCAL_PER_WIDTH, FlightPlan, aerial_cameras
from geomatch.synth.sensors import GPS_ORIGIN
from geomatch.synth.world import World

pytestmark = pytest.mark.unit

W, H = 160, 120


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list]:
    out = tmp_path_factory.mktemp("flight")
    return out, write_flight(out, 12, ground=1, seed=2, size=(W, H))


def _heading_diff(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def test_photos_carry_gps_and_xmp_headings_that_alternate_by_line(flight: tuple[Path, list]) -> None:
    out, cams = flight
    plan = json.loads((out / "gt" / "flight.json").read_text())
    assert plan["lines"] == 2 and plan["per_line"] == [6, 6]
    aerial = [c for c in cams if c.aerial]
    assert [c.name for c in aerial] == [f"DJI_{k:04d}.JPG" for k in range(1, 13)]
    assert (out / "aerial.txt").read_text().split() == [c.name for c in aerial]
    assert plan["ground"] == ["IMG_0001.JPG"]
    names = sorted(p.name for p in (out / "images").iterdir())
    assert names == sorted(c.name for c in cams)
    metas = {n: read_metadata(out / "images" / n) for n in names}
    bearing = plan["bearing_deg"]
    for k, c in enumerate(aerial):
        m = metas[c.name]
        assert m.aerial_hint is True and m.gimbal_pitch_deg is not None and m.gimbal_pitch_deg <= -88.0
        assert m.gimbal_yaw_deg is not None and m.relative_altitude_m is not None
        expected = bearing if k < 6 else bearing - 180.0  # the second line flown back
        assert _heading_diff(m.gimbal_yaw_deg, expected) < 10.0, (c.name, m.gimbal_yaw_deg)
        assert abs(m.relative_altitude_m - plan["altitude"]) < 2.0
        assert m.focal_px == pytest.approx(FOCAL_PER_WIDTH * W)
        # the image's top is where the drone heads: image y (down) points against the heading
        h = np.radians(expected)
        assert c.R[1] @ np.array([np.sin(h), np.cos(h), 0.0]) < -0.98
        assert c.R[2, 2] < -0.99  # nadir
    assert metas["IMG_0001.JPG"].aerial_hint is None and metas["IMG_0001.JPG"].has_gps
    # the fixes read back land within GNSS noise of the true centres, in GPS_ORIGIN's frame
    located = fixes(names, metas)
    assert located is not None and set(located.enu) == set(names)
    truth = json.loads((out / "gt" / "gps.json").read_text())
    for c in cams:
        lat, lon = metas[c.name].lat_lon or (0.0, 0.0)
        enu = GPS_ORIGIN.from_geodetic(lat, lon, metas[c.name].altitude_m or 0.0)
        assert np.linalg.norm(enu[:2] - c.centre[:2]) < 4 * truth["sigma_m"] + 0.1
        np.testing.assert_allclose(truth["true_enu"][c.name], c.centre, atol=1e-9)
    # consecutive photos of a line are a step apart, the lines a spacing apart
    centres = np.array([c.centre for c in aerial])
    steps = np.linalg.norm(np.diff(centres[:6, :2], axis=0), axis=1)
    assert np.all(np.abs(steps - plan["step"]) < 4.0)
    assert abs(np.linalg.norm(centres[0, :2] - centres[11, :2]) - plan["spacing"]) < 4.0


def test_ground_truth_is_a_colmap_model_of_the_cameras(flight: tuple[Path, list]) -> None:
    out, cams = flight
    rec = pycolmap.Reconstruction(str(out / "gt"))
    assert rec.num_images() == len(cams) == 13
    by_name = {im.name: im for im in rec.images.values()}
    for c in cams:
        pose = by_name[c.name].cam_from_world()
        np.testing.assert_allclose(pose.rotation.matrix(), c.R, atol=1e-9)
        np.testing.assert_allclose(np.asarray(pose.translation), c.t, atol=1e-6)
        assert (
            rec.cameras[by_name[c.name].camera_id].width,
            rec.cameras[by_name[c.name].camera_id].height,
        ) == (W, H)
    ground = [c for c in cams if not c.aerial]
    assert all(abs(np.degrees(np.arcsin(c.R[2, 2]))) < 20 for c in ground)  # near-horizontal


def test_renders_agree_with_the_poses_and_not_with_the_cache() -> None:
    """A pixel of one photo lifted to 3D by its depth lands on the same colour in the next photo
    of the line and in one of the line flown back (turned a half turn): poses, intrinsics,
    terrain and tiles agree; and a world with a cache of a few tiles renders the same pixels."""
    plan = FlightPlan.make(12, W, H)
    cams, _ = aerial_cameras(plan, 3)
    world = World(3, texel_m=plan.altitude / (FOCAL_PER_WIDTH * W) / 2)
    renders = {c.name: world.render(c) for c in cams}
    small = World(3, texel_m=world.texel, cache_mb=0.5)
    np.testing.assert_array_equal(small.render(cams[4])[0], renders[cams[4].name][0])
    checked = 0
    for a, b in ((cams[0], cams[1]), (cams[2], cams[9]), (cams[5], cams[6])):
        img_a, depth_a = renders[a.name]
        img_b, depth_b = renders[b.name]
        v, u = np.mgrid[0:H:3, 0:W:3]
        d = depth_a[v, u]
        pix = np.stack([u.ravel() + 0.5, v.ravel() + 0.5, np.ones(u.size)], 1)
        X = (pix @ np.linalg.inv(a.K).T * d.ravel()[:, None] - a.t) @ a.R
        uv, z = b.project(X)
        ub, vb = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
        inside = (z > 0) & (ub >= 0) & (ub < W) & (vb >= 0) & (vb < H)
        vis = inside.copy()
        vis[inside] = np.abs(depth_b[vb[inside], ub[inside]] - z[inside]) < 0.01 * z[inside]
        assert vis.sum() > 200, (a.name, b.name)
        ca = img_a[v.ravel()[vis], u.ravel()[vis]].astype(float)
        cb = img_b[vb[vis], ub[vis]].astype(float)
        assert np.median(np.abs(ca - cb)) < 25, (a.name, b.name)
        checked += 1
    assert checked == 3


def test_area_grows_with_the_photos_and_bad_plans_are_refused() -> None:
    small, large = FlightPlan.make(100), FlightPlan.make(1000)
    assert sum(small.per_line) == 100 and sum(large.per_line) == 1000
    assert large.lines > 2 * small.lines  # about square: lines grow as the square root
    # a side and a forward overlap as planned: the footprint less the spacing
    f = FOCAL_PER_WIDTH * small.width
    assert small.step == pytest.approx(small.altitude * small.height / f * (1 - small.front))
    assert small.spacing == pytest.approx(small.altitude * small.width / f * (1 - small.side))
    with pytest.raises(ValueError):
        FlightPlan.make(0)
    with pytest.raises(ValueError):
        FlightPlan.make(10, front=1.0)


def test_cli_renders_a_flight(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from geomatch.cli import main

    assert (
        main(["synth", str(tmp_path), "--kind", "flight", "--photos", "3", "--width", "64", "--height", "48"])
        == 0
    )
    assert "3 images (3 aerial, 0 ground)" in capsys.readouterr().out
    assert sorted(p.name for p in (tmp_path / "images").iterdir()) == [
        "DJI_0001.JPG",
        "DJI_0002.JPG",
        "DJI_0003.JPG",
    ]
    assert main(["synth", str(tmp_path / "x"), "--kind", "flight", "--photos", "0"]) != 0
