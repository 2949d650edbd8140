"""A short simulated swarm flight: ``python -m sitl.demo --n 8``.

Flies the no-avoidance reference controller (straight at the goal) in a scenario, prints
the paper's metrics and writes a top/side view of the trajectories. It is the quickstart's
first run until a trained policy ships; ``python -m sitl.swarm_test`` then takes over.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from sitl.cli_args import positive_int
from sitl.sim.baselines import straight_to_goal
from sitl.sim.config import CIRCLE_RADIUS_M, DENSITIES, SCENARIOS, ScenarioConfig, SimConfig, density_from_name
from sitl.sim.dynamics import DYNAMICS_NAMES
from sitl.sim.env import SwarmEnv
from sitl.sim.metrics import UAVRecord, summarize


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m sitl.demo", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=positive_int, default=8, help="UAVs per world (default 8)")
    parser.add_argument("--scenario", choices=SCENARIOS, default="circle", help="scenario (default circle)")
    parser.add_argument("--density", default="medium",
                        help=f"random scenario density: {', '.join(DENSITIES)} or UAV/m^3 (default medium)")
    parser.add_argument("--radius", type=float, default=CIRCLE_RADIUS_M, help=f"circle radius in m (default {CIRCLE_RADIUS_M:g})")
    parser.add_argument("--episodes", type=positive_int, default=10, help="episodes, run in parallel (default 10)")
    parser.add_argument("--dynamics", choices=DYNAMICS_NAMES, default=DYNAMICS_NAMES[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("runs/demo"), help="output folder (default runs/demo)")
    args = parser.parse_args(argv)
    try:
        args.density = density_from_name(args.density)
        args.scenario_config = ScenarioConfig(name=args.scenario, density=args.density, circle_radius_m=args.radius)
    except ValueError as err:
        parser.error(str(err))
    return args


def plot_trajectories(records: list[UAVRecord], path: Path, title: str) -> None:
    """Top and side view of the first episode's paths, one colour per UAV."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    first = [r for r in records if r.episode == records[0].episode]
    fig, (top, side) = plt.subplots(1, 2, figsize=(11, 5))
    colours = plt.cm.tab20(np.linspace(0, 1, max(len(first), 2)))
    for rec, colour in zip(first, colours):
        xyz = np.asarray(rec.path_ned)
        top.plot(xyz[:, 1], xyz[:, 0], color=colour, lw=1.5)
        top.plot(*rec.goal_ned[1::-1], "x", color=colour)
        if rec.outcome != "arrived":
            top.plot(xyz[-1, 1], xyz[-1, 0], "o", mfc="none", color=colour, ms=9)
        side.plot(xyz[:, 1], -xyz[:, 2], color=colour, lw=1.5)
    top.set(xlabel="east (m)", ylabel="north (m)", title="top view (x: goal, o: failure)", aspect="equal")
    side.set(xlabel="east (m)", ylabel="altitude (m)", title="side view")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from tqdm import tqdm

    config = SimConfig(num_uavs=args.n, num_worlds=args.episodes, scenario=args.scenario_config,
                       dynamics=args.dynamics)
    env = SwarmEnv(config, seed=args.seed)
    obs = env.reset()
    started = time.perf_counter()
    with tqdm(total=config.max_episode_steps, desc="flying", unit="step", file=sys.stderr) as bar:
        while not env.world_done.all():
            obs, *_ = env.step(straight_to_goal(obs.state))
            bar.update(1)
    wall = time.perf_counter() - started
    records = env.finish()
    summary = summarize(records)

    args.out.mkdir(parents=True, exist_ok=True)
    plot_path = args.out / "trajectories.png"
    plot_trajectories(records, plot_path, f"straight-to-goal, {args.scenario}, N={args.n}")
    (args.out / "metrics.json").write_text(json.dumps({"summary": summary, "config": config.to_dict()}, indent=2))

    sim_s = sum(r.duration_s for r in records) / args.n
    print(f"\nstraight-to-goal reference, {args.scenario} scenario, N={args.n}, {summary['episodes']} episodes "
          f"({sim_s:.0f} swarm-seconds simulated in {wall:.2f} s)")
    print(f"  success rate      {summary['success_rate']:.3f}")
    print(f"  SPL               {summary['spl']:.3f}")
    ed, sp = summary["extra_distance_m"], summary["average_speed_m_s"]
    print(f"  extra distance    {ed['mean']:.3f} / {ed['std']:.3f} m")
    print(f"  average speed     {sp['mean']:.3f} / {sp['std']:.3f} m/s")
    print(f"  collisions        UAV {summary['collision_uav_rate']:.3f}, ground {summary['collision_ground_rate']:.3f}, "
          f"timeout {summary['timeout_rate']:.3f}")
    print(f"wrote {plot_path} and {args.out / 'metrics.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
