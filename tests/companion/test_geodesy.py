"""companion.geodesy: WGS-84 <-> ECEF <-> NED about an origin, and the placement of one
tangent-plane frame in another (the fleet frame, issue 24.2). Pure: no I/O."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.geodesy import (
    WGS84_A,
    WGS84_E2,
    WGS84_F,
    Placement,
    check_lla,
    ecef_to_lla,
    lla_to_ecef,
    lla_to_ned,
    local_origin_from_home,
    ned_to_lla,
    placement,
)

ZURICH = (47.397742, 8.545594, 488.0)  # sitl_mock's default home


def test_ecef_of_known_points() -> None:
    assert np.allclose(lla_to_ecef((0.0, 0.0, 0.0)), [WGS84_A, 0.0, 0.0], atol=1e-9)
    assert np.allclose(lla_to_ecef((0.0, 90.0, 10.0)), [0.0, WGS84_A + 10.0, 0.0], atol=1e-6)
    assert np.allclose(lla_to_ecef((90.0, 0.0, 0.0)), [0.0, 0.0, WGS84_A * (1.0 - WGS84_F)], atol=1e-6)
    assert np.allclose(lla_to_ecef((-90.0, 0.0, 0.0)), [0.0, 0.0, -WGS84_A * (1.0 - WGS84_F)], atol=1e-6)


@pytest.mark.parametrize("lla", [ZURICH, (0.0, 0.0, 0.0), (-33.9, 151.2, 40.0), (89.9, -120.0, 2000.0),
                                 (-85.0, 179.9, -50.0), (60.0, -179.99, 10000.0)])
def test_ecef_round_trip(lla: tuple[float, float, float]) -> None:
    lat, lon, alt = ecef_to_lla(lla_to_ecef(lla))
    assert lat == pytest.approx(lla[0], abs=1e-10)
    assert lon == pytest.approx(lla[1], abs=1e-10)
    assert alt == pytest.approx(lla[2], abs=1e-6)


def test_ned_against_the_radii_of_curvature() -> None:
    """Small steps north and east are the meridian and prime-vertical radii times the angle."""
    lat = math.radians(ZURICH[0])
    s2 = math.sin(lat) ** 2
    meridian = WGS84_A * (1.0 - WGS84_E2) / (1.0 - WGS84_E2 * s2) ** 1.5
    prime = WGS84_A / math.sqrt(1.0 - WGS84_E2 * s2)
    d = 1e-5  # degrees: ~1.1 m north, ~0.75 m east
    north = lla_to_ned((ZURICH[0] + d, ZURICH[1], ZURICH[2]), ZURICH)
    east = lla_to_ned((ZURICH[0], ZURICH[1] + d, ZURICH[2]), ZURICH)
    assert north[0] == pytest.approx((meridian + ZURICH[2]) * math.radians(d), rel=1e-6)
    assert abs(north[1]) < 1e-9
    assert east[1] == pytest.approx((prime + ZURICH[2]) * math.cos(lat) * math.radians(d), rel=1e-6)
    up = lla_to_ned((ZURICH[0], ZURICH[1], ZURICH[2] + 100.0), ZURICH)
    assert np.allclose(up, [0.0, 0.0, -100.0], atol=1e-6)
    # far away, down grows as the Earth curves away from the tangent plane: ~d^2 / (2 R)
    far = lla_to_ned(ned_to_lla([10000.0, 0.0, 0.0], ZURICH), ZURICH)
    assert np.allclose(far, [10000.0, 0.0, 0.0], atol=1e-6)


def test_ned_round_trip() -> None:
    rng = np.random.default_rng(3)
    for ned in rng.uniform(-5000.0, 5000.0, size=(20, 3)):
        assert np.allclose(lla_to_ned(ned_to_lla(ned, ZURICH), ZURICH), ned, atol=1e-6)


def test_placement_maps_one_tangent_plane_into_another_exactly() -> None:
    """A geodetic point seen in a vehicle's local frame and in the fleet frame: the placement
    takes one to the other to a micrometre, 3 km apart."""
    fleet = ZURICH
    local = ned_to_lla([2000.0, -2200.0, -35.0], fleet)  # the vehicle's EKF origin
    pl = placement(local, fleet)
    assert np.allclose(pl.offset, [2000.0, -2200.0, -35.0], atol=1e-6)
    assert np.allclose(pl.rotation @ pl.rotation.T, np.eye(3), atol=1e-12)
    assert 0.0 < pl.angle_deg() < 0.05  # the tilt, ~3 km / 6371 km, and the meridians converging
    rng = np.random.default_rng(5)
    for ned_local in rng.uniform(-800.0, 800.0, size=(20, 3)):
        point = ned_to_lla(ned_local, local)
        assert np.allclose(pl.to_fleet(ned_local), lla_to_ned(point, fleet), atol=1e-6)
        assert np.allclose(pl.to_local(lla_to_ned(point, fleet)), ned_local, atol=1e-6)


def test_placement_at_the_fleet_origin_is_the_identity() -> None:
    pl = placement(ZURICH, ZURICH)
    assert np.allclose(pl.offset, 0.0, atol=1e-9) and np.allclose(pl.rotation, np.eye(3), atol=1e-15)


def test_halfspaces_boxes_and_vectors() -> None:
    fleet = ZURICH
    pl = placement(ned_to_lla([300.0, 400.0, 5.0], fleet), fleet)
    rng = np.random.default_rng(7)
    A = rng.normal(size=(6, 3))
    b = rng.uniform(1.0, 5.0, size=6) + A @ np.array([310.0, 390.0, 0.0])
    A_l, b_l = pl.halfspaces_to_local(A, b)
    for q in rng.uniform([290.0, 380.0, -10.0], [330.0, 420.0, 10.0], size=(200, 3)):
        p = pl.to_local(q)
        assert np.array_equal(A @ q <= b, A_l @ p <= b_l + 1e-9) or np.allclose(A @ q - b, A_l @ p - b_l, atol=1e-9)
    lo, hi = pl.box_to_local([300.0, 390.0, -5.0], [320.0, 410.0, 0.0])
    corners = pl.to_local([[300.0, 390.0, -5.0], [320.0, 410.0, 0.0]])
    assert np.all(lo <= corners.min(axis=0) + 1e-12) and np.all(hi >= corners.max(axis=0) - 1e-12)
    assert np.all(hi - lo < np.array([20.0, 20.0, 5.0]) + 0.01)  # barely larger: the rotation is tiny
    v = np.array([1.0, 2.0, -0.5])
    assert np.allclose(pl.rotation @ pl.vectors_to_local(v), v, atol=1e-12)


def test_configured_offset() -> None:
    pl = Placement(np.array([10.0, -5.0, 0.5]))
    assert np.allclose(pl.to_fleet([0.0, 0.0, 0.0]), [10.0, -5.0, 0.5])
    assert np.allclose(pl.to_local([10.0, -5.0, 0.5]), 0.0)
    assert pl.angle_deg() == 0.0


def test_local_origin_from_home() -> None:
    """HOME_POSITION gives home geodetic and in the local frame: the local origin follows."""
    origin = (47.4, 8.55, 490.0)
    home_local = np.array([-0.24, -0.49, 1.48])  # PX4 SIH's, measured (autopilot-facts.md)
    home_lla = ned_to_lla(home_local, origin)
    back = local_origin_from_home(home_lla, home_local)
    assert np.allclose(lla_to_ned(back, origin), 0.0, atol=1e-6)


def test_check_lla() -> None:
    assert check_lla([47, 8, 400]) == (47.0, 8.0, 400.0)
    for bad in ([91, 0, 0], [0, 181, 0], [0, 0], [0, 0, float("nan")], "x", [0, 0, 1e6]):
        with pytest.raises(ValueError):
            check_lla(bad)


def test_sitl_mock_flat_earth_agrees_within_its_approximation() -> None:
    """sitl_mock converts with a flat earth of radius 6378137 m (as ArduPilot does): two mocks
    20 m apart are placed within 0.3 % of that by the WGS-84 conversion."""
    from sitl_mock.telemetry import Home

    origin = Home(*ZURICH)
    lat, lon, alt = origin.to_global(np.array([20.0, 15.0, -2.0]))
    ned = lla_to_ned((lat * 1e-7, lon * 1e-7, alt * 1e-3), ZURICH)
    assert np.allclose(ned, [20.0, 15.0, -2.0], atol=0.003 * 25.0 + 0.02)
