"""Start and goal positions (and static obstacles) of every scenario; see :class:`ScenarioConfig`.

The paper's scenes (IV.B-C) are ``random`` and ``circle`` with the default geometry; the task as
flown (:func:`sitl.sim.config.scenario_for` ``("flown", ...)``) draws altitudes, circle sizes and
start offsets per episode, and ``obstacles`` puts poles, trees and boxes among the UAVs.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from companion.frames import wrap_angle_rad
from sitl.sim.collision import distance_to_obstacles_m
from sitl.sim.config import (OBSTACLE_BOX_HALF_SIDE_M, OBSTACLE_BOX_HEIGHT_M, OBSTACLE_CYLINDER_HEIGHT_M,
                             LOW_FLOOR_BAND_M, OBSTACLE_CYLINDER_RADIUS_M, ScenarioConfig)

#: Test seeds (the final evaluation of a training run, ``swarm_test``) are ``EVAL_SEED_OFFSET + seed``;
#: training seeds stay below it.
EVAL_SEED_OFFSET = 1_000_000
#: Validation seeds (periodic evaluations during training, snapshot selection, ``sitl.rescore``):
#: disjoint from both, so choosing a snapshot never looks at the test episodes.
VALIDATION_SEED_OFFSET = 500_000


@dataclass
class ScenarioSample:
    """One episode's initial conditions for a world of N UAVs (local NED, metres)."""

    start_ned: np.ndarray  # [N, 3]
    goal_ned: np.ndarray  # [N, 3]
    yaw_rad: np.ndarray  # [N]
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))  # [Kb, 6] static boxes (camera layout)
    cylinders: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))  # [Kc, 5] static vertical cylinders
    circle: bool = False  # a circle episode (every UAV bound for the antipodal point)


def random_box_size(num_uavs: int, density: float, aspect: float) -> tuple[float, float]:
    """Side and height (m) of the random scenario's box: volume N / density, height = aspect * side."""
    volume = num_uavs / density
    side = (volume / aspect) ** (1.0 / 3.0)
    return side, aspect * side


def _bearing_rad(from_ned: np.ndarray, to_ned: np.ndarray) -> np.ndarray:
    delta = to_ned - from_ned
    return np.arctan2(delta[..., 1], delta[..., 0])


def _spread_points(count: int, low: np.ndarray, high: np.ndarray, min_sep: float, rng: np.random.Generator,
                   avoid: np.ndarray | None = None, avoid_min: float = 0.0, max_tries: int = 2000) -> np.ndarray:
    """Draw ``count`` points uniformly in a box, pairwise >= ``min_sep`` apart (rejection sampling).

    ``avoid[i]`` (optional) is a point that point i must stay ``avoid_min`` away from.
    """
    points = np.empty((count, 3))
    for i in range(count):
        for _ in range(max_tries):
            candidate = rng.uniform(low, high)
            if i and np.min(np.linalg.norm(points[:i] - candidate, axis=1)) < min_sep:
                continue
            if avoid is not None and np.linalg.norm(candidate - avoid[i]) < avoid_min:
                continue
            points[i] = candidate
            break
        else:
            raise ValueError(
                f"cannot place {count} points {min_sep} m apart in a box of size {np.round(high - low, 2)} m: "
                "the density is too high for the minimum separation"
            )
    return points


def box_floor_alt_m(num_uavs: int, config: ScenarioConfig, rng: np.random.Generator) -> float:
    """The random box's floor altitude (m) for one episode: fixed, or drawn so the box fits the altitude range."""
    if config.altitude_range_m is None:
        return config.box_floor_alt_m
    _, height = random_box_size(num_uavs, config.density, config.box_aspect)
    lo, hi = config.altitude_range_m
    if lo + height > hi:
        raise ValueError(f"the random box of {num_uavs} UAVs at {config.density:g} UAV/m^3 is {height:.1f} m tall: "
                         f"it does not fit between {lo:g} and {hi:g} m above the ground")
    # Only a positive fraction draws the extra number: every other run keeps its episodes exactly.
    if config.low_floor_fraction > 0 and rng.uniform() < config.low_floor_fraction:
        return float(rng.uniform(lo, min(lo + LOW_FLOOR_BAND_M, hi - height)))
    return float(rng.uniform(lo, hi - height))


def _jitter_starts(start: np.ndarray, config: ScenarioConfig, rng: np.random.Generator) -> np.ndarray:
    """Each start moved by up to ``start_jitter_m`` per axis, kept ``min_separation_m`` from the others and
    above the lowest altitude (a start whose every try fails stays where it was planned)."""
    if config.start_jitter_m <= 0:
        return start
    lowest_alt = config.altitude_range_m[0] if config.altitude_range_m else 0.0
    return _moved_apart(start, lambda: rng.uniform(-config.start_jitter_m, config.start_jitter_m, 3),
                        config.min_separation_m, lowest_alt)


def _moved_apart(start: np.ndarray, draw_offset, min_separation_m: float, lowest_alt_m: float = 0.0,
                 max_tries: int = 50) -> np.ndarray:
    """Each start moved by an offset from ``draw_offset()`` ([3], NED m), redrawn while it would come closer than
    ``min_separation_m`` to another start or below ``lowest_alt_m``; a start whose every try fails stays put."""
    out = start.copy()
    for i in range(len(start)):
        for _ in range(max_tries):
            candidate = start[i] + draw_offset()
            others = np.delete(out, i, axis=0)
            if -candidate[2] < lowest_alt_m:
                continue
            if len(others) and np.min(np.linalg.norm(others - candidate, axis=1)) < min_separation_m:
                continue
            out[i] = candidate
            break
    return out


def sample_random(num_uavs: int, config: ScenarioConfig, rng: np.random.Generator) -> ScenarioSample:
    """Random scenario: starts and goals uniformly in a box whose volume sets the density."""
    side, height = random_box_size(num_uavs, config.density, config.box_aspect)
    floor = box_floor_alt_m(num_uavs, config, rng)
    # NED box centred on the origin horizontally; z is down, so altitudes are negated.
    low = np.array([-side / 2, -side / 2, -(floor + height)])
    high = np.array([side / 2, side / 2, -floor])
    start = _spread_points(num_uavs, low, high, config.min_separation_m, rng)
    goal = _spread_points(num_uavs, low, high, config.min_separation_m, rng,
                          avoid=start, avoid_min=config.min_goal_distance_m)
    start = _jitter_starts(start, config, rng)
    yaw = _bearing_rad(start, goal) + rng.uniform(-config.yaw_jitter_rad, config.yaw_jitter_rad, num_uavs)
    return ScenarioSample(start, goal, wrap_angle_rad(yaw))


def obstacle_counts(num_uavs: int, config: ScenarioConfig) -> tuple[int, int]:
    """(boxes, cylinders) of one ``obstacles`` episode: the density times the widened footprint of the box."""
    side, _ = random_box_size(num_uavs, config.density, config.box_aspect)
    area_m2 = (side + 2 * config.obstacle_margin_m) ** 2
    total = int(round(config.obstacle_density_per_100m2 * area_m2 / 100.0))
    boxes = int(round(total * config.obstacle_box_fraction))
    return boxes, total - boxes


def _place_obstacles(num_uavs: int, config: ScenarioConfig, keep_clear: np.ndarray,
                     rng: np.random.Generator, max_tries: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """Boxes and cylinders standing on the ground around the box, each ``obstacle_clearance_m`` from
    every point of ``keep_clear`` [P, 3]. One that finds no free place in ``max_tries`` is left out
    (the scene is then a little sparser; at the default density this does not happen)."""
    side, _ = random_box_size(num_uavs, config.density, config.box_aspect)
    half = side / 2 + config.obstacle_margin_m
    n_boxes, n_cylinders = obstacle_counts(num_uavs, config)
    boxes, cylinders = [], []
    for kind, count in (("box", n_boxes), ("cylinder", n_cylinders)):
        for _ in range(count):
            for _ in range(max_tries):
                north, east = rng.uniform(-half, half, 2)
                if kind == "box":
                    hn, he = rng.uniform(*OBSTACLE_BOX_HALF_SIDE_M, 2)
                    height = rng.uniform(*OBSTACLE_BOX_HEIGHT_M)
                    row = np.array([north, east, -height / 2, hn, he, height / 2])
                    shape = (row[None], np.zeros((0, 5)))
                else:
                    radius = rng.uniform(*OBSTACLE_CYLINDER_RADIUS_M)
                    height = rng.uniform(*OBSTACLE_CYLINDER_HEIGHT_M)
                    row = np.array([north, east, radius, -height, 0.0])
                    shape = (np.zeros((0, 6)), row[None])
                if distance_to_obstacles_m(keep_clear, *shape).min() >= config.obstacle_clearance_m:
                    (boxes if kind == "box" else cylinders).append(row)
                    break
    return np.array(boxes).reshape(-1, 6), np.array(cylinders).reshape(-1, 5)


def sample_obstacles(num_uavs: int, config: ScenarioConfig, rng: np.random.Generator) -> ScenarioSample:
    """Obstacles scenario: a random scene among static boxes and vertical cylinders (poles, trees)."""
    sample = sample_random(num_uavs, config, rng)
    keep_clear = np.concatenate([sample.start_ned, sample.goal_ned])
    sample.boxes, sample.cylinders = _place_obstacles(num_uavs, config, keep_clear, rng)
    return sample


def sample_circle(num_uavs: int, config: ScenarioConfig, rng: np.random.Generator) -> ScenarioSample:
    """Circle scenario: evenly spaced on a circle, goals antipodal, formation randomly rotated."""
    angles = rng.uniform(0, 2 * math.pi) + 2 * math.pi * np.arange(num_uavs) / num_uavs
    # Drawn only when asked, so the paper's circle consumes the generator exactly as before.
    radius = rng.uniform(*config.circle_radius_range_m) if config.circle_radius_range_m else config.circle_radius_m
    alt = rng.uniform(*config.circle_alt_range_m) if config.circle_alt_range_m else config.circle_alt_m
    ring = np.stack([np.cos(angles), np.sin(angles), np.zeros(num_uavs)], axis=1) * radius
    ring[:, 2] = -alt
    goal = ring * np.array([-1.0, -1.0, 1.0])
    start = ring + rng.uniform(-config.circle_jitter_m, config.circle_jitter_m, ring.shape)
    if config.circle_scatter_m > 0:  # drawn only when asked: other circles consume the generator as before
        start = _moved_apart(start, lambda: _disc_offset(config.circle_scatter_m, rng), config.min_separation_m)
    return ScenarioSample(start, goal, _circle_start_heading(start, goal, config.circle_heading, rng), circle=True)


def _disc_offset(radius_m: float, rng: np.random.Generator) -> np.ndarray:
    """A horizontal offset ([3], NED m) drawn uniformly in a disc of ``radius_m``."""
    r, a = radius_m * math.sqrt(rng.random()), rng.uniform(0.0, 2 * math.pi)
    return np.array([r * math.cos(a), r * math.sin(a), 0.0])


def _circle_start_heading(start: np.ndarray, goal: np.ndarray, heading: str, rng: np.random.Generator) -> np.ndarray:
    """[N] start yaw (rad from north) of a circle episode; draws from ``rng`` only when ``heading`` is not ``goal``,
    so the paper's circle consumes the generator exactly as before."""
    if heading == "mixed":
        heading = ("goal", "common", "any")[int(rng.integers(3))]
    if heading == "common":
        return np.full(len(start), rng.uniform(-math.pi, math.pi))
    if heading == "any":
        return rng.uniform(-math.pi, math.pi, len(start))
    return _bearing_rad(start, goal)


def random_episode_config(config: ScenarioConfig, rng: np.random.Generator) -> ScenarioConfig:
    """The configuration one random episode is drawn with: at a density drawn log-uniformly within
    ``density_range`` when set (the draw is only made then, so other runs keep their episodes)."""
    if config.density_range is None:
        return config
    low, high = np.log(config.density_range)
    return dataclasses.replace(config, density=float(np.exp(rng.uniform(low, high))), density_range=None)


def sample_scenario(num_uavs: int, config: ScenarioConfig, rng: np.random.Generator) -> ScenarioSample:
    """Draw one episode of the configured scenario."""
    if config.name == "mixed":
        u = rng.random()  # one draw, as before obstacles existed: the paper's mixed training is unchanged
        if u < config.circle_fraction:
            return sample_circle(num_uavs, config, rng)
        if u < config.circle_fraction + config.obstacle_fraction:
            return sample_obstacles(num_uavs, obstacle_episode_config(config), rng)
        return sample_random(num_uavs, random_episode_config(config, rng), rng)
    if config.name == "random":
        return sample_random(num_uavs, random_episode_config(config, rng), rng)
    if config.name == "circle":
        return sample_circle(num_uavs, config, rng)
    if config.name == "obstacles":
        return sample_obstacles(num_uavs, config, rng)
    raise ValueError(f"unknown scenario {config.name!r}")


def obstacle_episode_config(config: ScenarioConfig) -> ScenarioConfig:
    """The configuration a mixed scenario's obstacles episodes are drawn with: at ``obstacle_density`` when set."""
    if config.obstacle_density is None:
        return config
    return dataclasses.replace(config, density=config.obstacle_density)


def max_obstacles(num_uavs: int, config: ScenarioConfig) -> tuple[int, int]:
    """(boxes, cylinders) rows an environment must hold per world for ``config``'s episodes."""
    if config.name == "obstacles":
        return obstacle_counts(num_uavs, config)
    if config.name == "mixed" and config.obstacle_fraction > 0:
        return obstacle_counts(num_uavs, obstacle_episode_config(config))
    return 0, 0
