"""Anatomy of the UAV-UAV collisions a controller still has: when, and who could see whom.

A forward depth camera sees only what is in its field of view. This tool flies the same
test episodes as ``python -m sitl.swarm_test`` and, for every UAV that collides with
another, asks whether the partner was inside the collider's camera frustum (and whether the
collider was inside the partner's) at any control step of the last second before the
collision. Collisions neither UAV could see coming are out of reach of any policy that
sees only its own camera; collisions the collider saw are the policy's to avoid.

    python -m sitl.collision_anatomy --scenario random --density medium --episodes 100

Prints a table and writes ``--json`` if given. Geometry test: the partner's centre inside
the camera's horizontal and vertical field of view (heading frame, level camera as in the
simulator) and within its range.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from sitl.config import DENSITIES, ScenarioConfig
from sitl.env import COLLISION_UAV, SwarmEnv
from sitl.swarm_test import DEFAULT_POLICY, EvalSettings, EvaluationError, resolve_method, sim_config_for

LOOKBACK_S = 1.0  # "could have seen it coming": in view at some step of this window before the collision
TIME_BINS_S = (1.0, 2.0, 5.0)  # collision time since the episode start, for the table


def in_view(pos_ned: np.ndarray, yaw_rad: np.ndarray, other_ned: np.ndarray, hfov_rad: float, vfov_rad: float,
            max_range_m: float) -> np.ndarray:
    """Whether each ``other_ned`` point lies in the level camera frustum of the UAV at ``pos_ned``/``yaw_rad``.

    Shapes broadcast: ``pos_ned``/``other_ned`` [..., 3], ``yaw_rad`` [...].
    """
    d = other_ned - pos_ned
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    fwd = c * d[..., 0] + s * d[..., 1]
    right = -s * d[..., 0] + c * d[..., 1]
    down = d[..., 2]
    return ((fwd > 0) & (np.abs(np.arctan2(right, fwd)) <= hfov_rad / 2)
            & (np.abs(np.arctan2(down, fwd)) <= vfov_rad / 2) & (np.linalg.norm(d, axis=-1) <= max_range_m))


def analyse(policy: str, settings: EvalSettings) -> dict:
    """Fly ``settings.episodes`` episodes at once and classify every UAV-UAV collision."""
    if settings.episodes > settings.batch_worlds:
        raise EvaluationError("collision_anatomy flies all episodes at once: --episodes must be <= --batch")
    method = resolve_method(policy)
    config = sim_config_for(method, settings, settings.episodes)
    env = SwarmEnv(config, seed=settings.env_seed)
    obs = env.reset()
    actor = method.make_actor(env)
    cam = config.camera
    hfov = math.radians(cam.hfov_deg)
    vfov = 2 * math.atan(math.tan(hfov / 2) * cam.height / cam.width)
    lookback = max(1, round(LOOKBACK_S / config.control_period_s))
    n = config.num_uavs
    positions, yaws = [env.dynamics.pos_ned.copy()], [env.dynamics.yaw_rad.copy()]
    events = []
    step = 0
    while not env.world_done.all():
        acting = env.acting.copy()
        obs, _, _, _, info = env.step(actor(env, obs))
        step += 1
        positions.append(env.dynamics.pos_ned.copy())
        yaws.append(env.dynamics.yaw_rad.copy())
        for r in np.flatnonzero(acting & (info["outcome"] == COLLISION_UAV)):
            world = r // n
            rows = np.arange(world * n, (world + 1) * n)
            rows = rows[rows != r]
            # The partner: the nearest other UAV over the step (the crash check is continuous).
            gap = np.minimum(np.linalg.norm(positions[-2][rows] - positions[-2][r], axis=1),
                             np.linalg.norm(positions[-1][rows] - positions[-1][r], axis=1))
            partner = int(rows[np.argmin(gap)])
            window = range(max(0, step - lookback), step)
            saw = any(in_view(positions[t][r], yaws[t][r], positions[t][partner], hfov, vfov, cam.max_range_m)
                      for t in window)
            seen = any(in_view(positions[t][partner], yaws[t][partner], positions[t][r], hfov, vfov,
                               cam.max_range_m) for t in window)
            velocity = (positions[-1] - positions[-2]) / config.control_period_s
            gap_rate = np.dot(velocity[partner] - velocity[r], positions[-2][partner] - positions[-2][r]) / max(
                np.linalg.norm(positions[-2][partner] - positions[-2][r]), 1e-6)
            events.append({"episode": int(world), "uav": int(r % n), "partner": int(partner % n),
                           "speed_m_s": round(float(np.linalg.norm(velocity[r])), 2),
                           "closing_speed_m_s": round(float(-gap_rate), 2),
                           "time_s": round(step * config.control_period_s, 2), "collider_saw_partner": bool(saw),
                           "partner_saw_collider": bool(seen), "partner_was_done": bool(not acting[partner])})
    uav_episodes = settings.episodes * n
    return {"policy": policy, "scenario": settings.describe(), "uav_episodes": uav_episodes,
            "lookback_s": LOOKBACK_S, "collisions": len(events), "events": events,
            "summary": summarize_events(events, uav_episodes)}


def summarize_events(events: list[dict], uav_episodes: int) -> dict:
    """Counts and rates (per UAV-episode) by visibility and by time since the start."""
    count = lambda pred: sum(1 for e in events if pred(e))  # noqa: E731
    out = {
        "collider_saw_partner": count(lambda e: e["collider_saw_partner"]),
        "only_partner_saw": count(lambda e: not e["collider_saw_partner"] and e["partner_saw_collider"]),
        "neither_saw": count(lambda e: not e["collider_saw_partner"] and not e["partner_saw_collider"]),
        "with_a_finished_uav": count(lambda e: e["partner_was_done"]),
    }
    for name, pick in (("saw", lambda e: e["collider_saw_partner"]), ("did_not_see", lambda e: not e["collider_saw_partner"])):
        speeds = [e["speed_m_s"] for e in events if pick(e)]
        out[f"median_speed_when_{name}_m_s"] = float(np.median(speeds)) if speeds else float("nan")
    out["median_closing_speed_m_s"] = float(np.median([e["closing_speed_m_s"] for e in events])) if events else float("nan")
    edges = (0.0, *TIME_BINS_S, math.inf)
    for lo, hi in zip(edges[:-1], edges[1:]):
        out[f"time_{lo:g}_{hi:g}_s"] = count(lambda e, lo=lo, hi=hi: lo < e["time_s"] <= hi)
    out["rates"] = {k: v / uav_episodes for k, v in out.items() if not k.startswith("median")}
    return out


def format_table(result: dict) -> str:
    s, total = result["summary"], max(result["collisions"], 1)
    rows = [("all UAV-UAV collisions", result["collisions"]),
            (f"collider had the partner in view (last {result['lookback_s']:g} s)", s["collider_saw_partner"]),
            ("only the partner had the collider in view", s["only_partner_saw"]),
            ("neither had the other in view", s["neither_saw"]),
            ("partner had already finished (hovering at its goal)", s["with_a_finished_uav"])]
    rows += [(f"collided {k[5:-2].replace('_', '-')} s after the start", v) for k, v in s.items()
             if k.startswith("time_")]
    lines = [f"{result['policy']}: {result['scenario']} ({result['uav_episodes']} UAV-episodes)",
             "| | UAVs | share of collisions | per UAV-episode |", "| --- | --- | --- | --- |"]
    lines += [f"| {name} | {v} | {v / total:.2f} | {v / result['uav_episodes']:.3f} |" for name, v in rows]
    lines.append(f"median speed at the collision: {s['median_speed_when_saw_m_s']:.2f} m/s when the collider had "
                 f"the partner in view, {s['median_speed_when_did_not_see_m_s']:.2f} m/s when not; median closing "
                 f"speed {s['median_closing_speed_m_s']:.2f} m/s")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sitl.collision_anatomy", description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", default=str(DEFAULT_POLICY), help="policy file or baseline name")
    parser.add_argument("--scenario", choices=("random", "circle"), default="random")
    parser.add_argument("--density", choices=tuple(DENSITIES), default="medium")
    parser.add_argument("--radius", type=float, default=12.0, help="circle radius (m)")
    parser.add_argument("--n", type=int, default=8, help="UAVs per episode")
    parser.add_argument("--episodes", type=int, default=100, help="episodes (all flown at once, <= 200)")
    parser.add_argument("--seed", type=int, default=0, help="evaluation seed (episodes of 1,000,000 + seed)")
    parser.add_argument("--json", type=Path, help="write the result with every collision here")
    args = parser.parse_args(argv)
    if not 1 <= args.episodes <= 200 or args.n < 2:
        parser.error("--episodes must be in 1..200 and --n at least 2")
    scenario = ScenarioConfig(name=args.scenario, density=DENSITIES[args.density], circle_radius_m=args.radius)
    settings = EvalSettings(scenario=scenario, num_uavs=args.n, episodes=args.episodes, seed=args.seed,
                            batch_worlds=200, record_paths=False)
    try:
        result = analyse(args.policy, settings)
    except EvaluationError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(format_table(result))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
