"""Training speed: SAC+AE updates per second and environment steps per second.

Measures, on this machine's CPU (``--threads`` torch threads):

* one full agent update (critic, actor every 2nd, targets, decoder) at batch 128 from a
  filled replay buffer, for each method and image size given;
* rollout throughput of the training loop: vectorised environment steps with the actor's
  sampled actions for the default preset's worlds of 8 UAVs (transitions per second).

The last line is one JSON object with ``updates_per_s`` (default ``fast`` preset: sac_ae,
32x32, its hidden units) and ``env_steps_per_s`` (agent transitions per second while acting),
plus every configuration measured.

Usage: ``python benchmarks/train_speed.py [--sizes 32 64] [--methods sac_ae cnn drq] [--seconds 10]``
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from companion.spec import DEFAULT_ACTION_SPEC, CameraSpec
from sitl.learn.agent import AgentConfig, SacAeAgent
from sitl.learn.buffer import FrameReplayBuffer
from sitl.learn.config import PRESETS, TrainConfig, make_sim_config
from sitl.sim.env import SwarmEnv


def update_rate(method: str, size: int, hidden: int, seconds: float) -> float:
    cam = CameraSpec(width=size, height=size)
    agent = SacAeAgent(AgentConfig(method=method, hidden_dim=hidden), cam, DEFAULT_ACTION_SPEC)
    buf = FrameReplayBuffer(4096, 64, 3, size, size, 6, 3)
    rng = np.random.default_rng(0)
    agents = np.arange(64)
    buf.start_episodes(agents, rng.uniform(0, 20, (64, size, size)))
    for _ in range(40):
        buf.add(agents, rng.normal(size=(64, 6)), rng.uniform(-1, 1, (64, 3)), rng.normal(size=64),
                rng.uniform(0, 20, (64, size, size)), rng.normal(size=(64, 6)), np.zeros(64, bool))
    for _ in range(3):
        agent.update(buf.sample(128, agent.device))
    count, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds:
        agent.update(buf.sample(128, agent.device))
        count += 1
    return count / (time.perf_counter() - started)


def rollout_rate(seconds: float) -> float:
    cfg = TrainConfig()
    sim = make_sim_config(cfg, cfg.num_worlds)
    env = SwarmEnv(sim, seed=0)
    agent = SacAeAgent(AgentConfig(), sim.camera, DEFAULT_ACTION_SPEC)
    obs = env.reset()
    transitions, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds:
        transitions += int(env.acting.sum())
        obs, *_ = env.step(agent.act(obs.depth, obs.state, explore=True))
        if env.world_done.any():
            obs = env.reset_worlds(env.world_done)
    return transitions / (time.perf_counter() - started)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[32, 64])
    parser.add_argument("--methods", nargs="+", default=["sac_ae", "cnn", "drq"])
    parser.add_argument("--hidden", type=int, nargs="+", default=[1024, 256])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    rates = {}
    for size in args.sizes:
        for method in args.methods:
            for hidden in args.hidden:
                rate = update_rate(method, size, hidden, args.seconds)
                rates[f"{method}_{size}px_h{hidden}"] = round(rate, 2)
                print(f"{method:7s} {size}x{size} hidden {hidden:4d}: {rate:6.2f} updates/s "
                      f"({1000 / rate:6.1f} ms/update)", flush=True)
    env_rate = rollout_rate(args.seconds)
    cfg = TrainConfig()
    print(f"rollouts ({cfg.num_worlds} worlds x {cfg.num_uavs} UAVs, actor sampling): {env_rate:.0f} transitions/s",
          flush=True)
    fast_hidden = PRESETS["fast"]["agent"]["hidden_dim"]
    default = rates.get(f"sac_ae_32px_h{fast_hidden}")
    print(json.dumps({"benchmark": "train_speed", "threads": args.threads, "updates_per_s": default,
                      "updates_per_s_config": f"sac_ae_32px_h{fast_hidden}",
                      "env_steps_per_s": round(env_rate), "updates_per_s_by_config": rates}))


if __name__ == "__main__":
    main()
