"""Anatomy of the UAV-UAV collisions a controller still has: when, and who could see whom.

A forward depth camera sees only what is in its field of view. This tool flies the same
test episodes as ``python -m sitl.swarm_test`` and, for every UAV that collides with
another, asks whether the partner was inside the collider's camera frustum (and whether the
collider was inside the partner's) at any control step of the last second before the
collision. Collisions neither UAV could see coming are out of reach of any policy that
sees only its own camera; collisions the collider saw are the policy's to avoid.

    python -m sitl.collision_anatomy --scenario random --density medium --episodes 100
    python -m sitl.collision_anatomy --protocol flown --cell random-medium --episodes 100

Prints a table and writes ``--json`` if given. Geometry test: the partner's centre inside
the camera's horizontal and vertical field of view (heading frame, level camera as in the
simulator) and within its range.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import deque
from pathlib import Path

import numpy as np

from sitl.sim.config import CIRCLE_RADIUS_M, DENSITIES, ScenarioConfig, SimConfig
from sitl.sim.env import COLLISION_UAV, SwarmEnv
from sitl.eval.evaluate import EvalSettings, evaluate_method, sim_config_for
from sitl.eval.flown import flown_cells
from sitl.eval.methods import DEFAULT_POLICY, EvaluationError, resolve_method
from sitl.eval.visibility import camera_fov_rad, in_view

#: The flown protocol's kinematic cells, the ones this tool can fly (not the JSBSim cell: the tool observes the
#: kinematic model). ``sitl.eval.flown.FLOWN_CELL_NAMES`` has them all.
KINEMATIC_FLOWN_CELLS = tuple(c.name for c in flown_cells(episodes=1, jsbsim=False))
LOOKBACK_S = 1.0  # "could have seen it coming": in view at some step of this window before the collision
TIME_BINS_S = (1.0, 2.0, 5.0)  # collision time since the episode start, for the table


def moving_in_view(velocity_ned: np.ndarray, yaw_rad: float, hfov_rad: float, vfov_rad: float) -> bool:
    """Whether a UAV flies where its (level, forward) camera looks: its velocity's direction inside the frustum.

    A UAV that climbs or descends steeply at low forward speed moves into space its camera does not
    cover (a D435 sees +-29 deg vertically); one that is still counts as in view.
    """
    speed = float(np.linalg.norm(velocity_ned))
    if speed < 1e-6:
        return True
    # The unit direction is a point 1 m away: any range above 1 m keeps only the frustum's angles.
    return bool(in_view(np.zeros(3), np.asarray(yaw_rad), np.asarray(velocity_ned) / speed, hfov_rad, vfov_rad,
                        max_range_m=np.inf))


class CollisionObserver:
    """Records, around every control step, what it needs to classify UAV-UAV collisions.

    Keeps the poses of the last ``lookback`` steps (tagged with each world's episode, as
    worlds restart with new episodes between steps) rather than whole episodes, so any
    number of episodes can be analysed.
    """

    def __init__(self, config: SimConfig) -> None:
        cam = config.camera
        self.hfov, self.vfov = camera_fov_rad(cam)  # a real sensor's (e.g. the D435's 87 x 58 deg) or square pixels'
        self.max_range_m = cam.max_range_m
        self.dt = config.control_period_s
        self.n = config.num_uavs
        self.recent: deque[tuple[np.ndarray, np.ndarray, np.ndarray]] = deque(
            maxlen=max(1, round(LOOKBACK_S / self.dt)))
        self.events: list[dict] = []
        self._acting = np.zeros(0, dtype=bool)

    def before_step(self, env: SwarmEnv) -> None:
        self._acting = env.acting.copy()
        self.recent.append((env.dynamics.pos_ned.copy(), env.dynamics.yaw_rad.copy(), env.world_episode.copy()))

    def after_step(self, env: SwarmEnv, info: dict) -> None:
        n, acting = self.n, self._acting
        before, after = self.recent[-1][0], env.dynamics.pos_ned
        for r in np.flatnonzero(acting & (info["outcome"] == COLLISION_UAV)):
            world = r // n
            rows = np.arange(world * n, (world + 1) * n)
            rows = rows[rows != r]
            # The partner: the nearest other UAV over the step (the crash check is continuous).
            gap = np.minimum(np.linalg.norm(before[rows] - before[r], axis=1),
                             np.linalg.norm(after[rows] - after[r], axis=1))
            partner = int(rows[np.argmin(gap)])
            episode = int(env.world_episode[world])
            window = [(pos, yaw) for pos, yaw, episodes in self.recent if episodes[world] == episode]
            saw = any(in_view(pos[r], yaw[r], pos[partner], self.hfov, self.vfov, self.max_range_m)
                      for pos, yaw in window)
            seen = any(in_view(pos[partner], yaw[partner], pos[r], self.hfov, self.vfov, self.max_range_m)
                       for pos, yaw in window)
            velocity = (after - before) / self.dt
            heading_seen = moving_in_view(velocity[r], self.recent[-1][1][r], self.hfov, self.vfov)
            offset = before[partner] - before[r]
            gap_rate = np.dot(velocity[partner] - velocity[r], offset) / max(np.linalg.norm(offset), 1e-6)
            self.events.append({"episode": episode, "uav": int(r % n), "partner": int(partner % n),
                                "speed_m_s": round(float(np.linalg.norm(velocity[r])), 2),
                                "closing_speed_m_s": round(float(-gap_rate), 2),
                                "time_s": round(int(env.world_steps[world]) * self.dt, 2),
                                "collider_saw_partner": bool(saw), "partner_saw_collider": bool(seen),
                                "partner_was_done": bool(not acting[partner]),
                                "collider_moved_in_view": heading_seen})


def analyse(policy: str, settings: EvalSettings, progress: bool = False) -> dict:
    """Fly ``settings.episodes`` episodes (as ``swarm_test`` does) and classify every UAV-UAV collision."""
    method = resolve_method(policy)
    observer = CollisionObserver(sim_config_for(method, settings, 1))
    result = evaluate_method(method, settings, progress=progress, desc="collision anatomy", observer=observer)
    uav_episodes = settings.episodes * settings.num_uavs
    events = sorted(observer.events, key=lambda e: (e["episode"], e["time_s"], e["uav"]))
    return {"policy": policy, "scenario": settings.describe(), "uav_episodes": uav_episodes,
            "lookback_s": LOOKBACK_S, "collisions": len(events),
            "collision_uav_rate": result.summary["collision_uav_rate"], "events": events,
            "summary": summarize_events(events, uav_episodes)}


def summarize_events(events: list[dict], uav_episodes: int) -> dict:
    """Counts and rates (per UAV-episode) by visibility and by time since the start."""
    count = lambda pred: sum(1 for e in events if pred(e))  # noqa: E731
    out = {
        "collider_saw_partner": count(lambda e: e["collider_saw_partner"]),
        "only_partner_saw": count(lambda e: not e["collider_saw_partner"] and e["partner_saw_collider"]),
        "neither_saw": count(lambda e: not e["collider_saw_partner"] and not e["partner_saw_collider"]),
        "with_a_finished_uav": count(lambda e: e["partner_was_done"]),
        # e.g. climbing or descending steeply at low forward speed: outside a D435's +-29 deg
        "collider_moved_out_of_view": count(lambda e: not e["collider_moved_in_view"]),
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
            ("partner had already finished (hovering at its goal)", s["with_a_finished_uav"]),
            ("collider was moving outside its camera's view (its velocity's direction)",
             s["collider_moved_out_of_view"])]
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
    parser.add_argument("--protocol", choices=("paper", "flown"), default="paper",
                        help="paper: the scene given by --scenario/--density/--radius/--n (paper geometry, "
                             "perfect depth); flown: one cell of `swarm_test flown` (--cell), as it flies it")
    parser.add_argument("--cell", choices=KINEMATIC_FLOWN_CELLS, default="random-medium",
                        help="the flown protocol's cell (with --protocol flown)")
    parser.add_argument("--scenario", choices=("random", "circle"), default="random")
    parser.add_argument("--density", choices=tuple(DENSITIES), default="medium")
    parser.add_argument("--radius", type=float, default=CIRCLE_RADIUS_M, help="circle radius (m)")
    parser.add_argument("--n", type=int, default=8, help="UAVs per episode")
    parser.add_argument("--episodes", type=int, default=100, help="episodes")
    parser.add_argument("--seed", type=int, default=0, help="evaluation seed (episodes of 1,000,000 + seed)")
    parser.add_argument("--json", type=Path, help="write the result with every collision here")
    args = parser.parse_args(argv)
    if args.episodes < 1 or args.n < 2:
        parser.error("--episodes must be at least 1 and --n at least 2")
    given = sys.argv[1:] if argv is None else argv
    paper_scene = [flag for flag in ("--scenario", "--density", "--radius", "--n")
                   if any(a == flag or a.startswith(flag + "=") for a in given)]
    if args.protocol == "flown" and paper_scene:  # the cell fixes the scene: a flag that would be ignored is refused
        parser.error(f"{', '.join(paper_scene)}: a paper-protocol scene setting; with --protocol flown choose a --cell")
    if args.protocol == "flown":
        settings = next(c.settings for c in flown_cells(args.episodes, args.seed, jsbsim=False) if c.name == args.cell)
    else:
        scenario = ScenarioConfig(name=args.scenario, density=DENSITIES[args.density], circle_radius_m=args.radius)
        settings = EvalSettings(scenario=scenario, num_uavs=args.n, episodes=args.episodes, seed=args.seed,
                                record_paths=False)
    try:
        result = analyse(args.policy, settings, progress=True)
    except EvaluationError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(format_table(result))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
