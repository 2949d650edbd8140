"""The paper's reward, eqs. 2-4: progress to the goal plus a penalty for nearby surfaces.

Beside it, two training options that are not the paper's: a price on flying where the camera does
not look (``RewardConfig.w_blind``, :func:`sitl.sim.camera.blind_speed_m_s`) and one on commanding
more forward speed than the corridor ahead allows (``RewardConfig.w_corridor``).
"""

from __future__ import annotations

import numpy as np

from sitl.sim.config import RewardConfig


def nearest_depth_m(depth_m: np.ndarray) -> np.ndarray:
    """The paper's d_min of eq. 4: the smallest depth in each UAV's newest image [M, H, W] -> [M].

    It counts the ground (``RewardConfig.avoid_counts_ground``); without it, the environment
    takes d_min from the camera kernel's nearest UAV or obstacle (``DepthCamera.render_with_objects``).
    """
    return depth_m.reshape(depth_m.shape[0], -1).min(axis=1)


def goal_reward(prev_dist_m: np.ndarray, dist_m: np.ndarray, arrived: np.ndarray, cfg: RewardConfig) -> np.ndarray:
    """Eq. 3: r_arrival inside the arrival radius, else w_goal times the progress made."""
    return np.where(arrived, cfg.r_arrival, cfg.w_goal * (prev_dist_m - dist_m))


def avoid_reward(collided: np.ndarray, d_min_m: np.ndarray, cfg: RewardConfig,
                 hit_uav: np.ndarray | None = None) -> np.ndarray:
    """Eq. 4: r_collision on a collision, else w_avoid * max(d_safe - d_min, 0).

    ``hit_uav`` marks the collisions with another UAV; they cost ``r_collision_uav_extra`` more
    (0 in the paper, where it makes no difference).
    """
    r_collision = cfg.r_collision if hit_uav is None else cfg.r_collision + cfg.r_collision_uav_extra * hit_uav
    return np.where(collided, r_collision, cfg.w_avoid * np.maximum(cfg.d_safe_m - d_min_m, 0.0))


def step_reward(prev_dist_m: np.ndarray, dist_m: np.ndarray, arrived: np.ndarray, collided: np.ndarray,
                d_min_m: np.ndarray, cfg: RewardConfig, hit_uav: np.ndarray | None = None,
                blind_speed: np.ndarray | None = None, corridor_excess: np.ndarray | None = None) -> np.ndarray:
    """Eq. 2: r = r_goal + r_avoid. A UAV that collides gets no arrival bonus in the same step.

    ``blind_speed`` (:func:`sitl.sim.camera.blind_speed_m_s`) adds ``cfg.w_blind`` per m/s on the steps that end
    neither in a collision nor in arrival (not in the paper; ``w_blind`` 0 leaves eq. 2 as it is);
    ``corridor_excess`` (m/s of forward command above the governor's cap) adds ``cfg.w_corridor`` per m/s on the
    same steps (not in the paper either).
    """
    reward = goal_reward(prev_dist_m, dist_m, arrived & ~collided, cfg) + avoid_reward(collided, d_min_m, cfg, hit_uav)
    if blind_speed is not None and cfg.w_blind:
        reward = reward + np.where(collided | arrived, 0.0, cfg.w_blind * blind_speed)
    if corridor_excess is not None and cfg.w_corridor:
        reward = reward + np.where(collided | arrived, 0.0, cfg.w_corridor * corridor_excess)
    return reward
