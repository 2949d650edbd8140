"""The PettingZoo ParallelEnv passes PettingZoo's own conformance test."""

from __future__ import annotations

from pettingzoo.test import parallel_api_test

from sitl.sim.config import ScenarioConfig, SimConfig
from sitl.sim.pettingzoo_env import SwarmParallelEnv


def test_parallel_api_random_scenario():
    parallel_api_test(SwarmParallelEnv(SimConfig(num_uavs=4, max_episode_steps=60)), num_cycles=200)


def test_parallel_api_circle_scenario_agents_leave_when_done():
    env = SwarmParallelEnv(SimConfig(num_uavs=3, scenario=ScenarioConfig(name="circle", circle_radius_m=2.0)))
    parallel_api_test(env, num_cycles=100)
    obs, _ = env.reset(seed=0)
    assert set(obs) == {"uav_0", "uav_1", "uav_2"} and obs["uav_0"]["depth"].shape == (3, 32, 32)
    steps = 0
    while env.agents and steps < 400:
        _, _, term, trunc, infos = env.step({a: [2.0, 0.0, 0.0] for a in env.agents})
        steps += 1
    assert not env.agents  # everyone collided at the centre or arrived
    assert steps < 100
