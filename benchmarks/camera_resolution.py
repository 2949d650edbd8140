"""Which depth resolution to train on: what a UAV covers versus what an image costs.

For square images of several sizes (90 deg field of view, 4x4 min-pooled sub-rays) this
prints:

* pixels covered by a UAV (0.6 m x 0.24 m body) at d_safe = 5 m and at 10 m, straight
  ahead and 30 deg off-axis;
* rendering cost in frames/s (random medium scene, 8 UAVs, one core);
* the cost of one encoder+decoder forward/backward at batch 128 with the paper's conv
  stack (4 conv layers of 32 3x3 filters, first stride 2) — the part of a SAC+AE update
  that grows with the image (two threads).

With ``--camera realsense_d435`` the candidates are ``WxH`` grids over the D435's 87 x 58 deg
(``--grids 32x20 48x32 64x42 96x64``), the UAV is measured at 5 m and 8 m (the range is 10 m),
and the cost is one full SAC+AE update of :class:`sitl.learn.agent.SacAeAgent` at batch 128
(critic, actor, temperature and autoencoder; two threads): what drives training time.

Last line: one JSON object with those figures per resolution.
Usage: ``python benchmarks/camera_resolution.py [--sizes 16 24 32 48 64] [--smoke]``,
``python benchmarks/camera_resolution.py --camera realsense_d435 [--grids 32x20 48x32 64x42]``
(``--smoke``: 32x32 only, 0.2 s of rendering and one timed autoencoder update; what CI runs to
keep the script working.)
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402

from companion.spec import CameraSpec  # noqa: E402
from sitl.sim.camera import DepthCamera  # noqa: E402
from sitl.sim.config import SimConfig  # noqa: E402
from sitl.sim.env import SwarmEnv  # noqa: E402


def covered_pixels(size: int, distance_m: float, bearing_deg: float) -> int:
    """Pixels of a ``size`` x ``size`` image covered by a UAV ``distance_m`` away, ``bearing_deg`` off-axis."""
    cam = DepthCamera(CameraSpec(width=size, height=size), 4)
    b = math.radians(bearing_deg)
    pos = np.array([[0.0, 0.0, -100.0], [distance_m * math.cos(b), distance_m * math.sin(b), -100.0]])
    return int((cam.render(pos, np.zeros(2), 2)[0] < distance_m + 1).sum())


def render_fps(size: int, seconds: float = 1.0) -> float:
    """Depth frames rendered per second (random medium scene, 8 UAVs in 16 worlds, one core)."""
    env = SwarmEnv(SimConfig(num_uavs=8, num_worlds=16, camera=CameraSpec(width=size, height=size)), seed=0)
    env.reset()
    env._render()
    frames, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds:
        env._render()
        frames += env.num_agents
    return frames / (time.perf_counter() - started)


def autoencoder_update_s(size: int, repeats: int = 5) -> float:
    """Seconds of one encoder+decoder forward/backward/step at batch 128 (two threads)."""
    import torch
    from torch import nn

    torch.set_num_threads(2)
    convs = nn.Sequential(nn.Conv2d(3, 32, 3, 2), nn.ReLU(), nn.Conv2d(32, 32, 3), nn.ReLU(),
                          nn.Conv2d(32, 32, 3), nn.ReLU(), nn.Conv2d(32, 32, 3), nn.ReLU())
    side = convs(torch.zeros(1, 3, size, size)).shape[-1]
    fc, dfc = nn.Linear(32 * side * side, 50), nn.Linear(50, 32 * side * side)
    deconvs = nn.Sequential(nn.ConvTranspose2d(32, 32, 3), nn.ReLU(), nn.ConvTranspose2d(32, 32, 3), nn.ReLU(),
                            nn.ConvTranspose2d(32, 32, 3), nn.ReLU(), nn.ConvTranspose2d(32, 3, 3, 2, output_padding=1))
    params = [p for m in (convs, fc, dfc, deconvs) for p in m.parameters()]
    opt = torch.optim.Adam(params)
    x = torch.rand(128, 3, size, size)

    def step() -> None:
        z = fc(convs(x).flatten(1))
        recon = deconvs(dfc(z).view(-1, 32, side, side))[..., :size, :size]
        loss = (recon - x).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()

    step()
    started = time.perf_counter()
    for _ in range(repeats):
        step()
    return (time.perf_counter() - started) / repeats


def covered_pixels_spec(spec: CameraSpec, distance_m: float, bearing_deg: float) -> int:
    """Pixels of ``spec``'s image covered by a UAV ``distance_m`` away, ``bearing_deg`` off-axis."""
    cam = DepthCamera(spec, 4)
    b = math.radians(bearing_deg)
    pos = np.array([[0.0, 0.0, -100.0], [distance_m * math.cos(b), distance_m * math.sin(b), -100.0]])
    return int((cam.render(pos, np.zeros(2), 2)[0] < distance_m + 1).sum())


def render_fps_spec(spec: CameraSpec, seconds: float) -> float:
    """Depth frames rendered per second with ``spec`` (random medium scene, 8 UAVs in 16 worlds, one core)."""
    env = SwarmEnv(SimConfig(num_uavs=8, num_worlds=16, camera=spec), seed=0)
    env.reset()
    env._render()
    frames, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds:
        env._render()
        frames += env.num_agents
    return frames / (time.perf_counter() - started)


def agent_update_s(spec: CameraSpec, repeats: int) -> float:
    """Seconds of one SAC+AE update (sitl.learn.agent, default hyperparameters, batch 128, two threads)."""
    import torch

    from companion.spec import DEFAULT_ACTION_SPEC, STATE_DIM
    from sitl.learn.agent import AgentConfig, SacAeAgent
    from sitl.learn.buffer import FrameReplayBuffer

    torch.set_num_threads(2)
    torch.manual_seed(0)
    agent = SacAeAgent(AgentConfig(), spec, DEFAULT_ACTION_SPEC)
    h, w, a = spec.height, spec.width, DEFAULT_ACTION_SPEC.dim
    buf = FrameReplayBuffer(1024, 32, spec.frames, h, w, STATE_DIM, a)
    rng = np.random.default_rng(0)
    agents = np.arange(32)
    buf.start_episodes(agents, rng.uniform(0, spec.max_range_m, (32, h, w)))
    for _ in range(20):
        buf.add(agents, rng.normal(size=(32, STATE_DIM)), rng.uniform(-1, 1, (32, a)), rng.normal(size=32),
                rng.uniform(0, spec.max_range_m, (32, h, w)), rng.normal(size=(32, STATE_DIM)), np.zeros(32, bool))
    agent.update(buf.sample(128, agent.device))
    started = time.perf_counter()
    for _ in range(repeats):
        agent.update(buf.sample(128, agent.device))
    return (time.perf_counter() - started) / repeats


def grid(text: str) -> tuple[int, int]:
    width, _, height = text.partition("x")
    return int(width), int(height)


def main_preset(preset: str, grids: list[tuple[int, int]], render_seconds: float, repeats: int) -> None:
    """The table for a real camera's field of view at several pixel grids."""
    import dataclasses

    from companion.spec import CAMERA_PRESETS

    base = CAMERA_PRESETS[preset]
    rows = {}
    print(f"{'grid':>7} {'px@5m':>6} {'px@5m,30deg':>12} {'px@8m':>6} {'frames/s':>9} {'SAC+AE update s':>16}")
    for width, height in grids:
        spec = dataclasses.replace(base, width=width, height=height)
        row = {
            "pixels_at_5m": covered_pixels_spec(spec, 5.0, 0.0),
            "pixels_at_5m_30deg": covered_pixels_spec(spec, 5.0, 30.0),
            "pixels_at_8m": covered_pixels_spec(spec, 8.0, 0.0),
            "render_frames_per_s": round(render_fps_spec(spec, render_seconds)),
            "sac_ae_update_s": round(agent_update_s(spec, repeats), 4),
        }
        rows[f"{width}x{height}"] = row
        print(f"{width}x{height:<3} {row['pixels_at_5m']:6d} {row['pixels_at_5m_30deg']:12d} {row['pixels_at_8m']:6d} "
              f"{row['render_frames_per_s']:9d} {row['sac_ae_update_s']:16.4f}", flush=True)
    print(json.dumps({"benchmark": "camera_resolution", "camera": preset, "results": rows}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=None, help="image sides (default 16 24 32 48 64)")
    parser.add_argument("--smoke", action="store_true",
                        help="CI check: 32x32 only, 0.2 s of rendering, one timed autoencoder update")
    parser.add_argument("--camera", choices=("realsense_d435",), default=None,
                        help="measure WxH grids over this camera's field of view instead of square 90 deg images")
    parser.add_argument("--grids", type=grid, nargs="+", default=None, metavar="WxH",
                        help="with --camera: pixel grids (default 32x20 48x32 64x42 96x64)")
    args = parser.parse_args()
    if args.camera:
        grids = args.grids or ([(48, 32)] if args.smoke else [(32, 20), (48, 32), (64, 42), (96, 64)])
        main_preset(args.camera, grids, *((0.2, 1) if args.smoke else (1.0, 5)))
        return
    sizes = args.sizes or ([32] if args.smoke else [16, 24, 32, 48, 64])
    if min(sizes) < 16:
        parser.error(f"--sizes must be >= 16 (the encoder shrinks an image by 14 pixels), got {min(sizes)}")
    render_seconds, repeats = (0.2, 1) if args.smoke else (1.0, 5)
    rows = {}
    print(f"{'size':>5} {'px@5m':>6} {'px@5m,30deg':>12} {'px@10m':>7} {'frames/s':>9} {'AE update s':>12}")
    for size in sizes:
        row = {
            "pixels_at_5m": covered_pixels(size, 5.0, 0.0),
            "pixels_at_5m_30deg": covered_pixels(size, 5.0, 30.0),
            "pixels_at_10m": covered_pixels(size, 10.0, 0.0),
            "render_frames_per_s": round(render_fps(size, render_seconds)),
            "autoencoder_update_s": round(autoencoder_update_s(size, repeats), 4),
        }
        rows[f"{size}x{size}"] = row
        print(f"{size:5d} {row['pixels_at_5m']:6d} {row['pixels_at_5m_30deg']:12d} {row['pixels_at_10m']:7d} "
              f"{row['render_frames_per_s']:9d} {row['autoencoder_update_s']:12.4f}", flush=True)
    print(json.dumps({"benchmark": "camera_resolution", "results": rows}))


if __name__ == "__main__":
    main()
