"""Small simulated worlds that several test files fly."""

from __future__ import annotations

import numpy as np

from companion.spec import CAMERA_PRESETS
from sitl.sim.config import ScenarioConfig, SimConfig
from sitl.sim.env import SwarmEnv


def pole_world(pole_east_m: float = 0.0, max_episode_steps: int = 300) -> tuple[SwarmEnv, object]:
    """One UAV (D435 camera) 5 m south of a 0.2 m pole at 8 m altitude, its goal 5 m north of the pole;
    the pole stands ``pole_east_m`` east of the straight line. Returns the env and its first observation
    from the placed start."""
    cfg = SimConfig(num_uavs=1, camera=CAMERA_PRESETS["realsense_d435"], max_episode_steps=max_episode_steps,
                    scenario=ScenarioConfig(name="random", density=0.01, min_goal_distance_m=0.0))
    env = SwarmEnv(cfg, seed=0, cylinders=np.array([[[0.0, pole_east_m, 0.2, -30.0, 0.0]]]))
    env.reset()
    env.dynamics.reset(np.array([0]), np.array([[-5.0, 0.0, -8.0]]), np.array([0.0]))
    env.goal_ned[0] = [5.0, 0.0, -8.0]
    obs, *_ = env.step(np.zeros((1, 3), dtype=np.float32))
    return env, obs
