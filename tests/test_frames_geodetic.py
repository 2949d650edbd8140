"""companion.frames: the one geodetic conversion and the attitude math (exact references, no mocks)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.frames import (
    WGS84_A_M,
    WGS84_E2,
    body_to_ned_matrix,
    euler_yaw_rate,
    geodetic_to_ned,
    ned_to_frd,
    ned_to_geodetic,
    quaternion_to_euler,
    yaw_to_quaternion,
)

HOME = (47.397742, 8.545594, 488.0)  # PX4 SITL's default home


def _ecef(lat_deg: float, lon_deg: float, alt_m: float) -> np.ndarray:
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    n = WGS84_A_M / math.sqrt(1.0 - WGS84_E2 * math.sin(lat) ** 2)
    return np.array([(n + alt_m) * math.cos(lat) * math.cos(lon), (n + alt_m) * math.cos(lat) * math.sin(lon),
                     (n * (1.0 - WGS84_E2) + alt_m) * math.sin(lat)])


def _exact_ned(geo: np.ndarray, origin: tuple[float, float, float]) -> np.ndarray:
    """Exact WGS-84 NED of a geodetic point in the tangent frame at ``origin`` (via ECEF)."""
    lat, lon = math.radians(origin[0]), math.radians(origin[1])
    rot = np.array([[-math.sin(lat) * math.cos(lon), -math.sin(lat) * math.sin(lon), math.cos(lat)],
                    [-math.sin(lon), math.cos(lon), 0.0],
                    [-math.cos(lat) * math.cos(lon), -math.cos(lat) * math.sin(lon), -math.sin(lat)]])
    return rot @ (_ecef(*geo) - _ecef(*origin))


def test_geodetic_round_trip_and_documented_accuracy():
    pos = np.array([[0.0, 0.0, 0.0], [30.0, -12.0, -5.0], [-70.0, 70.0, 0.0], [700.0, -700.0, -50.0]])
    geo = ned_to_geodetic(pos, *HOME)
    assert np.allclose(geodetic_to_ned(geo, *HOME), pos, atol=1e-9)
    assert geo[1, 2] == pytest.approx(HOME[2] + 5.0)
    for origin in (HOME[:2] + (0.0,), HOME):  # the documented accuracy: at sea level, and at altitude
        for p in pos:
            g = ned_to_geodetic(p, *origin)
            horizontal_error_m = float(np.linalg.norm(_exact_ned(g, origin)[:2] - p[:2]))
            distance_m = float(np.linalg.norm(p[:2]))
            bound_m = 1.1e-3 * (distance_m / 100.0) ** 2 + distance_m * origin[2] / 6_371_000.0 + 1e-6
            assert horizontal_error_m <= bound_m, (origin, p, horizontal_error_m)


def test_attitude_math():
    for yaw in (-3.0, -0.4, 0.0, 1.2, 3.1):
        roll, pitch, got = quaternion_to_euler(yaw_to_quaternion(yaw))
        assert (roll, pitch) == pytest.approx((0.0, 0.0), abs=1e-12)
        assert got == pytest.approx(yaw, abs=1e-12)
        vel_ned = np.array([1.0, -2.0, 0.5])
        assert np.allclose(body_to_ned_matrix(0.0, 0.0, yaw).T @ vel_ned, ned_to_frd(vel_ned, yaw))
    assert euler_yaw_rate(0.0, 0.0, 0.3, 0.7) == pytest.approx(0.7)
