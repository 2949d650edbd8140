"""Kinematic quadrotor: velocity commands tracked by a first-order lag with acceleration limits.

This is what a multicopter's velocity controller looks like from outside: the commanded
body-frame velocity is rotated into NED with the current heading, and the NED velocity
approaches it with time constant ``tau`` while its acceleration is capped (horizontal and
vertical separately), as PX4's ``MPC_ACC_HOR`` / ``MPC_ACC_UP_MAX`` do. Velocity lives in
NED, so a UAV that turns keeps part of its old velocity for a moment — it slides through
turns as a real multicopter does. Yaw rate follows the same law with its own limits.
Integration is explicit Euler on ``substep_s`` sub-steps of each control period.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from sitl.sim.dynamics.base import Dynamics


@dataclass(frozen=True)
class KinematicParams:
    """Response of the velocity controller (defaults close to PX4's multicopter defaults)."""

    tau_horizontal_s: float = 0.25
    tau_vertical_s: float = 0.25
    tau_yaw_s: float = 0.15
    max_acc_horizontal_m_s2: float = 3.0
    max_acc_vertical_m_s2: float = 2.0
    max_yaw_acc_rad_s2: float = 3.0
    substep_s: float = 0.02


class KinematicDynamics(Dynamics):
    """Fast vectorized kinematic model of M quadrotors (numba kernel)."""

    def __init__(self, num_uavs: int, params: KinematicParams = KinematicParams()) -> None:
        super().__init__(num_uavs)
        self.params = params

    def reset(self, index: np.ndarray, pos_ned: np.ndarray, yaw_rad: np.ndarray) -> None:
        self.pos_ned[index] = pos_ned
        self.yaw_rad[index] = yaw_rad
        self.vel_ned[index] = 0.0
        self.yaw_rate_rad_s[index] = 0.0

    def step(self, cmd_frd: np.ndarray, dt_s: float, active: np.ndarray) -> None:
        p = self.params
        n_sub = max(1, int(round(dt_s / p.substep_s)))
        _integrate(
            self.pos_ned, self.vel_ned, self.yaw_rad, self.yaw_rate_rad_s,
            np.ascontiguousarray(cmd_frd, dtype=np.float64), np.ascontiguousarray(active, dtype=np.bool_),
            dt_s / n_sub, n_sub,
            p.tau_horizontal_s, p.tau_vertical_s, p.tau_yaw_s,
            p.max_acc_horizontal_m_s2, p.max_acc_vertical_m_s2, p.max_yaw_acc_rad_s2,
        )


@numba.njit(cache=True)
def _integrate(pos, vel, yaw, yaw_rate, cmd, active, h, n_sub, tau_h, tau_v, tau_yaw, acc_h, acc_v, acc_yaw):
    for m in range(pos.shape[0]):
        if not active[m]:
            continue
        for _ in range(n_sub):
            c = math.cos(yaw[m])
            s = math.sin(yaw[m])
            # Desired NED velocity: the body command rotated by the current heading.
            target_n = c * cmd[m, 0]
            target_e = s * cmd[m, 0]
            acc_n = (target_n - vel[m, 0]) / tau_h
            acc_e = (target_e - vel[m, 1]) / tau_h
            norm = math.sqrt(acc_n * acc_n + acc_e * acc_e)
            if norm > acc_h:
                acc_n *= acc_h / norm
                acc_e *= acc_h / norm
            acc_d = min(max((cmd[m, 1] - vel[m, 2]) / tau_v, -acc_v), acc_v)
            yaw_acc = min(max((cmd[m, 2] - yaw_rate[m]) / tau_yaw, -acc_yaw), acc_yaw)
            vel[m, 0] += acc_n * h
            vel[m, 1] += acc_e * h
            vel[m, 2] += acc_d * h
            yaw_rate[m] += yaw_acc * h
            pos[m, 0] += vel[m, 0] * h
            pos[m, 1] += vel[m, 1] * h
            pos[m, 2] += vel[m, 2] * h
            # companion.frames.wrap_angle_rad, spelled out: this loop is compiled by numba
            yaw[m] = (yaw[m] + yaw_rate[m] * h + math.pi) % (2.0 * math.pi) - math.pi
