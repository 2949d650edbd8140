"""Start and goal positions of the paper's test scenarios (paper IV.B); see :class:`ScenarioConfig`."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.frames import wrap_angle_rad
from sitl.sim.config import ScenarioConfig

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


def sample_random(num_uavs: int, config: ScenarioConfig, rng: np.random.Generator) -> ScenarioSample:
    """Random scenario: starts and goals uniformly in a box whose volume sets the density."""
    side, height = random_box_size(num_uavs, config.density, config.box_aspect)
    # NED box centred on the origin horizontally; z is down, so altitudes are negated.
    low = np.array([-side / 2, -side / 2, -(config.box_floor_alt_m + height)])
    high = np.array([side / 2, side / 2, -config.box_floor_alt_m])
    start = _spread_points(num_uavs, low, high, config.min_separation_m, rng)
    goal = _spread_points(num_uavs, low, high, config.min_separation_m, rng,
                          avoid=start, avoid_min=config.min_goal_distance_m)
    yaw = _bearing_rad(start, goal) + rng.uniform(-config.yaw_jitter_rad, config.yaw_jitter_rad, num_uavs)
    return ScenarioSample(start, goal, wrap_angle_rad(yaw))


def sample_circle(num_uavs: int, config: ScenarioConfig, rng: np.random.Generator) -> ScenarioSample:
    """Circle scenario: evenly spaced on a circle, goals antipodal, formation randomly rotated."""
    angles = rng.uniform(0, 2 * math.pi) + 2 * math.pi * np.arange(num_uavs) / num_uavs
    ring = np.stack([np.cos(angles), np.sin(angles), np.zeros(num_uavs)], axis=1) * config.circle_radius_m
    ring[:, 2] = -config.circle_alt_m
    goal = ring * np.array([-1.0, -1.0, 1.0])
    start = ring + rng.uniform(-config.circle_jitter_m, config.circle_jitter_m, ring.shape)
    return ScenarioSample(start, goal, _bearing_rad(start, goal))


def sample_scenario(num_uavs: int, config: ScenarioConfig, rng: np.random.Generator) -> ScenarioSample:
    """Draw one episode of the configured scenario."""
    if config.name == "mixed":
        draw_circle = rng.random() < config.circle_fraction
        return (sample_circle if draw_circle else sample_random)(num_uavs, config, rng)
    if config.name == "random":
        return sample_random(num_uavs, config, rng)
    if config.name == "circle":
        return sample_circle(num_uavs, config, rng)
    raise ValueError(f"unknown scenario {config.name!r}")
