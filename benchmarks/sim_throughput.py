"""Throughput of the full environment step: dynamics, 3-frame depth observation and reward.

Runs the random (medium) scenario with the straight-to-goal reference controller, resetting
worlds as their episodes end, in one process on one core (numba serial kernels), for
N = 8, 32 and 64 UAVs per world. It prints a table and, as its last line, one JSON object:

* ``realtime_factor``: simulated swarm-seconds per wall-second for one 8-UAV world;
* ``realtime_factor_batched``: the same with ``--worlds`` 8-UAV worlds stepped together,
  counting every world's seconds (what training and evaluation see);
* per N: agent-steps per second (one UAV advanced by one 0.1 s control period, with its
  new depth frame and reward) for a single world and for the batch.

Usage: ``python benchmarks/sim_throughput.py [--seconds 3] [--worlds 64] [--memory-steps N] [--smoke]``
(``--memory-steps N``: every UAV's state also carries remembered depth over N control steps,
``companion.spec.MemorySpec``, what ``sitl.train --memory-steps`` trains with)
(``--smoke``: N = 8 only, 4 batched worlds, 0.2 s per configuration; what CI runs to keep the
script working.)
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from companion.spec import MEMORY_MAX_STEPS, MemorySpec, memory_for_steps  # noqa: E402
from sitl.sim.baselines import straight_to_goal  # noqa: E402
from sitl.sim.config import SimConfig  # noqa: E402
from sitl.sim.env import SwarmEnv  # noqa: E402


def measure(num_uavs: int, num_worlds: int, seconds: float, memory: MemorySpec | None = None) -> dict:
    """Step the environment for about ``seconds`` and return its throughput."""
    config = SimConfig(num_uavs=num_uavs, num_worlds=num_worlds, record_paths=False, memory=memory)
    env = SwarmEnv(config, seed=0)
    obs = env.reset()
    for _ in range(5):  # warm-up (numba's compiled kernels load from cache)
        obs, *_ = env.step(straight_to_goal(obs.state))
    steps, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds:
        obs, *_ = env.step(straight_to_goal(obs.state))
        if env.world_done.any():
            obs = env.reset_worlds(env.world_done)
        steps += 1
    wall = time.perf_counter() - started
    sim_seconds = steps * config.control_period_s * num_worlds
    return {
        "uavs": num_uavs,
        "worlds": num_worlds,
        "steps_per_s": steps / wall,
        "realtime_factor": sim_seconds / wall,
        "agent_steps_per_s": steps * num_uavs * num_worlds / wall,
        "ms_per_step": 1000 * wall / steps,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=None, help="measuring time per configuration (default 3)")
    parser.add_argument("--worlds", type=int, default=None, help="worlds in the batched measurement (default 64)")
    parser.add_argument("--memory-steps", type=int, default=0,
                        help="remembered depth over this many control steps in every UAV's state (default 0: none)")
    parser.add_argument("--smoke", action="store_true",
                        help="CI check: N = 8 only, 4 batched worlds, 0.2 s per configuration")
    args = parser.parse_args()
    seconds = args.seconds if args.seconds is not None else (0.2 if args.smoke else 3.0)
    batched_worlds = args.worlds if args.worlds is not None else (4 if args.smoke else 64)
    if seconds <= 0 or batched_worlds < 1:
        parser.error(f"--seconds must be > 0 and --worlds >= 1, got {seconds} and {batched_worlds}")
    if not 0 <= args.memory_steps <= MEMORY_MAX_STEPS:
        parser.error(f"--memory-steps must be in 0..{MEMORY_MAX_STEPS}, got {args.memory_steps}")
    memory = memory_for_steps(args.memory_steps)
    swarm_sizes = (8,) if args.smoke else (8, 32, 64)

    results = []
    for n in swarm_sizes:
        for worlds in (1, max(1, batched_worlds * 8 // n)):
            r = measure(n, worlds, seconds, memory)
            results.append(r)
            print(f"N={n:3d} worlds={worlds:3d}: {r['ms_per_step']:7.3f} ms/step  "
                  f"real-time x{r['realtime_factor']:8.1f}  {r['agent_steps_per_s']:9.0f} agent-steps/s", flush=True)
    single8 = next(r for r in results if r["uavs"] == 8 and r["worlds"] == 1)
    batch8 = next((r for r in results if r["uavs"] == 8 and r["worlds"] > 1), single8)  # --worlds 1: no batch
    summary = {
        "benchmark": "sim_throughput",
        "camera": "32x32 planar depth, 90 deg hfov, 4x4 min-pooled sub-rays",
        "memory_steps": args.memory_steps,
        "realtime_factor": round(single8["realtime_factor"], 1),
        "realtime_factor_batched": round(batch8["realtime_factor"], 1),
        "batched_worlds": batch8["worlds"],
        "agent_steps_per_s": {f"N{r['uavs']}_worlds{r['worlds']}": round(r["agent_steps_per_s"]) for r in results},
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
