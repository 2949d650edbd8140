"""What an asymmetric critic sees besides the policy's own observation (training only).

With ``AgentConfig.privileged_critic`` the critic's input gains, for every UAV, the true
state of its surroundings that the depth image shows only in part or not at all: the
nearest other UAVs (position and velocity relative to it), the nearest point of a static
obstacle and its altitude. The actor and the exported policy are unchanged — they still see
depth, goal and own velocity only — so flight needs nothing the vehicle does not have. This
is the asymmetric actor-critic of Pinto et al. 2017 ("Asymmetric Actor Critic for Image-Based
Robot Learning"): a critic that knows where the unseen neighbours are can value a start
among them correctly, and the actor's gradient comes from that critic. Not in the paper:
the paper's critic sees what the actor sees.

Every vector is in the UAV's heading frame (FRD, the frame of the goal in the state), scaled
to order one; a slot with nothing within :data:`PRIVILEGED_RANGE_M` is all zeros with its
presence flag 0.
"""

from __future__ import annotations

import numpy as np

from companion.frames import ned_to_frd
from sitl.sim.collision import nearest_obstacle_points

#: How many of the nearest other UAVs the critic sees.
PRIVILEGED_NEIGHBOURS = 3
#: Neighbours and obstacle points farther than this are left out (the D435's range).
PRIVILEGED_RANGE_M = 10.0
#: Scales: positions by the range, velocities by the forward speed limit, altitude by 10 m.
_POSITION_SCALE_M = PRIVILEGED_RANGE_M
_VELOCITY_SCALE_M_S = 2.0
_ALTITUDE_SCALE_M = 10.0
#: Per neighbour: relative position (3), relative velocity (3), present (1); then the nearest
#: obstacle point (3) and its presence (1); then the altitude (1).
PRIVILEGED_DIM = PRIVILEGED_NEIGHBOURS * 7 + 4 + 1


def privileged_features(pos_ned: np.ndarray, vel_ned: np.ndarray, yaw_rad: np.ndarray, present: np.ndarray,
                        uavs_per_world: int, boxes: np.ndarray, cylinders: np.ndarray) -> np.ndarray:
    """float32 [M, PRIVILEGED_DIM]: the critic's extra input for every UAV (rows world-major as in
    :class:`sitl.sim.env.SwarmEnv`). Only ``present`` UAVs count as neighbours."""
    m = pos_ned.shape[0]
    worlds, n = m // uavs_per_world, uavs_per_world
    pos = pos_ned.reshape(worlds, n, 3)
    vel = vel_ned.reshape(worlds, n, 3)
    rel_pos = pos[:, None, :, :] - pos[:, :, None, :]  # [B, i, j, 3]: j seen from i
    rel_vel = vel[:, None, :, :] - vel[:, :, None, :]
    dist = np.linalg.norm(rel_pos, axis=-1)
    visible = present.reshape(worlds, 1, n) & ~np.eye(n, dtype=bool)[None] & (dist <= PRIVILEGED_RANGE_M)
    dist = np.where(visible, dist, np.inf)
    k = min(PRIVILEGED_NEIGHBOURS, n - 1)
    order = np.argsort(dist, axis=2, kind="stable")[:, :, :k]  # [B, i, k]
    found = np.isfinite(np.take_along_axis(dist, order, axis=2))  # [B, i, k]
    yaw = yaw_rad.reshape(worlds, n, 1)
    near_pos = ned_to_frd(np.take_along_axis(rel_pos, order[..., None], axis=2), yaw) / _POSITION_SCALE_M
    near_vel = ned_to_frd(np.take_along_axis(rel_vel, order[..., None], axis=2), yaw) / _VELOCITY_SCALE_M_S
    neighbours = np.zeros((worlds, n, PRIVILEGED_NEIGHBOURS, 7))
    neighbours[:, :, :k, 0:3] = np.where(found[..., None], near_pos, 0.0)
    neighbours[:, :, :k, 3:6] = np.where(found[..., None], near_vel, 0.0)
    neighbours[:, :, :k, 6] = found

    to_obstacle = nearest_obstacle_points(pos, boxes, cylinders) - pos  # [B, N, 3], inf without obstacles
    with np.errstate(invalid="ignore"):
        near = np.linalg.norm(to_obstacle, axis=-1) <= PRIVILEGED_RANGE_M
    obstacle = np.zeros((worlds, n, 4))
    obstacle[..., 0:3] = np.where(near[..., None], ned_to_frd(np.where(near[..., None], to_obstacle, 0.0), yaw[..., 0])
                                  / _POSITION_SCALE_M, 0.0)
    obstacle[..., 3] = near
    altitude = -pos[..., 2:3] / _ALTITUDE_SCALE_M
    out = np.concatenate([neighbours.reshape(worlds, n, -1), obstacle, altitude], axis=-1)
    return out.reshape(m, PRIVILEGED_DIM).astype(np.float32)


def env_privileged_features(env) -> np.ndarray:
    """:func:`privileged_features` of a :class:`sitl.sim.env.SwarmEnv` as it is now."""
    d = env.dynamics
    return privileged_features(d.pos_ned, d.vel_ned, d.yaw_rad, env.present, env.uavs_per_world, env.boxes,
                               env.cylinders)
