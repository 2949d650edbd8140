"""Training speed: SAC+AE updates per second and environment steps per second.

Measures, on this machine's CPU (``--threads`` torch threads) or its GPU (``--device cuda``):

* one full agent update (critic, actor every 2nd, targets, decoder) at the preset's batch (128; ``--batch-size``) from a
  filled replay buffer, for each method and image size given;
* rollout throughput of the training loop: vectorised environment steps with the actor's
  sampled actions for the preset's worlds of 8 UAVs and its camera (transitions per second;
  a recipe's first stage).

The last line is one JSON object with ``updates_per_s`` (the preset's configuration: by default
``flown-fast``, the bundled policy's recipe (``sitl.learn.config.BUNDLE_PRESET``): sac_ae, the
RealSense D435 preset's 32x20 grid, 512 hidden units, the decoder every second update;
``--preset flown`` is the same task at the paper's 1024 units, the bundle's recipe until
2026-11-25) and ``env_steps_per_s`` (agent transitions per second while acting), plus every
configuration measured.

``--profile`` also runs the preset's update under ``torch.profiler`` and prints where its time goes
(convolutions forward and backward, matrix products, optimiser steps, the rest), as shares of the
profiled CPU time; the last line then carries ``profile_shares``.

``--copies N`` answers another question: how fast do N runs side by side go (a sweep's seeds on one
machine, ``python -m sitl.sweep --cpus-per-run``)? It measures the preset's configuration only, in N
processes at once with ``--threads`` threads each, and the last line's ``updates_per_s`` is their sum
(``updates_per_s_per_copy`` lists each); no rollouts.

Usage: ``python benchmarks/train_speed.py [--preset flown-fast] [--sizes 32 64 32x20 48x32]
[--methods sac_ae cnn drq] [--seconds 10] [--threads 2] [--batch-size 128] [--num-filters N] [--device cpu] [--copies 1]
[--profile] [--smoke]`` (a size is a
square side or WIDTHxHEIGHT of the preset's field of view; ``--smoke``: the preset's configuration
only, no warm-up update, a fraction of a second per measurement, and the rollouts reuse that agent;
what CI runs.)
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402
import torch  # noqa: E402

import dataclasses  # noqa: E402

from companion.spec import DEFAULT_ACTION_SPEC, STATE_DIM, CameraSpec  # noqa: E402
from sitl.learn.agent import AgentConfig, SacAeAgent  # noqa: E402
from sitl.learn.buffer import FrameReplayBuffer  # noqa: E402
from sitl.learn.config import (BUNDLE_PRESET, PRESETS, TrainConfig, make_sim_config, parse_camera_grid,  # noqa: E402
                               resolve_configs, training_camera)
from sitl.sim.env import SwarmEnv  # noqa: E402

#: Seconds per measurement with --smoke: enough for one timed update on a busy 2-core machine.
SMOKE_SECONDS = 0.3


def parse_grid(text: str) -> tuple[int, int]:
    """``"32"`` -> (32, 32); ``"32x20"`` -> (32, 20): width and height in pixels (``--camera-grid``'s rules)."""
    try:
        return parse_camera_grid(text if "x" in text.lower() else f"{int(text)}x{int(text)}")
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a side or WIDTHxHEIGHT in pixels, each 16..256, got {text!r}") from None


def preset_configs(preset: str) -> tuple[TrainConfig, AgentConfig]:
    """A preset's configs as its first training run sees them (a recipe: its first stage's overrides)."""
    stages = PRESETS[preset].get("stages", ())
    first = stages[0] if stages else None
    return resolve_configs({"preset": preset, **(first.train if first else {})}, dict(first.agent) if first else {})


def make_agent(method: str, camera: CameraSpec, hidden: int, agent_cfg: AgentConfig,
               device: str = "cpu") -> SacAeAgent:
    """A freshly initialised agent of ``method`` for ``camera``'s depth images (other values: ``agent_cfg``)."""
    return SacAeAgent(dataclasses.replace(agent_cfg, method=method, hidden_dim=hidden), camera, DEFAULT_ACTION_SPEC,
                      device=device)


def update_rate(agent: SacAeAgent, seconds: float, batch_size: int, warmup_updates: int = 3) -> float:
    """Agent updates per second at ``batch_size`` from a filled replay buffer (random transitions)."""
    cam = agent.camera
    height, width = cam.height, cam.width
    action_dim = DEFAULT_ACTION_SPEC.dim
    extra = agent.privileged_dim  # an asymmetric critic's input (--privileged-critic), else 0
    buf = FrameReplayBuffer(4096, 64, cam.frames, height, width, STATE_DIM, action_dim, privileged_dim=extra)
    rng = np.random.default_rng(0)
    agents = np.arange(64)
    buf.start_episodes(agents, rng.uniform(0, 20, (64, height, width)))
    for _ in range(40):
        privileged = {"privileged": rng.normal(size=(64, extra)), "next_privileged": rng.normal(size=(64, extra))}
        buf.add(agents, rng.normal(size=(64, STATE_DIM)), rng.uniform(-1, 1, (64, action_dim)), rng.normal(size=64),
                rng.uniform(0, 20, (64, height, width)), rng.normal(size=(64, STATE_DIM)), np.zeros(64, bool),
                rng.uniform(-1, 1, (64, action_dim)), **(privileged if extra else {}))  # a teacher's labels too
    labelled = agent.config.method == "distill"  # a distilled student learns from the teacher's labels only
    for _ in range(warmup_updates):
        agent.update(buf.sample(batch_size, agent.device, with_teacher=labelled))
    synchronize = torch.cuda.synchronize if agent.device.type == "cuda" else (lambda: None)
    synchronize()
    count, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds:
        agent.update(buf.sample(batch_size, agent.device, with_teacher=labelled))
        count += 1
    synchronize()  # a GPU's queued work counts too
    return count / (time.perf_counter() - started)


#: torch.profiler operator names -> the part of an update they belong to (``--profile``); anything else is "other".
PROFILE_PARTS = {
    "convolution forward": ("aten::mkldnn_convolution", "aten::_convolution", "aten::slow_conv_transpose2d",
                            "aten::convolution"),
    "convolution backward": ("aten::convolution_backward",),
    "matrix products": ("aten::addmm", "aten::mm", "aten::bmm"),
    "optimiser steps": ("Optimizer.step#Adam.step", "aten::addcdiv_", "aten::addcmul_", "aten::lerp_", "aten::sqrt",
                        "aten::mul_", "Optimizer.zero_grad#Adam.zero_grad"),
}


def update_profile(agent: SacAeAgent, seconds: float, batch_size: int) -> dict[str, float]:
    """Shares of an update's CPU time by part (:data:`PROFILE_PARTS`), from ``torch.profiler``'s self times.

    ``aten::lerp_`` is the targets' moving average and ``aten::sqrt`` Adam's; both count as optimiser
    steps. Self times are each operator's own, so no time is counted twice."""
    from torch.profiler import ProfilerActivity, profile
    update_rate(agent, min(seconds, 2.0), batch_size)  # warm caches outside the profile
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        update_rate(agent, seconds, batch_size, warmup_updates=0)
    self_us = {event.key: event.self_cpu_time_total for event in prof.key_averages()}
    total = sum(self_us.values()) or 1.0
    part_of = {op: part for part, ops in PROFILE_PARTS.items() for op in ops}
    shares = dict.fromkeys([*PROFILE_PARTS, "other"], 0.0)
    for op, us in self_us.items():
        shares[part_of.get(op, "other")] += us / total
    return {part: round(share, 3) for part, share in shares.items()}


def copy_update_rate(job: tuple[str, int, float, bool, object]) -> float:
    """One of ``--copies``' processes: the preset's configuration's update rate at ``threads`` threads.

    ``job`` is (preset, threads, seconds, smoke, barrier); every copy builds its agent and fills its
    buffer, then waits at the barrier so that the timed updates overlap."""
    preset, threads, seconds, smoke, barrier = job
    torch.set_num_threads(threads)
    cfg, agent_cfg = preset_configs(preset)
    agent = make_agent(agent_cfg.method, training_camera(cfg), agent_cfg.hidden_dim, agent_cfg)
    barrier.wait()
    return update_rate(agent, seconds, cfg.batch_size, warmup_updates=0 if smoke else 3)


def side_by_side_rates(preset: str, copies: int, threads: int, seconds: float, smoke: bool) -> list[float]:
    """Update rates of ``copies`` processes measuring the preset's configuration at the same time."""
    context = multiprocessing.get_context("spawn")  # fresh interpreters: no torch thread pool inherited
    with context.Manager() as manager:
        barrier = manager.Barrier(copies)
        with context.Pool(copies) as pool:
            return pool.map(copy_update_rate, [(preset, threads, seconds, smoke, barrier)] * copies)


def rollout_rate(seconds: float, agent: SacAeAgent | None = None, cfg: TrainConfig | None = None) -> float:
    """Agent transitions per second while ``cfg``'s worlds (default: the fast preset's) roll out with sampled actions.

    ``agent`` (default: a fresh one) must see ``cfg``'s camera.
    """
    cfg = cfg or TrainConfig()
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
    parser.add_argument("--preset", default=BUNDLE_PRESET, choices=sorted(PRESETS),
                        help=f"the headline configuration and the rollouts' scenes and camera (default "
                             f"{BUNDLE_PRESET}: the bundle's recipe; flown: the same task at 1024 units)")
    parser.add_argument("--sizes", type=parse_grid, nargs="+", default=None,
                        help="image grids, a side or WIDTHxHEIGHT, in the preset camera's field of view "
                             "(default: the preset's grid and 32, 64)")
    parser.add_argument("--methods", nargs="+", default=None, help="learning methods (default sac_ae cnn drq)")
    parser.add_argument("--hidden", type=int, nargs="+", default=None,
                        help="hidden units (default: the preset's, 1024 and 256)")
    parser.add_argument("--seconds", type=float, default=None, help="seconds per measurement (default 10)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads per process (default 2)")
    parser.add_argument("--batch-size", type=int, default=None,
                        help="transitions per update (default: the preset's, 128 in every recipe)")
    parser.add_argument("--num-filters", type=int, default=None,
                        help="convolution filters per encoder layer in every measured configuration (default: the "
                             "preset's, the paper's 32)")
    parser.add_argument("--profile", action="store_true",
                        help="also profile the preset's update with torch.profiler and print its time by part")
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"],
                        help="where the updates run (default cpu; rollouts render on the CPU either way)")
    parser.add_argument("--copies", type=int, default=1,
                        help="measure the preset's configuration in this many processes at once and report "
                             "their summed updates/s (runs side by side, as a sweep runs seeds; default 1)")
    parser.add_argument("--smoke", action="store_true",
                        help="CI check: the preset's configuration only, no warm-up, a fraction of a second "
                             "per measurement")
    args = parser.parse_args()
    cfg, agent_cfg = preset_configs(args.preset)
    args.batch_size = cfg.batch_size if args.batch_size is None else args.batch_size
    camera = training_camera(cfg)
    preset_grid = (camera.width, camera.height)

    def grid_camera(grid: tuple[int, int]) -> CameraSpec:
        """The preset's camera (field of view, range) sampled on ``grid``."""
        return dataclasses.replace(camera, width=grid[0], height=grid[1])

    def name(method: str, grid: tuple[int, int], hidden: int) -> str:
        width = f"_f{args.num_filters}" if args.num_filters is not None else ""  # the preset's width goes unnamed
        return f"{method}_{grid[0]}x{grid[1]}px_h{hidden}{width}"

    headline = name(agent_cfg.method, preset_grid, agent_cfg.hidden_dim)
    if args.smoke:
        grids = args.sizes or [preset_grid]
        methods = args.methods or [agent_cfg.method]
        hiddens = args.hidden or [agent_cfg.hidden_dim]
        seconds = SMOKE_SECONDS if args.seconds is None else args.seconds
    else:
        grids = args.sizes or list(dict.fromkeys([preset_grid, (32, 32), (64, 64)]))
        methods = args.methods or ["sac_ae", "cnn", "drq"]
        hiddens = args.hidden or list(dict.fromkeys([agent_cfg.hidden_dim, 1024, 256]))
        seconds = 10.0 if args.seconds is None else args.seconds
    if seconds <= 0:
        parser.error(f"--seconds must be > 0, got {seconds}")
    if args.threads < 1 or args.copies < 1 or not 1 <= args.batch_size <= 4096:
        parser.error(f"--threads and --copies must be >= 1 and --batch-size in 1..4096, got {args.threads}, "
                     f"{args.copies} and {args.batch_size}")
    if args.num_filters is not None:
        if not 1 <= args.num_filters <= 256:
            parser.error(f"--num-filters must be in 1..256, got {args.num_filters}")
        agent_cfg = dataclasses.replace(agent_cfg, num_filters=args.num_filters)
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda asked for, but torch sees no CUDA device")
    if args.copies > 1:
        if args.device != "cpu" or args.batch_size != cfg.batch_size:
            parser.error("--copies measures CPU processes side by side at the preset's batch; leave out --device and "
                         "--batch-size")
        if args.sizes or args.methods or args.hidden or args.num_filters or args.profile:
            parser.error("--copies measures the preset's configuration only; leave out --sizes, --methods, --hidden, "
                         "--num-filters and --profile")
        per_copy = side_by_side_rates(args.preset, args.copies, args.threads, seconds, args.smoke)
        print(f"{args.copies} copies of {headline} side by side, {args.threads} thread(s) each: "
              f"{', '.join(f'{rate:.2f}' for rate in per_copy)} updates/s; {sum(per_copy):.2f} in all", flush=True)
        print(json.dumps({"benchmark": "train_speed", "preset": args.preset, "threads": args.threads,
                          "copies": args.copies, "updates_per_s": round(sum(per_copy), 2),
                          "updates_per_s_config": headline,
                          "updates_per_s_per_copy": [round(rate, 2) for rate in per_copy]}))
        return
    torch.set_num_threads(args.threads)

    rates, headline_agent = {}, None
    for grid in grids:
        for method in methods:
            for hidden in hiddens:
                agent = make_agent(method, grid_camera(grid), hidden, agent_cfg, args.device)
                key = name(method, grid, hidden)
                if key == headline:
                    headline_agent = agent  # the rollouts reuse it: one fewer initialisation
                rate = update_rate(agent, seconds, args.batch_size, warmup_updates=0 if args.smoke else 3)
                rates[key] = round(rate, 2)
                print(f"{method:7s} {grid[0]}x{grid[1]} hidden {hidden:4d}: {rate:6.2f} updates/s "
                      f"({1000 / rate:6.1f} ms/update)", flush=True)
    env_rate = rollout_rate(seconds, headline_agent or make_agent(agent_cfg.method, camera, agent_cfg.hidden_dim,
                                                                   agent_cfg, args.device), cfg)
    print(f"rollouts of preset {args.preset} ({cfg.num_worlds} worlds x {cfg.num_uavs} UAVs, {cfg.scenario} scenes, "
          f"actor sampling): {env_rate:.0f} transitions/s", flush=True)
    summary = {"benchmark": "train_speed", "preset": args.preset, "threads": args.threads,
               "device": args.device, "batch_size": args.batch_size, "num_filters": agent_cfg.num_filters,
               "updates_per_s": rates.get(headline), "updates_per_s_config": headline,
               "env_steps_per_s": round(env_rate), "updates_per_s_by_config": rates}
    if args.profile:
        shares = update_profile(headline_agent or make_agent(agent_cfg.method, camera, agent_cfg.hidden_dim, agent_cfg,
                                                             args.device), seconds, args.batch_size)
        print(f"{headline}'s update by part (torch.profiler self CPU time): "
              + ", ".join(f"{part} {share:.0%}" for part, share in shares.items()), flush=True)
        summary["profile_shares"] = shares
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
