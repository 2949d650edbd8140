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
"""

from __future__ import annotations

import numpy as np


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
