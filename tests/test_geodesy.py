"""WGS84 <-> ECEF <-> ENU against values that follow from the ellipsoid's definition alone."""

from __future__ import annotations

import numpy as np
import pytest

from geomatch.geo.geodesy import WGS84_A, WGS84_B, EnuFrame, ecef_to_geodetic, enu_rotation, geodetic_to_ecef

pytestmark = pytest.mark.unit


def test_known_ecef_values() -> None:
    np.testing.assert_allclose(geodetic_to_ecef(0.0, 0.0, 0.0), [WGS84_A, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(geodetic_to_ecef(0.0, 90.0, 100.0), [0.0, WGS84_A + 100.0, 0.0], atol=1e-8)
    np.testing.assert_allclose(geodetic_to_ecef(90.0, 0.0, 0.0), [0.0, 0.0, WGS84_B], atol=1e-8)
    np.testing.assert_allclose(geodetic_to_ecef(-90.0, 0.0, 10.0), [0.0, 0.0, -WGS84_B - 10.0], atol=1e-8)
    # the published WGS84 polar radius, and a textbook point (45 N 45 E, on the ellipsoid)
    assert pytest.approx(6356752.314245, abs=1e-6) == WGS84_B
    n = WGS84_A / np.sqrt(1 - 0.00669437999014 * 0.5)
    np.testing.assert_allclose(
        geodetic_to_ecef(45.0, 45.0, 0.0),
        [n * 0.5, n * 0.5, n * (1 - 0.00669437999014) * np.sqrt(0.5)],
        atol=1e-3,
    )


@pytest.mark.parametrize("lat", [-89.9, -47.0, 0.0, 12.5, 47.3769, 80.0, 89.999])
def test_geodetic_round_trip_is_micrometre_exact(lat: float) -> None:
    rng = np.random.default_rng(int(lat * 1000) % 2**31)
    lats = lat + rng.uniform(-0.01, 0.01, 50)
    lats = np.clip(lats, -89.9999, 89.9999)
    lons = rng.uniform(-180, 180, 50)
    alts = rng.uniform(-400, 9000, 50)
    xyz = geodetic_to_ecef(lats, lons, alts)
    la, lo, h = ecef_to_geodetic(xyz)
    np.testing.assert_allclose(geodetic_to_ecef(la, lo, h), xyz, atol=1e-6, rtol=0)
    np.testing.assert_allclose(h, alts, atol=1e-6)


def test_enu_axes_point_east_north_up() -> None:
    f = EnuFrame(47.3769, 8.5417, 408.0)
    np.testing.assert_allclose(f.from_geodetic(47.3769, 8.5417, 418.0), [0, 0, 10.0], atol=1e-6)
    north = f.from_geodetic(47.3779, 8.5417, 408.0)  # 0.001 deg of latitude: about 111.2 m here
    assert abs(north[0]) < 1e-6 and 111.0 < north[1] < 111.4 and -0.01 < north[2] < 0
    east = f.from_geodetic(47.3769, 8.5427, 408.0)  # 0.001 deg of longitude: 111.3 cos(lat) m
    assert 75.2 < east[0] < 75.6 and abs(east[1]) < 0.01
    R = enu_rotation(47.3769, 8.5417)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_enu_round_trip_and_ecef_matrix() -> None:
    f = EnuFrame(-33.8568, 151.2153, 20.0)
    enu = np.random.default_rng(0).uniform(-2000, 2000, (200, 3))
    la, lo, h = f.to_geodetic(enu)
    np.testing.assert_allclose(f.from_geodetic(la, lo, h), enu, atol=1e-6, rtol=0)
    m = np.array(f.ecef_from_enu_matrix())
    np.testing.assert_allclose(enu @ m[:3, :3].T + m[:3, 3], f.to_ecef(enu), atol=1e-6)
