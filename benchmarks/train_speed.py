"""Training speed: SAC+AE updates per second and environment steps per second.

Measures, on this machine's CPU (``--threads`` torch threads):

* one full agent update (critic, actor every 2nd, targets, decoder) at batch 128 from a
  filled replay buffer, for each method and image size given;
* rollout throughput of the training loop: vectorised environment steps with the actor's
  sampled actions for the default preset's worlds of 8 UAVs (transitions per second).

The last line is one JSON object with ``updates_per_s`` (default ``fast`` preset: sac_ae,
32x32, its hidden units) and ``env_steps_per_s`` (agent transitions per second while acting),
plus every configuration measured.

Usage: ``python benchmarks/train_speed.py [--sizes 32 64] [--methods sac_ae cnn drq] [--seconds 10] [--smoke]``
(``--smoke``: the fast preset's configuration only, no warm-up update, a fraction of a second per
measurement, and the rollouts reuse that agent; what CI runs to keep the script working.)
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from companion.spec import DEFAULT_ACTION_SPEC, STATE_DIM, CameraSpec  # noqa: E402
from sitl.learn.agent import AgentConfig, SacAeAgent  # noqa: E402
from sitl.learn.buffer import FrameReplayBuffer  # noqa: E402
from sitl.learn.config import TrainConfig, make_sim_config, resolve_configs  # noqa: E402
from sitl.sim.env import SwarmEnv  # noqa: E402

#: Seconds per measurement with --smoke: enough for one timed update on a busy 2-core machine.
SMOKE_SECONDS = 0.3


def make_agent(method: str, size: int, hidden: int) -> SacAeAgent:
    """A freshly initialised agent of ``method`` for ``size`` x ``size`` depth images."""
    return SacAeAgent(AgentConfig(method=method, hidden_dim=hidden), CameraSpec(width=size, height=size),
                      DEFAULT_ACTION_SPEC)


def update_rate(agent: SacAeAgent, seconds: float, warmup_updates: int = 3) -> float:
    """Agent updates per second at batch 128 from a filled replay buffer (random transitions)."""
    cam = agent.camera
    size = cam.width
    action_dim = DEFAULT_ACTION_SPEC.dim
    buf = FrameReplayBuffer(4096, 64, cam.frames, size, size, STATE_DIM, action_dim)
    rng = np.random.default_rng(0)
    agents = np.arange(64)
    buf.start_episodes(agents, rng.uniform(0, 20, (64, size, size)))
    for _ in range(40):
        buf.add(agents, rng.normal(size=(64, STATE_DIM)), rng.uniform(-1, 1, (64, action_dim)), rng.normal(size=64),
                rng.uniform(0, 20, (64, size, size)), rng.normal(size=(64, STATE_DIM)), np.zeros(64, bool))
    for _ in range(warmup_updates):
        agent.update(buf.sample(128, agent.device))
    count, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds:
        agent.update(buf.sample(128, agent.device))
        count += 1
    return count / (time.perf_counter() - started)


def rollout_rate(seconds: float, agent: SacAeAgent | None = None) -> float:
    """Agent transitions per second while the default preset's worlds roll out with sampled actions.

    ``agent`` (default: a fresh one of the default size) must see the default preset's camera.
    """
    cfg = TrainConfig()
    sim = make_sim_config(cfg, cfg.num_worlds)
    env = SwarmEnv(sim, seed=0)
    agent = agent or SacAeAgent(AgentConfig(), sim.camera, DEFAULT_ACTION_SPEC)
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
    parser.add_argument("--sizes", type=int, nargs="+", default=None, help="image sides in pixels (default 32 64)")
    parser.add_argument("--methods", nargs="+", default=None, help="learning methods (default sac_ae cnn drq)")
    parser.add_argument("--hidden", type=int, nargs="+", default=None, help="hidden units (default 1024 256)")
    parser.add_argument("--seconds", type=float, default=None, help="seconds per measurement (default 10)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--smoke", action="store_true",
                        help="CI check: the fast preset's configuration only, no warm-up, a fraction of a second "
                             "per measurement")
    args = parser.parse_args()
    # The headline configuration: the default (fast) preset's method, image size and hidden units.
    cfg, agent_cfg = resolve_configs({}, {})
    headline = f"{agent_cfg.method}_{cfg.image_size}px_h{agent_cfg.hidden_dim}"
    if args.smoke:
        sizes = args.sizes or [cfg.image_size]
        methods = args.methods or [agent_cfg.method]
        hiddens = args.hidden or [agent_cfg.hidden_dim]
        seconds = SMOKE_SECONDS if args.seconds is None else args.seconds
    else:
        sizes, methods = args.sizes or [32, 64], args.methods or ["sac_ae", "cnn", "drq"]
        hiddens = args.hidden or [1024, 256]
        seconds = 10.0 if args.seconds is None else args.seconds
    if seconds <= 0:
        parser.error(f"--seconds must be > 0, got {seconds}")
    torch.set_num_threads(args.threads)

    rates, headline_agent = {}, None
    for size in sizes:
        for method in methods:
            for hidden in hiddens:
                agent = make_agent(method, size, hidden)
                if args.smoke and f"{method}_{size}px_h{hidden}" == headline:
                    headline_agent = agent  # the smoke run's rollouts reuse it: one fewer initialisation
                rate = update_rate(agent, seconds, warmup_updates=0 if args.smoke else 3)
                rates[f"{method}_{size}px_h{hidden}"] = round(rate, 2)
                print(f"{method:7s} {size}x{size} hidden {hidden:4d}: {rate:6.2f} updates/s "
                      f"({1000 / rate:6.1f} ms/update)", flush=True)
    env_rate = rollout_rate(seconds, headline_agent)
    print(f"rollouts ({cfg.num_worlds} worlds x {cfg.num_uavs} UAVs, actor sampling): {env_rate:.0f} transitions/s",
          flush=True)
    print(json.dumps({"benchmark": "train_speed", "threads": args.threads, "updates_per_s": rates.get(headline),
                      "updates_per_s_config": headline,
                      "env_steps_per_s": round(env_rate), "updates_per_s_by_config": rates}))


if __name__ == "__main__":
    main()
