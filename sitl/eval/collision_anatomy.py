"""Anatomy of the UAV-UAV collisions a controller still has (when, and who could see whom), and of its timeouts.

A forward depth camera sees only what is in its field of view. This tool flies the same
test episodes as ``python -m sitl.swarm_test`` and, for every UAV that collides with
another, asks whether the partner was inside the collider's camera frustum (and whether the
collider was inside the partner's) at any control step of the last second before the
collision. Collisions neither UAV could see coming are out of reach of any policy that
sees only its own camera; collisions the collider saw are the policy's to avoid. For those it
also says how early the collider first had the partner in view (looked for up to
``WARNING_WINDOW_S`` back) and how its speed changed since: a partner seen seconds ahead with no
slowing down is a decision the policy got wrong, one that entered the view at the last moment is not.

    python -m sitl.collision_anatomy --scenario random --density medium --episodes 100
    python -m sitl.collision_anatomy --protocol flown --cell random-medium --episodes 100

A UAV that times out ends the episode neither arrived nor crashed. The tool also says where
each one was at the time limit and whether it was still flying: *stalled near its goal* (within
``NEAR_GOAL_M`` and it moved less than ``STALLED_M`` over the last ``STALL_WINDOW_S``),
*stalled elsewhere*, or *still flying* (e.g. a detour too long for the time limit, or circling),
with its distance to the goal and to the nearest static obstacle.

It also measures how much of the flight goes where the camera does not look: the share of moving
UAV-steps (faster than ``MOVING_M_S``) and of the distance flown whose velocity points outside the
UAV's camera frustum, and how much of that is vertical (climbing or descending too steeply for the
camera's vertical field of view) and within the first ``EARLY_S`` of the episode.

For each collision it records where the partner was at the start of that last second, seen from the
collider (bearing and elevation in its heading frame), and counts the unseen collisions whose partner
was then above or below the camera's vertical view: the blind spot of a level forward camera, where a
UAV climbing or descending meets one it never had in its image.

Prints the tables and writes ``--json`` if given. Geometry test: the partner's centre inside
the camera's horizontal and vertical field of view (heading frame, level camera as in the
simulator) and within its range.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from collections import deque
from pathlib import Path

import numpy as np

from companion.frames import ned_to_frd
from companion.governor import GOVERNOR_PRESETS, GovernorSpec
from sitl.cli_args import add_governor_flag, camera_preset
from sitl.sim.camera import in_frustum
from sitl.sim.config import CIRCLE_RADIUS_M, DENSITIES, ScenarioConfig, SimConfig
from sitl.sim.collision import distance_to_obstacles_m
from sitl.sim.env import COLLISION_UAV, TIMEOUT, SwarmEnv
from sitl.eval.evaluate import EvalSettings, evaluate_method, sim_config_for
from sitl.eval.flown import flown_cells
from sitl.eval.methods import DEFAULT_POLICY, GOVERNED_SUFFIX, EvaluationError, resolve_method
from sitl.eval.visibility import camera_fov_rad, in_view

#: The flown protocol's kinematic cells, the ones this tool can fly (not the JSBSim cell: the tool observes the
#: kinematic model). ``sitl.eval.flown.FLOWN_CELL_NAMES`` has them all.
KINEMATIC_FLOWN_CELLS = tuple(c.name for c in flown_cells(episodes=1, jsbsim=False))
LOOKBACK_S = 1.0  # "could have seen it coming": in view at some step of this window before the collision
WARNING_WINDOW_S = 5.0  # how early the collider first had the partner in view is looked for this far back
WARNING_LONG_S = 2.0  # "seen well in advance": first in view at least this long before the collision
TIME_BINS_S = (1.0, 2.0, 5.0)  # collision time since the episode start, for the table
STALL_WINDOW_S = 5.0  # a timed-out UAV's displacement is measured over this last window...
STALLED_M = 0.5  # ...and below this it counts as stalled (0.1 m/s on average)
NEAR_GOAL_M = 3.0  # "near its goal": the arrival radius is 0.5 m, so a stall inside this is the last metres
MOVING_M_S = 0.2  # blind flight: a UAV slower than this is hovering or turning in place, its direction noise
EARLY_S = 3.0  # blind flight "early": the first seconds, when UAVs leave their starts 1-2 m apart


def moving_in_view(velocity_ned: np.ndarray, yaw_rad: float, hfov_rad: float, vfov_rad: float) -> bool:
    """Whether a UAV flies where its (level, forward) camera looks: its velocity's direction inside the frustum.

    A UAV that climbs or descends steeply at low forward speed moves into space its camera does not
    cover (a D435 sees +-29 deg vertically); one that is still counts as in view.
    """
    if float(np.linalg.norm(velocity_ned)) < 1e-6:
        return True
    return bool(in_frustum(ned_to_frd(np.asarray(velocity_ned), yaw_rad), math.tan(hfov_rad / 2), math.tan(vfov_rad / 2)))


def bearing_elevation_deg(offset_ned: np.ndarray, yaw_rad: float) -> tuple[float, float]:
    """Bearing (deg, right +) and elevation (deg, up +) of ``offset_ned`` in the heading frame of a UAV at ``yaw_rad``."""
    frd = ned_to_frd(np.asarray(offset_ned, dtype=float), yaw_rad)
    return (math.degrees(math.atan2(frd[1], frd[0])),
            math.degrees(math.atan2(-frd[2], math.hypot(frd[0], frd[1]))))


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
        self.lookback_steps = max(1, round(LOOKBACK_S / self.dt))
        self.recent: deque[tuple[np.ndarray, np.ndarray, np.ndarray]] = deque(
            maxlen=max(self.lookback_steps, round(WARNING_WINDOW_S / self.dt)))
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
            history = [(pos, yaw) for pos, yaw, episodes in self.recent if episodes[world] == episode]
            window = history[-self.lookback_steps:]
            saw = any(in_view(pos[r], yaw[r], pos[partner], self.hfov, self.vfov, self.max_range_m)
                      for pos, yaw in window)
            seen = any(in_view(pos[partner], yaw[partner], pos[r], self.hfov, self.vfov, self.max_range_m)
                       for pos, yaw in window)
            # How early the collider first had the partner in view (within WARNING_WINDOW_S), and how fast
            # it flew then: a long warning with no slowing down is a decision, not a sensing, failure.
            sighted = [k for k, (pos, yaw) in enumerate(history)
                       if in_view(pos[r], yaw[r], pos[partner], self.hfov, self.vfov, self.max_range_m)]
            first = sighted[0] if sighted else None
            velocity = (after - before) / self.dt
            heading_seen = moving_in_view(velocity[r], self.recent[-1][1][r], self.hfov, self.vfov)
            # Where the partner was 1 s before, seen from the collider (heading frame): to the side, or above/below?
            then_pos, then_yaw = window[0]
            bearing_deg, elevation_deg = bearing_elevation_deg(then_pos[partner] - then_pos[r], float(then_yaw[r]))
            offset = before[partner] - before[r]
            gap_rate = np.dot(velocity[partner] - velocity[r], offset) / max(np.linalg.norm(offset), 1e-6)
            if first is None:
                warning_s, speed_at_sight = 0.0, None
            else:
                warning_s = (len(history) - first) * self.dt
                later = history[first + 1][0][r] if first + 1 < len(history) else after[r]
                speed_at_sight = float(np.linalg.norm(later - history[first][0][r])) / self.dt
            self.events.append({"episode": episode, "uav": int(r % n), "partner": int(partner % n),
                                "speed_m_s": round(float(np.linalg.norm(velocity[r])), 2),
                                "warning_s": round(warning_s, 2),
                                "speed_at_first_sight_m_s": None if speed_at_sight is None else round(speed_at_sight, 2),
                                "closing_speed_m_s": round(float(-gap_rate), 2),
                                "time_s": round(int(env.world_steps[world]) * self.dt, 2),
                                "collider_saw_partner": bool(saw), "partner_saw_collider": bool(seen),
                                "partner_was_done": bool(not acting[partner]),
                                "collider_moved_in_view": heading_seen,
                                "partner_bearing_deg_lookback": round(bearing_deg, 1),
                                "partner_elevation_deg_lookback": round(elevation_deg, 1),
                                "vertical_gap_m": round(float(before[r, 2] - before[partner, 2]), 2),  # partner above: +
                                "beyond_vertical_view": bool(abs(elevation_deg) > math.degrees(self.vfov) / 2)})


class TimeoutObserver:
    """Records where every UAV that times out is at the time limit, and how far it moved before it.

    Keeps the positions of the last ``STALL_WINDOW_S`` (tagged with each world's episode, like
    :class:`CollisionObserver`).
    """

    def __init__(self, config: SimConfig) -> None:
        self.dt = config.control_period_s
        self.recent: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=max(1, round(STALL_WINDOW_S / self.dt)))
        self.events: list[dict] = []

    def before_step(self, env: SwarmEnv) -> None:
        self.recent.append((env.dynamics.pos_ned.copy(), env.world_episode.copy()))

    def after_step(self, env: SwarmEnv, info: dict) -> None:
        n = env.uavs_per_world
        for r in np.flatnonzero(info["acting"] & (info["outcome"] == TIMEOUT)):
            world, pos, goal = r // n, env.dynamics.pos_ned[r], env.goal_ned[r]
            episode = int(env.world_episode[world])
            window = [p[r] for p, episodes in self.recent if episodes[world] == episode]
            others = np.delete(env.dynamics.pos_ned[world * n:(world + 1) * n], r % n, axis=0)
            # Padding rows lie 1e6 m away, so they never win the minimum where an obstacle stands.
            obstacle = (distance_to_obstacles_m(pos[None], env.boxes[world], env.cylinders[world])[0]
                        if env.world_has_obstacles[world] else None)
            self.events.append({
                "episode": episode, "uav": int(r % n),
                "distance_to_goal_m": round(float(np.linalg.norm(goal - pos)), 2),
                "altitude_m": round(float(-pos[2]), 2), "goal_altitude_m": round(float(-goal[2]), 2),
                "moved_last_window_m": round(float(np.linalg.norm(pos - window[0])), 2),
                # closer to the goal than at the window's start by (negative: flying away from it)
                "progress_last_window_m": round(float(np.linalg.norm(goal - window[0]) - np.linalg.norm(goal - pos)), 2),
                "nearest_obstacle_m": None if obstacle is None else round(float(obstacle), 2),
                "nearest_uav_m": round(float(np.linalg.norm(others - pos, axis=1).min()), 2) if len(others) else None})


def timeout_kind(event: dict) -> str:
    """``stalled_near_goal``, ``stalled_elsewhere`` or ``still_flying`` (module doc)."""
    if event["moved_last_window_m"] >= STALLED_M:
        return "still_flying"
    return "stalled_near_goal" if event["distance_to_goal_m"] < NEAR_GOAL_M else "stalled_elsewhere"


def summarize_timeouts(events: list[dict], uav_episodes: int) -> dict:
    """Per kind: count, rate per UAV-episode and medians of distance to goal and to the nearest obstacle."""
    out: dict = {"timeouts": len(events), "rate": len(events) / uav_episodes}
    for kind in ("stalled_near_goal", "stalled_elsewhere", "still_flying"):
        picked = [e for e in events if timeout_kind(e) == kind]
        out[kind] = {"count": len(picked), "rate": len(picked) / uav_episodes,
                     **{f"median_{key}": _median(picked, key) for key in
                        ("distance_to_goal_m", "nearest_obstacle_m", "altitude_m", "progress_last_window_m")}}
    return out


def _median(events: list[dict], key: str) -> float:
    """Median of ``key`` over the events that have it (``None``: no obstacle in the scene); NaN if none."""
    values = [e[key] for e in events if e[key] is not None]
    return float(np.median(values)) if values else float("nan")


class BlindFlightObserver:
    """Sums, over every acting UAV-step, the motion whose direction lies outside the UAV's camera frustum."""

    def __init__(self, config: SimConfig) -> None:
        self.camera, self.dt = config.camera, config.control_period_s
        self.moving_steps = self.blind_steps = self.vertical_steps = self.early_steps = 0
        self.distance_m = self.blind_distance_m = 0.0

    def before_step(self, env: SwarmEnv) -> None:
        self._acting = env.acting.copy()
        self._early = np.repeat(env.world_steps * self.dt < EARLY_S, env.uavs_per_world)

    def after_step(self, env: SwarmEnv, info: dict) -> None:
        d, cam = env.dynamics, self.camera
        speed = np.linalg.norm(d.vel_ned, axis=1)
        rows = self._acting & (speed > MOVING_M_S)
        speed, pitch = speed[rows], env.mount_pitch_rad[rows]
        v_frd = ned_to_frd(d.vel_ned[rows], d.yaw_rad[rows])
        blind = ~in_frustum(v_frd, cam.tan_half_hfov, cam.tan_half_vfov, pitch)
        # Vertically blind: outside the frustum, but its horizontal projection inside (it leaves
        # through the top or bottom of the view, not the sides).
        level = in_frustum(v_frd * np.array([1.0, 1.0, 0.0]), cam.tan_half_hfov, cam.tan_half_vfov, pitch)
        self.moving_steps += int(rows.sum())
        self.blind_steps += int(blind.sum())
        self.vertical_steps += int((blind & level).sum())
        self.early_steps += int((blind & self._early[rows]).sum())
        self.distance_m += float(speed.sum()) * self.dt
        self.blind_distance_m += float(speed[blind].sum()) * self.dt

    def summary(self) -> dict:
        steps = max(self.moving_steps, 1)
        return {"moving_steps": self.moving_steps, "blind_share_of_moving_steps": self.blind_steps / steps,
                "blind_share_of_distance": self.blind_distance_m / max(self.distance_m, 1e-9),
                "vertical_share_of_blind": self.vertical_steps / max(self.blind_steps, 1),
                f"early_share_of_blind_first_{EARLY_S:g}_s": self.early_steps / max(self.blind_steps, 1)}


class _Observers:
    """Calls several step observers in turn (``evaluate_method`` takes one)."""

    def __init__(self, *observers) -> None:
        self.observers = observers

    def before_step(self, env: SwarmEnv) -> None:
        for o in self.observers:
            o.before_step(env)

    def after_step(self, env: SwarmEnv, info: dict) -> None:
        for o in self.observers:
            o.after_step(env, info)


def analyse(policy: str, settings: EvalSettings, progress: bool = False, governor: GovernorSpec | None = None) -> dict:
    """Fly ``settings.episodes`` episodes (as ``swarm_test`` does, with the speed ``governor`` after the
    controller if given); classify every UAV-UAV collision and timeout."""
    method = resolve_method(policy)
    if governor is not None:
        method = method.with_governor(governor)
    config = sim_config_for(method, settings, 1)
    collisions, timeouts, blind = CollisionObserver(config), TimeoutObserver(config), BlindFlightObserver(config)
    result = evaluate_method(method, settings, progress=progress, desc="collision anatomy",
                             observer=_Observers(collisions, timeouts, blind))
    uav_episodes = settings.episodes * settings.num_uavs
    events = sorted(collisions.events, key=lambda e: (e["episode"], e["time_s"], e["uav"]))
    timed_out = sorted(timeouts.events, key=lambda e: (e["episode"], e["uav"]))
    return {"policy": policy, "method": method.label, "scenario": settings.describe(), "uav_episodes": uav_episodes,
            "lookback_s": LOOKBACK_S, "collisions": len(events),
            "collision_uav_rate": result.summary["collision_uav_rate"], "events": events,
            "summary": summarize_events(events, uav_episodes),
            "timeout_rate": result.summary["timeout_rate"], "timeout_events": timed_out,
            "timeouts": summarize_timeouts(timed_out, uav_episodes), "blind_flight": blind.summary()}


def summarize_events(events: list[dict], uav_episodes: int) -> dict:
    """Counts and rates (per UAV-episode) by visibility and by time since the start."""
    count = lambda pred: sum(1 for e in events if pred(e))  # noqa: E731
    out = {
        "collider_saw_partner": count(lambda e: e["collider_saw_partner"]),
        "only_partner_saw": count(lambda e: not e["collider_saw_partner"] and e["partner_saw_collider"]),
        "neither_saw": count(lambda e: not e["collider_saw_partner"] and not e["partner_saw_collider"]),
        # a level forward camera's blind spot: the partner above or below its vertical view a second before
        "neither_saw_partner_above_or_below": count(lambda e: not e["collider_saw_partner"]
                                                    and not e["partner_saw_collider"] and e["beyond_vertical_view"]),
        "with_a_finished_uav": count(lambda e: e["partner_was_done"]),
        # e.g. climbing or descending steeply at low forward speed: outside a D435's +-29 deg
        "collider_moved_out_of_view": count(lambda e: not e["collider_moved_in_view"]),
    }
    for name, pick in (("saw", lambda e: e["collider_saw_partner"]),
                       ("did_not_see", lambda e: not e["collider_saw_partner"])):
        speeds = [e["speed_m_s"] for e in events if pick(e)]
        out[f"median_speed_when_{name}_m_s"] = float(np.median(speeds)) if speeds else float("nan")
    closing = [e["closing_speed_m_s"] for e in events]
    out["median_closing_speed_m_s"] = float(np.median(closing)) if closing else float("nan")
    # Of the collisions the collider saw coming: how early it first saw the partner and what it did with its speed.
    saw = [e for e in events if e["collider_saw_partner"]]
    out[f"saw_with_warning_at_least_{WARNING_LONG_S:g}_s"] = count(
        lambda e: e["collider_saw_partner"] and e["warning_s"] >= WARNING_LONG_S)
    out["median_warning_when_saw_s"] = float(np.median([e["warning_s"] for e in saw])) if saw else float("nan")
    out["median_speed_change_when_saw_m_s"] = (float(np.median([e["speed_m_s"] - e["speed_at_first_sight_m_s"]
                                                                 for e in saw])) if saw else float("nan"))
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
            (f"... and the partner was above or below the collider's vertical view {result['lookback_s']:g} s before",
             s["neither_saw_partner_above_or_below"]),
            ("partner had already finished (hovering at its goal)", s["with_a_finished_uav"]),
            ("collider was moving outside its camera's view (its velocity's direction)",
             s["collider_moved_out_of_view"])]
    rows.append((f"collider had it in view and first saw it {WARNING_LONG_S:g} s or more before",
                 s[f"saw_with_warning_at_least_{WARNING_LONG_S:g}_s"]))
    rows += [(f"collided {k[5:-2].replace('_', '-')} s after the start", v) for k, v in s.items()
             if k.startswith("time_")]
    flown_as = f" ({result['method']})" if GOVERNED_SUFFIX in result.get("method", "") else ""
    lines = [f"{result['policy']}{flown_as}: {result['scenario']} ({result['uav_episodes']} UAV-episodes)",
             "| | UAVs | share of collisions | per UAV-episode |", "| --- | --- | --- | --- |"]
    lines += [f"| {name} | {v} | {v / total:.2f} | {v / result['uav_episodes']:.3f} |" for name, v in rows]
    lines.append(f"median speed at the collision: {s['median_speed_when_saw_m_s']:.2f} m/s when the collider had "
                 f"the partner in view, {s['median_speed_when_did_not_see_m_s']:.2f} m/s when not; median closing "
                 f"speed {s['median_closing_speed_m_s']:.2f} m/s; when the collider had the partner in view, it "
                 f"first saw it a median {s['median_warning_when_saw_s']:.1f} s before (looked for up to "
                 f"{WARNING_WINDOW_S:g} s) and its speed changed by a median "
                 f"{s['median_speed_change_when_saw_m_s']:+.2f} m/s since")
    b = result["blind_flight"]
    lines.append(f"flight outside the camera's view: {b['blind_share_of_moving_steps']:.3f} of the moving UAV-steps "
                 f"(> {MOVING_M_S:g} m/s), {b['blind_share_of_distance']:.3f} of the distance flown; of those steps "
                 f"{b['vertical_share_of_blind']:.2f} vertical (too steep for the camera) and "
                 f"{b[f'early_share_of_blind_first_{EARLY_S:g}_s']:.2f} in the first {EARLY_S:g} s")
    t = result["timeouts"]
    lines += ["", f"timeouts: {t['timeouts']} UAVs ({t['rate']:.3f} per UAV-episode)",
              "| at the time limit | UAVs | per UAV-episode | median distance to goal (m) | "
              "median nearest obstacle (m) | median altitude (m) | median progress to goal, last window (m) |",
              "| --- | --- | --- | --- | --- | --- | --- |"]
    names = {"stalled_near_goal": f"stalled (< {STALLED_M:g} m in the last {STALL_WINDOW_S:g} s) within {NEAR_GOAL_M:g} m of its goal",
             "stalled_elsewhere": "stalled farther from its goal", "still_flying": "still flying"}
    for kind, name in names.items():
        k = t[kind]
        lines.append(f"| {name} | {k['count']} | {k['rate']:.3f} | {k['median_distance_to_goal_m']:.2f} | "
                     f"{k['median_nearest_obstacle_m']:.2f} | {k['median_altitude_m']:.2f} | "
                     f"{k['median_progress_last_window_m']:.2f} |")
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
    parser.add_argument("--camera", type=camera_preset, default=None,
                        help="with --protocol flown: camera preset the UAVs carry (default: the policy's own, paper "
                             "for the references; orca-fov avoids what this camera covers, e.g. realsense_d435)")
    parser.add_argument("--obstacle-clearance", type=float, metavar="M",
                        help="with --cell obstacles: keep obstacles M m from every start and goal instead of the "
                             f"scene's {ScenarioConfig.obstacle_clearance_m:g} m (does a pole beside the goal stall it?)")
    add_governor_flag(parser)
    parser.add_argument("--json", type=Path, help="write the result with every collision and timeout here")
    args = parser.parse_args(argv)
    if args.episodes < 1 or args.n < 2:
        parser.error("--episodes must be at least 1 and --n at least 2")
    given = sys.argv[1:] if argv is None else argv
    paper_scene = [flag for flag in ("--scenario", "--density", "--radius", "--n")
                   if any(a == flag or a.startswith(flag + "=") for a in given)]
    if args.protocol == "flown" and paper_scene:  # the cell fixes the scene: a flag that would be ignored is refused
        parser.error(f"{', '.join(paper_scene)}: a paper-protocol scene setting; with --protocol flown choose a --cell")
    if args.camera is not None and args.protocol != "flown":
        parser.error("--camera needs --protocol flown")
    if args.obstacle_clearance is not None and (args.protocol != "flown" or args.cell != "obstacles"):
        parser.error("--obstacle-clearance needs --protocol flown --cell obstacles")
    if args.protocol == "flown":
        settings = next(c.settings for c in flown_cells(args.episodes, args.seed, jsbsim=False, camera=args.camera)
                        if c.name == args.cell)
        if args.obstacle_clearance is not None:
            try:
                scenario = dataclasses.replace(settings.scenario, obstacle_clearance_m=args.obstacle_clearance)
            except ValueError as err:
                parser.error(f"--obstacle-clearance: {err}")
            settings = dataclasses.replace(settings, scenario=scenario)
    else:
        scenario = ScenarioConfig(name=args.scenario, density=DENSITIES[args.density], circle_radius_m=args.radius)
        settings = EvalSettings(scenario=scenario, num_uavs=args.n, episodes=args.episodes, seed=args.seed,
                                record_paths=False)
    try:
        result = analyse(args.policy, settings, progress=True, governor=GOVERNOR_PRESETS[args.governor] if args.governor else None)
    except EvaluationError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(format_table(result))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
