"""Which depth resolution to train on: what a UAV covers versus what an image costs.

For square images of several sizes (90 deg field of view, 4x4 min-pooled sub-rays) this
prints:

* pixels covered by a UAV (0.6 m x 0.24 m body) at d_safe = 5 m and at 10 m, straight
  ahead and 30 deg off-axis;
* rendering cost in frames/s (random medium scene, 8 UAVs, one core);
* the cost of one encoder+decoder forward/backward at batch 128 with the paper's conv
  stack (4 conv layers of 32 3x3 filters, first stride 2) — the part of a SAC+AE update
  that grows with the image (two threads).

Last line: one JSON object with those figures per resolution.
Usage: ``python benchmarks/camera_resolution.py [--sizes 16 24 32 48 64] [--smoke]``
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=None, help="image sides (default 16 24 32 48 64)")
    parser.add_argument("--smoke", action="store_true",
                        help="CI check: 32x32 only, 0.2 s of rendering, one timed autoencoder update")
    args = parser.parse_args()
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
