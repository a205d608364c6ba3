"""Synthetic fixed-wing surveys: return legs flown the other way with sparser photos, banked turns
photographed, triggers that fail, EXIF GPS and no XMP, farmland that a near-infrared camera sees
with little colour; the ground truth is a COLMAP model of the same poses."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from geomatch.metadata import read_metadata
from geomatch.synth.camera import Camera
from geomatch.synth.farmtex import FarmTiles
from geomatch.synth.fixedwing import (
    EAST_TURN,
    LEG,
    RETURN,
    WEST_TURN,
    FixedWingPlan,
    Shot,
    airframe_rotation,
    shots,
)
from geomatch.synth.flight import write_fixedwing
from geomatch.synth.sensors import GPS_ORIGIN

pytestmark = pytest.mark.unit

W, H = 64, 48


def _angle(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


@pytest.fixture(scope="module")
def fired() -> tuple[FixedWingPlan, list[Shot]]:
    plan = FixedWingPlan(120, W, H, missing=0.05)
    return plan, shots(plan, 4)


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Camera]]:
    out = tmp_path_factory.mktemp("fixedwing")
    return out, write_fixedwing(out, FixedWingPlan(36, W, H, missing=0.1), seed=5)


def _runs(fired: list[Shot], part: str) -> list[list[Shot]]:
    """The written photos of each leg of ``part``, in order."""
    legs: dict[int, list[Shot]] = {}
    for s in fired:
        if s.part == part and s.name is not None:
            legs.setdefault(s.loop, []).append(s)
    return list(legs.values())


def test_return_legs_are_flown_back_with_sparser_photos(fired: tuple[FixedWingPlan, list[Shot]]) -> None:
    plan, triggers = fired
    assert sum(s.name is not None for s in triggers) == 120
    for part, heading, step in (
        (LEG, plan.bearing_deg, plan.step_m),
        (RETURN, plan.bearing_deg + 180, plan.step_m * plan.return_ratio),
    ):
        legs = _runs(triggers, part)
        assert len(legs) >= 2
        for leg in legs:
            for s in leg:
                assert _angle(s.track_deg, heading) < 1.0
                assert _angle(s.heading_deg, heading) < 10.0  # crab and the airframe's scatter
        # consecutive triggers (none failed between them) are one timer period apart
        gaps = [
            np.linalg.norm(b.position[:2] - a.position[:2])
            for leg in legs
            for a, b in itertools.pairwise(leg)
            if b.index == a.index + 1
        ]
        assert abs(np.median(gaps) - step) < 0.1 * step, (part, np.median(gaps), step)
    # a return leg's photos are turned a half turn against the outbound ones
    out_R = airframe_rotation(_runs(triggers, LEG)[0][3].heading_deg, 0, 0)
    back_R = airframe_rotation(_runs(triggers, RETURN)[0][3].heading_deg, 0, 0)
    assert out_R[1] @ back_R[1] < -0.95  # image "down" axes opposite


def test_turns_are_banked_and_photographed(fired: tuple[FixedWingPlan, list[Shot]]) -> None:
    _, triggers = fired
    for part in (EAST_TURN, WEST_TURN):
        rolls = np.array([s.roll_deg for s in triggers if s.part == part])
        assert len(rolls) >= 4
        assert 10.0 <= rolls.max() <= 35.0, (part, rolls)  # the right-hand circuits
    # the left-hand ones (every other pass) bank the other way
    assert min(s.roll_deg for s in triggers if s.part == EAST_TURN) < -10.0
    legs = [abs(s.roll_deg) for s in triggers if s.part in (LEG, RETURN)]
    assert np.median(legs) < 3.0
    # the camera is fixed to the airframe: a right bank of 25 deg tilts the view 25 deg to the left
    R = airframe_rotation(0.0, 0.0, 25.0)
    axis = R[2]
    assert np.degrees(np.arccos(-axis[2])) == pytest.approx(25.0)
    assert axis[0] < 0  # heading north, banked right: the view swings west, out of the turn


def test_some_triggers_fail_and_the_names_count_on(fired: tuple[FixedWingPlan, list[Shot]]) -> None:
    plan, triggers = fired
    failed = [s for s in triggers if s.name is None]
    assert 1 <= len(failed) <= 0.15 * len(triggers)
    names = [s.name for s in triggers if s.name is not None]
    assert names == [f"IMG_{k:04d}.JPG" for k in range(1, len(names) + 1)]
    assert [s.index for s in triggers] == list(range(len(triggers)))
    # the flight circles the field again, the other way round: the second pass's outbound
    # legs run half a spacing beside the first pass's return legs, and the other way about
    assert max(s.loop for s in triggers) >= plan.lines
    across = {
        (part, first): {
            round(float(s.position[:2] @ plan.across) / plan.spacing_m * 2)
            for s in triggers
            if s.part == part and (s.loop < plan.lines) == first
        }
        for part in (LEG, RETURN)
        for first in (True, False)
    }
    assert across[(LEG, False)] and across[(RETURN, False)]
    for part, other in ((LEG, RETURN), (RETURN, LEG)):
        # offsets in half spacings: each strip of the second pass interleaves with the other
        # leg kind's strip of the first
        assert {v + d for v in across[(part, False)] for d in (-1, 1)} & across[(other, True)]


def test_photos_carry_exif_gps_and_no_xmp(flight: tuple[Path, list[Camera]]) -> None:
    out, cams = flight
    truth = json.loads((out / "gt" / "gps.json").read_text())
    assert truth["sigma_m"] == pytest.approx(2.5)
    for c in cams:
        path = out / "images" / c.name
        raw = path.read_bytes()
        assert b"xmpmeta" not in raw and b"drone-dji" not in raw
        m = read_metadata(path)
        assert m.gimbal_pitch_deg is None and m.relative_altitude_m is None and m.aerial_hint is None
        assert m.lat_lon is not None
        lat, lon = m.lat_lon or (0.0, 0.0)
        enu = GPS_ORIGIN.from_geodetic(lat, lon, m.altitude_m or 0.0)
        assert np.linalg.norm(enu[:2] - c.centre[:2]) < 5 * 2.5
        np.testing.assert_allclose(enu, truth["gps_enu"][c.name], atol=0.01)


def test_ground_truth_and_the_flight_record(flight: tuple[Path, list[Camera]]) -> None:
    out, cams = flight
    rec = pycolmap.Reconstruction(str(out / "gt"))
    by_name = {im.name: im for im in rec.images.values()}
    assert set(by_name) == {c.name for c in cams} == {p.name for p in (out / "images").iterdir()}
    for c in cams:
        pose = by_name[c.name].cam_from_world()
        np.testing.assert_allclose(pose.rotation.matrix(), c.R, atol=1e-9)
        np.testing.assert_allclose(np.asarray(pose.translation), c.t, atol=1e-6)
    record = json.loads((out / "gt" / "flight.json").read_text())
    assert record["kind"] == "fixedwing"
    written = [t for t in record["triggers"] if t["name"]]
    assert [t["name"] for t in written] == [c.name for c in cams]
    assert record["missing_triggers"] == [t["index"] for t in record["triggers"] if not t["name"]]
    assert record["missing_triggers"]  # 10 %: at least one of ~40 triggers failed


def test_farmland_is_grey_in_near_infrared_with_dark_roads() -> None:
    tiles = FarmTiles(3, texel_m=2.0, detail=0.15)
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-300, 300, 4000), rng.uniform(-300, 300, 4000)
    rgb = tiles.sample(x, y)
    v, kind, _ = tiles.layout(x, y)
    assert np.median(rgb.max(1) - rgb.min(1)) < 0.2 * np.median(rgb.mean(1))  # little colour
    assert (kind == -1).any()  # a road crosses 600 m
    fields = np.isin(kind, (1, 2))
    assert np.median(v[kind == -1]) < 0.5 * np.median(v[fields])
    colour = FarmTiles(3, texel_m=2.0, nir=False).sample(x, y)
    assert np.median(colour.max(1) - colour.min(1)) > np.median(rgb.max(1) - rgb.min(1))


def test_cli_renders_a_fixedwing_flight(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from geomatch.cli import main

    args = ["synth", str(tmp_path), "--kind", "fixedwing", "--photos", "3", "--width", "64", "--height", "48"]
    assert main(args) == 0
    assert "3 images (fixed-wing)" in capsys.readouterr().out
    assert sorted(p.name for p in (tmp_path / "images").iterdir()) == [f"IMG_{k:04d}.JPG" for k in (1, 2, 3)]
    assert main([*args[:5], "0"]) != 0
    assert main([*args, "--return-spacing", "0.5"]) != 0
