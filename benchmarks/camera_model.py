"""What the real camera model changes: the ground in the reward, and how much of a frame is "no data".

Two measurements, each a table and, as the last line, one JSON object:

* ``avoid``: eq. 4's avoidance term per step (``w_avoid * max(d_safe - d_min, 0)``) of one UAV
  alone in an empty scene, level, at several altitudes, for the paper camera (32x32, 90 deg,
  20 m) and the RealSense D435 preset (32x20, 87 x 58 deg, 10 m), with d_min over the whole
  image (the paper: the ground counts) and over UAVs and obstacles only
  (``RewardConfig.avoid_counts_ground=False``). For scale: full-speed progress pays
  ``w_goal * 0.2 m = 0.6`` per step, arrival 50.
* ``invalid``: the fraction of invalid pixels (0, as the RealSense SDK reports no data) in the
  raw frames of the D435 preset with the stereo noise model and +-5 deg mount pitch jitter, over
  normal flights (8 UAVs flying straight at their goals, random medium scenes with the box floor
  at 1.5-12 m and circles at 2-15 m), binned by the camera's altitude: what the companion's
  blinded-camera check (``--max-invalid-depth``) sees in flight.

Usage: ``python benchmarks/camera_model.py [--episodes 20] [--smoke]`` (``--smoke``: 2 episodes
per scene, what CI runs to keep the script working). ``--render-cost [--repo CHECKOUT]`` only
times ``DepthCamera.render`` of 128 cameras (32x32, 4x4 sub-rays, random medium scene, one
thread, best of 7 x 20 renders) in this or another checkout: alternate runs for a before/after.
``--noise-cost [--repo CHECKOUT]`` likewise times ``StereoNoise.apply`` on what an evaluation batch
renders (800 cameras: 100 random medium worlds of 8, the D435 preset's 32x20), for the evaluation
protocols' noise (occlusion-shadow edges) and the recipes' training noise (both sides of every edge),
best of 7 x 20 calls each.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
# --render-cost --repo PATH times another checkout's kernel (the before/after of a kernel change).
_REPO = sys.argv[sys.argv.index("--repo") + 1] if "--repo" in sys.argv[:-1] else str(Path(__file__).resolve().parent.parent)
sys.path.insert(0, _REPO)

import numpy as np  # noqa: E402

from sitl.sim.config import SimConfig  # noqa: E402
from sitl.sim.env import SwarmEnv  # noqa: E402

ALTITUDES_M = (1.5, 2.0, 3.0, 5.0, 10.0)
ALTITUDE_BINS_M = ((0.0, 3.0), (3.0, 6.0), (6.0, 10.0), (10.0, 13.0), (13.0, 100.0))


def avoid_table() -> dict:
    """Avoidance reward per step at each altitude, per camera, with and without the ground."""
    from companion.spec import CAMERA_PRESETS
    from sitl.sim.camera import DepthCamera
    from sitl.sim.config import RewardConfig
    from sitl.sim.reward import avoid_reward, nearest_depth_m

    rows = {}
    for name, spec in CAMERA_PRESETS.items():
        camera = DepthCamera(spec, 4)
        for alt in ALTITUDES_M:
            depth, objects = camera.render_with_objects(np.array([[0.0, 0.0, -alt]]), np.zeros(1), 1)
            with_ground = float(avoid_reward(np.zeros(1, bool), nearest_depth_m(depth), RewardConfig())[0])
            without = float(avoid_reward(np.zeros(1, bool), objects, RewardConfig())[0])
            rows[f"{name}@{alt:g}m"] = {"d_min_with_ground_m": round(float(nearest_depth_m(depth)[0]), 3),
                                        "avoid_with_ground": round(with_ground, 4), "avoid_without_ground": round(without, 4)}
    return rows


def invalid_fractions(episodes: int, seed: int = 0) -> dict:
    """Invalid-pixel fractions of raw D435 frames over straight flights, binned by altitude."""
    from companion.spec import CAMERA_PRESETS
    from sitl.sim.baselines import straight_to_goal
    from sitl.sim.camera import StereoNoise
    from sitl.sim.config import ScenarioConfig

    spec = CAMERA_PRESETS["realsense_d435"]
    noise = StereoNoise(min_range_m=spec.min_range_m)
    scenes = [ScenarioConfig(name="random", box_floor_alt_m=floor) for floor in (1.5, 3.0, 6.0, 9.0, 12.0)]
    scenes += [ScenarioConfig(name="circle", circle_alt_m=alt, circle_radius_m=12.0) for alt in (2.0, 5.0, 10.0, 15.0)]
    samples_alt, samples_frac = [], []
    rng = np.random.default_rng(seed)
    for scene in scenes:
        env = SwarmEnv(SimConfig(num_uavs=8, num_worlds=min(episodes, 8), scenario=scene, camera=spec,
                                 mount_pitch_jitter_deg=5.0, record_paths=False), seed=seed)
        obs = env.reset()

        class Probe:
            def before_step(self, env_) -> None:
                pass

            def after_step(self, env_, info) -> None:
                rows = np.flatnonzero(env_.acting)
                if rows.size == 0:
                    return
                d = env_.dynamics
                raw = env_.camera.render(d.pos_ned, d.yaw_rad, env_.uavs_per_world, visible=env_.present,
                                         pitch_rad=env_.mount_pitch_rad)
                raw = noise.apply(raw[rows], spec.max_range_m, rng)
                samples_frac.append((raw == 0).reshape(rows.size, -1).mean(axis=1))
                samples_alt.append(-d.pos_ned[rows, 2])

        env.fly_episodes(obs, lambda o: straight_to_goal(o.state), episodes, observer=Probe())
    alt, frac = np.concatenate(samples_alt), np.concatenate(samples_frac)
    rows = {}
    for lo, hi in ALTITUDE_BINS_M:
        f = frac[(alt >= lo) & (alt < hi)]
        if f.size == 0:
            continue
        rows[f"{lo:g}-{hi:g} m"] = {
            "frames": int(f.size), "mean": round(float(f.mean()), 3), "p50": round(float(np.percentile(f, 50)), 3),
            "p99": round(float(np.percentile(f, 99)), 3), "max": round(float(f.max()), 3),
            "frames_over_0.9": round(float((f > 0.9).mean()), 4), "frames_all_invalid": round(float((f >= 1.0).mean()), 4),
        }
    return rows


def render_cost_ms() -> float:
    """Milliseconds to render 128 cameras (16 random medium worlds of 8), best of 7 x 20."""
    import time

    env = SwarmEnv(SimConfig(num_uavs=8, num_worlds=16, record_paths=False), seed=0)
    env.reset()
    d = env.dynamics
    env.camera.render(d.pos_ned, d.yaw_rad, 8, visible=env.present)
    best = float("inf")
    for _ in range(7):
        started = time.perf_counter()
        for _ in range(20):
            env.camera.render(d.pos_ned, d.yaw_rad, 8, visible=env.present)
        best = min(best, (time.perf_counter() - started) / 20)
    return best * 1e3


def noise_cost_ms() -> dict:
    """Milliseconds per ``StereoNoise.apply`` on 800 D435 frames, per edge-hole model, best of 7 x 20."""
    import time

    from companion.spec import CAMERA_PRESETS
    from sitl.sim.camera import StereoNoise

    env = SwarmEnv(SimConfig(num_uavs=8, num_worlds=100, record_paths=False,
                             camera=CAMERA_PRESETS["realsense_d435"]), seed=0)
    env.reset()
    d = env.dynamics
    depth = env.camera.render(d.pos_ned, d.yaw_rad, 8, visible=env.present)
    costs = {}
    for edges in ("shadow", "both"):
        noise, rng = StereoNoise(edge_holes=edges), np.random.default_rng(0)
        noise.apply(depth, env.camera.spec.max_range_m, rng)  # compile / warm up
        best = float("inf")
        for _ in range(7):
            started = time.perf_counter()
            for _ in range(20):
                noise.apply(depth, env.camera.spec.max_range_m, rng)
            best = min(best, (time.perf_counter() - started) / 20)
        costs[f"ms_per_800_frames_{edges}"] = round(best * 1e3, 3)
    return costs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=20, help="episodes per scene (default 20)")
    parser.add_argument("--smoke", action="store_true", help="CI check: 2 episodes per scene")
    parser.add_argument("--render-cost", action="store_true", help="only time the render kernel")
    parser.add_argument("--noise-cost", action="store_true", help="only time the stereo noise model")
    parser.add_argument("--repo", default=None, help="with --render-cost or --noise-cost: the checkout whose code to time")
    args = parser.parse_args()
    if args.render_cost:
        print(json.dumps({"benchmark": "render_cost", "repo": _REPO, "ms_per_128_cameras": round(render_cost_ms(), 3)}))
        return
    if args.noise_cost:
        print(json.dumps({"benchmark": "noise_cost", "repo": _REPO, **noise_cost_ms()}))
        return
    episodes = 2 if args.smoke else args.episodes
    if episodes < 1:
        parser.error(f"--episodes must be >= 1, got {episodes}")
    avoid = avoid_table()
    print(f"{'camera@altitude':>22} {'d_min (ground) m':>17} {'avoid, ground counts':>21} {'avoid, UAVs+obstacles':>22}")
    for key, row in avoid.items():
        print(f"{key:>22} {row['d_min_with_ground_m']:17.2f} {row['avoid_with_ground']:21.4f} {row['avoid_without_ground']:22.4f}")
    invalid = invalid_fractions(episodes)
    print(f"\n{'altitude':>10} {'frames':>7} {'mean':>6} {'p50':>6} {'p99':>6} {'max':>6} {'>0.9':>7} {'all':>7}")
    for key, row in invalid.items():
        print(f"{key:>10} {row['frames']:7d} {row['mean']:6.3f} {row['p50']:6.3f} {row['p99']:6.3f} {row['max']:6.3f} "
              f"{row['frames_over_0.9']:7.4f} {row['frames_all_invalid']:7.4f}")
    print(json.dumps({"benchmark": "camera_model", "avoid_per_step": avoid, "invalid_fraction_d435": invalid,
                      "episodes_per_scene": episodes}))


if __name__ == "__main__":
    main()
