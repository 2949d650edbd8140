"""The interface every dynamics backend implements.

A backend owns the physical state of ``M = B * N`` UAVs (all worlds, world-major) and
advances it under body-frame velocity commands. Frames follow :mod:`companion.frames`:
positions and velocities in local NED, yaw from north positive right, commands in the
heading FRD frame ``(vel_fwd_m_s, vel_down_m_s, yaw_rate_rad_s)``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np


class Dynamics(ABC):
    """State of M UAVs and how velocity commands move it.

    Attributes (arrays of length M, read-only for callers, float64):
        pos_ned: [M, 3] positions (m).
        vel_ned: [M, 3] velocities (m/s).
        yaw_rad: [M] headings.
        yaw_rate_rad_s: [M] yaw rates.
    """

    pos_ned: np.ndarray
    vel_ned: np.ndarray
    yaw_rad: np.ndarray
    yaw_rate_rad_s: np.ndarray

    def __init__(self, num_uavs: int) -> None:
        self.num_uavs = num_uavs
        self.pos_ned = np.zeros((num_uavs, 3))
        self.vel_ned = np.zeros((num_uavs, 3))
        self.yaw_rad = np.zeros(num_uavs)
        self.yaw_rate_rad_s = np.zeros(num_uavs)

    @abstractmethod
    def reset(self, index: np.ndarray, pos_ned: np.ndarray, yaw_rad: np.ndarray) -> None:
        """Place UAVs ``index`` (int array [k]) at rest, hovering at ``pos_ned`` [k, 3] with ``yaw_rad`` [k]."""

    @abstractmethod
    def step(self, cmd_frd: np.ndarray, dt_s: float, active: np.ndarray) -> None:
        """Advance every UAV by ``dt_s`` seconds tracking ``cmd_frd`` [M, 3].

        UAVs with ``active`` False (crashed and removed) are not advanced.
        """
