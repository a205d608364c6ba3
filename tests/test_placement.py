"""A georeferenced camera on the globe and its heading (geomatch/geo/placement.py)."""

from __future__ import annotations

import numpy as np
import pytest

from geomatch.geo.geodesy import EnuFrame
from geomatch.geo.placement import heading_deg, wgs84

pytestmark = pytest.mark.unit


def _world_from_cam(axis: list[float], down: list[float]) -> np.ndarray:
    """Camera -> ENU rotation with the optical axis (+z) and the image's down (+y) given."""
    z = np.array(axis, float) / np.linalg.norm(axis)
    y = np.array(down, float)
    y = y - z * (y @ z)
    y /= np.linalg.norm(y)
    return np.column_stack([np.cross(y, z), y, z])


@pytest.mark.parametrize(
    ("axis", "heading"),
    [([0, 1, 0], 0.0), ([1, 0, 0], 90.0), ([0, -1, -0.3], 180.0), ([-1, 1, 0.2], 315.0)],
)
def test_heading_is_the_optical_axis_azimuth(axis: list[float], heading: float) -> None:
    R = _world_from_cam(axis, [0, 0, -1])
    assert heading_deg(R) == pytest.approx(heading, abs=1e-6)


def test_nadir_heading_is_where_the_image_top_points() -> None:
    R = _world_from_cam([0, 0, -1], [0, -1, 0])  # looking down, image down = south: top = north
    assert heading_deg(R) == pytest.approx(0.0, abs=1e-6)
    R = _world_from_cam([0.01, 0, -1], [-1, 0, 0])  # top of the image to the east
    assert heading_deg(R) == pytest.approx(90.0, abs=1e-6)


def test_wgs84_of_an_enu_centre_round_trips() -> None:
    frame = EnuFrame(47.3769, 8.5417, 408.0)
    where = wgs84(frame, np.array([100.0, -50.0, 12.0]), _world_from_cam([0, 1, 0], [0, 0, -1]))
    assert set(where) == {"lat", "lon", "alt", "heading_deg"}
    back = frame.from_geodetic(where["lat"], where["lon"], where["alt"])
    assert np.allclose(back, [100.0, -50.0, 12.0], atol=1e-6)
    assert where["lat"] < 47.3769 and where["lon"] > 8.5417
