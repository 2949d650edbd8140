"""The one definition of the frames swarmnav uses, shared by flight and simulation.

World frame: local NED, as MAVLink's ``MAV_FRAME_LOCAL_NED`` — x north, y east, z down,
metres, origin on the ground (so altitude is ``-z`` and the ground is the plane z = 0).

Body frame: the *heading frame* in FRD, as MAVLink's ``MAV_FRAME_BODY_NED`` — x forward
along the vehicle's heading, y right, z down. It is rotated from NED by the yaw angle only
(roll and pitch are ignored), which is what a velocity setpoint in ``MAV_FRAME_BODY_NED``
means to PX4 and ArduPilot. Yaw is the heading measured from north, positive turning
right (clockwise seen from above), so a yaw rate > 0 turns right. The depth camera looks
along body +x and is assumed level (gimbal- or attitude-compensated).

Every vector in this project carries its frame in its name: ``*_ned`` or ``*_frd``.

Attitude: ZYX Euler angles (yaw, then pitch, then roll) of the FRD body relative to NED, and
body-to-NED quaternions ``(w, x, y, z)``, as MAVLink's ATTITUDE / ODOMETRY carry them.

Geodetic: a local NED frame is tied to the Earth at an origin (latitude, longitude in degrees,
altitude in metres AMSL) with the local tangent plane approximation on the WGS-84 ellipsoid:
north and east are arc lengths along the meridian and prime-vertical radii of curvature at
the origin's latitude, on the ellipsoid's surface. Horizontal error against exact WGS-84
(ECEF) at sea level: about 1 mm at 100 m from the origin, 0.1 m at 1 km (it grows with the
square of the distance); at altitude h the scale is off by h / 6,371 km more (0.8 cm per
100 m at PX4 SITL's 488 m home), as PX4's own projection is. Altitude is ``origin altitude -
down`` (the Earth's curvature, 8 cm at 1 km, is ignored: one flat ground).
"""

from __future__ import annotations

import math

import numpy as np

WGS84_A_M = 6_378_137.0  # WGS-84 semi-major axis
WGS84_E2 = 6.69437999014e-3  # WGS-84 first eccentricity squared


def wrap_angle_rad(angle_rad: np.ndarray | float) -> np.ndarray | float:
    """Wrap an angle to [-pi, pi)."""
    return (np.asarray(angle_rad) + np.pi) % (2.0 * np.pi) - np.pi


def ned_to_frd(vec_ned: np.ndarray, yaw_rad: np.ndarray | float) -> np.ndarray:
    """Rotate vectors from the NED world frame into the heading (FRD body) frame.

    ``vec_ned`` has shape [..., 3]; ``yaw_rad`` broadcasts against ``vec_ned[..., 0]``.
    """
    vec_ned = np.asarray(vec_ned, dtype=np.float64)
    cos_yaw = np.cos(yaw_rad)
    sin_yaw = np.sin(yaw_rad)
    out = np.empty(np.broadcast_shapes(vec_ned.shape, np.shape(cos_yaw) + (3,)), dtype=np.float64)
    out[..., 0] = cos_yaw * vec_ned[..., 0] + sin_yaw * vec_ned[..., 1]
    out[..., 1] = -sin_yaw * vec_ned[..., 0] + cos_yaw * vec_ned[..., 1]
    out[..., 2] = vec_ned[..., 2]
    return out


def frd_to_ned(vec_frd: np.ndarray, yaw_rad: np.ndarray | float) -> np.ndarray:
    """Rotate vectors from the heading (FRD body) frame into the NED world frame."""
    vec_frd = np.asarray(vec_frd, dtype=np.float64)
    cos_yaw = np.cos(yaw_rad)
    sin_yaw = np.sin(yaw_rad)
    out = np.empty(np.broadcast_shapes(vec_frd.shape, np.shape(cos_yaw) + (3,)), dtype=np.float64)
    out[..., 0] = cos_yaw * vec_frd[..., 0] - sin_yaw * vec_frd[..., 1]
    out[..., 1] = sin_yaw * vec_frd[..., 0] + cos_yaw * vec_frd[..., 1]
    out[..., 2] = vec_frd[..., 2]
    return out


# --------------------------------------------------------------------------- attitude


def quaternion_to_euler(q_wxyz) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in rad of a body-to-NED quaternion (w, x, y, z)."""
    w, x, y, z = (float(v) for v in q_wxyz)
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def yaw_to_quaternion(yaw_rad: float) -> list[float]:
    """The body-to-NED quaternion (w, x, y, z) of a level vehicle heading ``yaw_rad``."""
    return [math.cos(yaw_rad / 2.0), 0.0, 0.0, math.sin(yaw_rad / 2.0)]


def body_to_ned_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation matrix taking FRD body vectors into NED (ZYX Euler angles, rad)."""
    cr, sr, cp, sp, cy, sy = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    return np.array([
        [cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
        [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
        [-sp, sr * cp, cr * cp],
    ])


def euler_yaw_rate(roll: float, pitch: float, pitchspeed: float, yawspeed: float) -> float:
    """Heading rate (rad/s) from body rates: (q sin(roll) + r cos(roll)) / cos(pitch)."""
    return (pitchspeed * math.sin(roll) + yawspeed * math.cos(roll)) / max(math.cos(pitch), 1e-3)


# --------------------------------------------------------------------------- geodetic


def _radii_m(origin_lat_deg: float) -> tuple[float, float]:
    """(metres per radian of latitude, metres per radian of longitude) at ``origin_lat_deg``."""
    lat = math.radians(origin_lat_deg)
    den = math.sqrt(1.0 - WGS84_E2 * math.sin(lat) ** 2)
    meridian_m = WGS84_A_M * (1.0 - WGS84_E2) / den**3
    prime_vertical_m = WGS84_A_M / den
    return meridian_m, prime_vertical_m * math.cos(lat)


def ned_to_geodetic(pos_ned: np.ndarray, origin_lat_deg: float, origin_lon_deg: float,
                    origin_alt_m: float = 0.0) -> np.ndarray:
    """Local NED positions [..., 3] (m) -> [..., 3] (latitude deg, longitude deg, altitude m).

    Altitude is ``origin_alt_m - down``; see the module docstring for the approximation.
    """
    pos_ned = np.asarray(pos_ned, dtype=np.float64)
    m_per_rad_lat, m_per_rad_lon = _radii_m(origin_lat_deg)
    out = np.empty(pos_ned.shape, dtype=np.float64)
    out[..., 0] = origin_lat_deg + np.degrees(pos_ned[..., 0] / m_per_rad_lat)
    out[..., 1] = origin_lon_deg + np.degrees(pos_ned[..., 1] / m_per_rad_lon)
    out[..., 2] = origin_alt_m - pos_ned[..., 2]
    return out


def geodetic_to_ned(geo: np.ndarray, origin_lat_deg: float, origin_lon_deg: float,
                    origin_alt_m: float = 0.0) -> np.ndarray:
    """Inverse of :func:`ned_to_geodetic`: [..., 3] (latitude deg, longitude deg, altitude m) -> NED metres."""
    geo = np.asarray(geo, dtype=np.float64)
    m_per_rad_lat, m_per_rad_lon = _radii_m(origin_lat_deg)
    out = np.empty(geo.shape, dtype=np.float64)
    out[..., 0] = np.radians(geo[..., 0] - origin_lat_deg) * m_per_rad_lat
    out[..., 1] = np.radians(geo[..., 1] - origin_lon_deg) * m_per_rad_lon
    out[..., 2] = origin_alt_m - geo[..., 2]
    return out
