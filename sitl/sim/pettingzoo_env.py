"""PettingZoo ``ParallelEnv`` view of one swarm world, built on :class:`sitl.sim.env.SwarmEnv`.

Agents are named ``uav_0`` .. ``uav_{N-1}``. Each observation is a dict with ``depth``
(float32 [3, H, W], metres) and ``state`` (float32 [6]); each action a float32 [3]
``(vel_fwd_m_s, vel_down_m_s, yaw_rate_rad_s)``. An agent leaves ``agents`` once its
episode ends (arrival, collision or timeout), as the PettingZoo contract asks.
"""

from __future__ import annotations

import functools
from dataclasses import replace

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from companion.spec import state_dim_for
from sitl.sim.config import SimConfig
from sitl.sim.env import SwarmEnv
from sitl.sim.metrics import Outcome


class SwarmParallelEnv(ParallelEnv):
    """One world of N UAVs as a PettingZoo parallel environment."""

    metadata = {"name": "swarmnav_v0", "render_modes": []}

    def __init__(self, config: SimConfig | None = None) -> None:
        config = replace(config or SimConfig(), num_worlds=1)
        self.core = SwarmEnv(config)
        self.possible_agents = [f"uav_{i}" for i in range(config.num_uavs)]
        self.agents: list[str] = []
        cam = config.camera
        self._observation_space = spaces.Dict({
            "depth": spaces.Box(0.0, cam.max_range_m, (cam.frames, cam.height, cam.width), np.float32),
            "state": spaces.Box(-np.inf, np.inf, (state_dim_for(config.memory),), np.float32),
        })
        spec = self.core.action_spec
        self._action_space = spaces.Box(spec.low_array(), spec.high_array(), dtype=np.float32)

    @functools.lru_cache(maxsize=None)
    def observation_space(self, agent: str) -> spaces.Space:
        return self._observation_space

    @functools.lru_cache(maxsize=None)
    def action_space(self, agent: str) -> spaces.Space:
        return self._action_space

    def _obs_dict(self, agents: list[str]) -> dict[str, dict[str, np.ndarray]]:
        obs = self.core.observation()
        return {a: {"depth": obs.depth[i].copy(), "state": obs.state[i]} for i, a in enumerate(self.possible_agents) if a in agents}

    def reset(self, seed: int | None = None, options: dict | None = None):
        self.core.reset(seed=seed)
        self.agents = list(self.possible_agents)
        return self._obs_dict(self.agents), {a: {} for a in self.agents}

    def step(self, actions: dict[str, np.ndarray]):
        full = np.zeros((self.core.num_agents, 3), dtype=np.float32)
        for i, agent in enumerate(self.possible_agents):
            if agent in actions:
                full[i] = actions[agent]
        _, reward, terminated, truncated, info = self.core.step(full)
        live = list(self.agents)
        index = {a: i for i, a in enumerate(self.possible_agents)}
        observations = self._obs_dict(live)
        rewards = {a: float(reward[index[a]]) for a in live}
        terminations = {a: bool(terminated[index[a]]) for a in live}
        truncations = {a: bool(truncated[index[a]]) for a in live}
        infos = {a: ({"outcome": Outcome(int(info["outcome"][index[a]])).code}
                     if info["outcome"][index[a]] != Outcome.RUNNING else {}) for a in live}
        self.agents = [a for a in live if not (terminations[a] or truncations[a])]
        return observations, rewards, terminations, truncations, infos
