"""Evaluation speed of ``python -m sitl.swarm_test``: episodes per second, circle scenario, N = 8.

Flies ``--episodes`` (default 100) episodes of the 8-UAV circle (radius 12 m) exactly as
the command does (parallel worlds, one policy batch over every acting UAV, paths
recorded) with three controllers: a policy, the straight-to-goal reference and ORCA.

The policy is ``models/policy.pt`` when it exists (or ``--policy PATH``); otherwise a
freshly initialised actor of the fast training preset's size (32x32 depth, 1024 hidden
units) is exported to a temporary file. Its inference costs the same as a trained
policy's, but it never arrives, so every UAV flies the full 40 s time limit: an upper
bound on the time a trained policy needs (crossing the circle takes 12-20 s, not 40 s).

Usage: ``python benchmarks/eval_speed.py [--episodes 100] [--threads 2] [--policy PATH] [--smoke]``.
The last line printed is one JSON object. ``--smoke`` (what CI runs to keep the script working)
flies one episode per controller, cut at 50 steps (5 s), after a 10-step warm-up.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import torch  # noqa: E402

from sitl.sim.config import ScenarioConfig  # noqa: E402
from sitl.eval.evaluate import EvalSettings, evaluate_method  # noqa: E402
from sitl.eval.methods import DEFAULT_POLICY, resolve_method  # noqa: E402

#: --smoke: steps after which each controller's one episode ends (time limit).
SMOKE_MAX_STEPS = 50


def untrained_policy(path: Path) -> Path:
    """Export a randomly initialised fast-preset actor (same network size as a trained policy)."""
    from companion.spec import DEFAULT_ACTION_SPEC, CameraSpec
    from sitl.learn.agent import AgentConfig, SacAeAgent
    from sitl.learn.export import export_policy

    torch.manual_seed(0)
    agent = SacAeAgent(AgentConfig(), CameraSpec(width=32, height=32), DEFAULT_ACTION_SPEC)
    export_policy(agent, path, 0.1, {"method": "untrained", "note": "benchmark stand-in for a trained policy"})
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=None, help="episodes per controller (default 100)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2, the machine's cores)")
    parser.add_argument("--policy", type=Path, default=None, help="policy file (default models/policy.pt if present)")
    parser.add_argument("--smoke", action="store_true",
                        help="CI check: one episode per controller cut at 50 steps, after a 10-step warm-up")
    args = parser.parse_args()
    episodes = args.episodes if args.episodes is not None else (1 if args.smoke else 100)
    if episodes < 1:
        parser.error(f"--episodes must be >= 1, got {episodes}")
    torch.set_num_threads(args.threads)
    # Warm-up (numba's kernels, torch's first calls) before each timed run; the smoke run's is a few steps.
    warmup = EvalSettings(episodes=1, batch_worlds=1, max_episode_steps=10) if args.smoke else \
        EvalSettings(episodes=2, batch_worlds=2)

    with tempfile.TemporaryDirectory() as tmp:
        if args.policy is not None:
            policy_path, source = args.policy, str(args.policy)
        elif DEFAULT_POLICY.exists():
            policy_path, source = DEFAULT_POLICY, str(DEFAULT_POLICY)
        else:
            policy_path = untrained_policy(Path(tmp) / "untrained.pt")
            source = "untrained fast-preset actor (flies the full time limit)"
        settings = EvalSettings(scenario=ScenarioConfig(name="circle", circle_radius_m=12.0), num_uavs=8,
                                episodes=episodes, seed=0)
        if args.smoke:  # the policy's inference dominates: a short episode checks the same path
            settings = replace(settings, max_episode_steps=SMOKE_MAX_STEPS)
        out = {"scenario": "circle r=12 m", "num_uavs": 8, "episodes": episodes, "threads": args.threads,
               "policy_source": source}
        for name, spec in (("policy", str(policy_path)), ("straight", "straight"), ("orca", "orca")):
            method = resolve_method(spec)
            evaluate_method(method, warmup, progress=False)
            result = evaluate_method(method, settings, progress=False)
            steps = max(r.duration_s for r in result.records) / result.sim_config.control_period_s
            print(f"{name:8s} {episodes} episodes in {result.wall_s:6.1f} s = {result.episodes_per_s:6.2f} "
                  f"episodes/s (success {result.summary['success_rate']:.3f}, longest episode {steps:.0f} steps)")
            out[f"{name}_episodes_per_s"] = round(result.episodes_per_s, 2)
            out[f"{name}_wall_s"] = round(result.wall_s, 2)
            out[f"{name}_success_rate"] = round(result.summary["success_rate"], 3)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
