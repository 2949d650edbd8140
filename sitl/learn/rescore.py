"""``python -m sitl.rescore RUN_DIR``: re-validate a run's snapshots on more episodes and scenes.

A training run validates each snapshot on a few dozen episodes of its own scenes
(``--eval-episodes``), which resolves success to only ±3-4 points and never looks at
circles larger than the training worlds. This tool flies every validated snapshot of a
run again on the *validation* seeds (disjoint from the test seeds that ``swarm_test``
reports) in a chosen set of scenes, e.g. the medium random scene with 8 UAVs and circles
of 8, 12 and 14 UAVs, and writes the result into each snapshot's row of
``snapshots/validation.json`` under ``"rescored"``.

The rescored score then takes the place of the training-time score in the selection:
``python -m sitl.train --resume RUN_DIR`` on the finished run re-selects, runs the final
(test-seed) evaluation and exports ``policy.pt`` from the new choice. The score is the
mean over the kinds of scene flown (random scenes, circles, obstacle scenes) of each kind's
mean success, so no kind can outvote another by being listed more often.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch

from sitl.cli_args import ArgumentParser, int_list
from sitl.learn.agent import AgentConfig
from sitl.learn.config import SelectionGate, TrainConfig, make_sim_config
from sitl.learn.trainer import (agent_actor, evaluate_scenario, flight_governor, load_training_file, make_agent,
                                select_snapshot)
from sitl.sim.episodes import ActorFactory
from sitl.sim.scenarios import VALIDATION_SEED_OFFSET


def load_run(run_dir: Path) -> tuple[TrainConfig, AgentConfig, list[dict]]:
    """A run's configuration and its validation rows (with a clear error if it has none)."""
    config_path, index_path = run_dir / "config.json", run_dir / "snapshots" / "validation.json"
    if not config_path.is_file():
        raise ValueError(f"{run_dir}: not a training run directory (no config.json)")
    if not index_path.is_file():
        raise ValueError(f"{run_dir}: has no validated snapshots (snapshots/validation.json); "
                         "train with --select-best and --eval-every-updates")
    saved = json.loads(config_path.read_text())
    return TrainConfig(**saved["train"]), AgentConfig(**saved["agent"]), json.loads(index_path.read_text())


def snapshot_actor(cfg: TrainConfig, agent_cfg: AgentConfig, snapshot: Path) -> ActorFactory:
    """The factory of a snapshot's deterministic actor."""
    agent = make_agent(agent_cfg, make_sim_config(cfg, 1))
    try:
        agent.load_state_dict(load_training_file(snapshot))
    except Exception as err:  # noqa: BLE001 - a corrupt file or other networks: the same clear refusal
        raise ValueError(f"{snapshot}: not a snapshot of this run's networks ({str(err)[:200]})") from None
    agent.eval()
    return agent_actor(agent, flight_governor(cfg))


#: one scene to fly: (name, scenario, UAVs, random-scene density)
Scene = tuple[str, str, int, str]


def scenes_of(densities: list[str], circle_uavs: list[int], random_uavs: int) -> list[Scene]:
    """Every scene to fly, random scenes first."""
    return [(f"random-{d}", "random", random_uavs, d) for d in densities] + \
           [(f"circle-n{n}", "circle", n, "medium") for n in circle_uavs]


def rescore_snapshot(cfg: TrainConfig, make_actor: ActorFactory, scenes: list[Scene], episodes: int,
                     max_episode_steps: int | None = None) -> dict:
    """Success and SPL of one controller in every scene on the validation seeds, and its score.

    ``max_episode_steps``: the time limit to fly them with (default: the run's training limit).
    """
    results: dict[str, dict] = {}
    steps = cfg.time_limit(max_episode_steps)
    for name, scenario, uavs, density in scenes:
        scene_cfg = replace(cfg, num_uavs=uavs, density=density, max_episode_steps=steps)
        summary = evaluate_scenario(make_actor, scene_cfg, scenario, episodes, VALIDATION_SEED_OFFSET + cfg.seed)
        results[name] = {"success_rate": summary["success_rate"], "spl": summary["spl"],
                         "success_ci95_half_width": summary["success_ci95_half_width"]}
    return {"episodes": episodes, "max_episode_steps": steps, "scenes": results, "score": selection_score(results)}


def gate_config(cfg: TrainConfig, gate: SelectionGate, max_episode_steps: int) -> TrainConfig:
    """The run's configuration with the gate's scene: its geometry, camera noise, number of UAVs and circle starts."""
    return replace(cfg, geometry=gate.geometry, camera_noise=gate.camera_noise, num_uavs=gate.num_uavs,
                   circle_scatter_m=gate.circle_scatter_m, max_episode_steps=max_episode_steps)


def gate_snapshot(cfg: TrainConfig, make_actor: ActorFactory, gates: list[SelectionGate], episodes: int,
                  max_episode_steps: int | None = None) -> dict:
    """Success of one controller in every gate's scene on the validation seeds, and whether it clears them all.

    Each gate flies the run's configuration with the gate's geometry, camera noise and number of UAVs.
    """
    steps = cfg.time_limit(max_episode_steps)
    scenes = {}
    for gate in gates:
        summary = evaluate_scenario(make_actor, gate_config(cfg, gate, steps), gate.scenario, episodes,
                                    VALIDATION_SEED_OFFSET + cfg.seed)
        scenes[gate.name] = {"success_rate": summary["success_rate"], "min_success": gate.min_success}
    return {"episodes": episodes, "max_episode_steps": steps, "gates": [asdict(g) for g in gates], "scenes": scenes,
            "passed": all(r["success_rate"] >= r["min_success"] for r in scenes.values())}


#: The kinds of scene the selection score weighs equally, by the scene name's prefix.
SCENE_KINDS = ("random", "circle", "obstacles")


def selection_score(results: dict[str, dict]) -> float:
    """Mean over the kinds of scene (:data:`SCENE_KINDS`) of each kind's mean success (see the module doc)."""
    kinds = [[r["success_rate"] for name, r in results.items() if name.startswith(kind)] for kind in SCENE_KINDS]
    return float(np.mean([np.mean(k) for k in kinds if k]))


def _density_list(text: str) -> list[str]:
    values = [v.strip() for v in text.split(",") if v.strip()]
    bad = [v for v in values if v not in ("small", "medium", "large")]
    if bad:
        raise argparse.ArgumentTypeError(f"densities are small, medium or large, got {', '.join(bad)}")
    return values


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = ArgumentParser(prog="python -m sitl.rescore", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dirs", nargs="+", type=Path, metavar="RUN_DIR", help="training run directories")
    parser.add_argument("--episodes", type=int, default=200, help="episodes per scene (default: 200)")
    parser.add_argument("--densities", type=_density_list, default=["medium"],
                        help="random scenes to fly, comma-separated (default: medium)")
    parser.add_argument("--circle-uavs", type=int_list(2, allow_empty=True), default=[8, 12, 14],
                        help="circle sizes to fly, comma-separated; empty for none (default: 8,12,14)")
    parser.add_argument("--random-uavs", type=int, default=8, help="UAVs in the random scenes (default: 8)")
    parser.add_argument("--updates", type=int_list(2, allow_empty=True), default=None,
                        help="rescore only the snapshots at these update counts, comma-separated (default: all)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default: 2)")
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error(f"--episodes must be at least 1, got {args.episodes}")
    if args.random_uavs < 2:
        parser.error(f"--random-uavs must be at least 2, got {args.random_uavs}")
    if not args.densities and not args.circle_uavs:
        parser.error("nothing to fly: give --densities or --circle-uavs")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    scenes = scenes_of(args.densities, args.circle_uavs, args.random_uavs)
    try:
        runs = [(run_dir, *load_run(run_dir)) for run_dir in args.run_dirs]
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for run_dir, cfg, agent_cfg, rows in runs:
        index_path = run_dir / "snapshots" / "validation.json"
        print(f"{run_dir}: {len(rows)} snapshots, {args.episodes} validation episodes per scene", flush=True)
        print("updates  " + "  ".join(f"{scene[0]:>12}" for scene in scenes) + "   score  (training-time score)")
        for row in sorted(rows, key=lambda r: r["updates"]):
            if args.updates is not None and row["updates"] not in args.updates:
                continue
            snapshot = run_dir / "snapshots" / f"agent_{row['updates']}.pt"
            if not snapshot.is_file():
                print(f"{row['updates']:>7}  snapshot file missing, skipped", flush=True)
                continue
            started = time.perf_counter()
            try:
                act = snapshot_actor(cfg, agent_cfg, snapshot)
            except ValueError as err:
                print(f"{row['updates']:>7}  skipped: {err}", flush=True)
                continue
            row["rescored"] = rescore_snapshot(cfg, act, scenes, args.episodes)
            cells = "  ".join(f"{r['success_rate']:.3f}/{r['spl']:.2f}".rjust(12) for r in row["rescored"]["scenes"].values())
            print(f"{row['updates']:>7}  {cells}   {row['rescored']['score']:.3f}  ({row['score']:.3f}), "
                  f"{time.perf_counter() - started:.0f} s", flush=True)
            index_path.write_text(json.dumps(rows, indent=1))  # after each snapshot: an interruption loses little
        if any("rescored" in row for row in rows):
            best = select_snapshot(rows)  # the choice `sitl.train --resume` will make
            print(f"best: {best['updates']} updates (score {best['rescored']['score']:.3f}); "
                  f"`python -m sitl.train --resume {run_dir}` exports it with a test-seed evaluation")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
