"""Evaluation metrics of paper IV.B: success rate, SPL (eq. 9), extra distance, average speed."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np


class Outcome(IntEnum):
    """How a UAV's episode ends: the simulator's per-row code and, as :attr:`code`, the name
    records, logs and the simulated vehicles' crash events carry."""

    RUNNING = 0
    ARRIVED = 1
    COLLISION_UAV = 2
    COLLISION_GROUND = 3
    TIMEOUT = 4
    COLLISION_OBSTACLE = 5  # a static obstacle (pole, tree, box) of the ``obstacles`` scene

    @property
    def code(self) -> str:
        """``"arrived"``, ``"collision_uav"``, ``"collision_ground"``, ``"timeout"`` or ``"collision_obstacle"``."""
        return self.name.lower()


#: The names of the outcomes an episode ends with, in the order the metrics report them.
OUTCOMES = tuple(o.code for o in Outcome if o is not Outcome.RUNNING)


@dataclass
class UAVRecord:
    """What one UAV did in one episode."""

    episode: int  # global episode index (world resets are numbered in order)
    uav: int  # index of the UAV in its world
    start_ned: list[float]
    goal_ned: list[float]
    outcome: str  # one of OUTCOMES
    path_length_m: float  # p: length of the path actually flown until the UAV's episode ended
    straight_distance_m: float  # l: start-to-goal distance (shortest path in free space)
    duration_s: float  # flight time until arrival, collision or timeout
    path_ned: list[list[float]] | None = field(default=None, repr=False)  # positions every control step

    @property
    def success(self) -> bool:
        return self.outcome == "arrived"


def spl(records: list[UAVRecord]) -> float:
    """Success weighted by Path Length, eq. 9: mean over UAVs and episodes of S * l / max(p, l)."""
    if not records:
        return float("nan")
    terms = [r.success * r.straight_distance_m / max(r.path_length_m, r.straight_distance_m) for r in records]
    return float(np.mean(terms))


def success_half_width(records: list[UAVRecord], z: float = 1.96) -> float:
    """Half-width of the ~95 % confidence interval of the success rate, clustered by episode.

    UAVs of one episode share its geometry (and collide in pairs), so they are not
    independent trials: the standard error is the ratio estimator's over episodes,
    ``sqrt(E / (E - 1) * sum_e (s_e - p * n_e)^2) / N`` for episodes ``e`` with ``n_e`` UAVs
    and ``s_e`` successes (``N`` UAVs in all). NaN with fewer than two episodes.
    """
    by_episode: dict[int, list[int]] = {}
    for r in records:
        by_episode.setdefault(r.episode, []).append(r.success)
    if len(by_episode) < 2:
        return float("nan")
    n = np.array([len(v) for v in by_episode.values()], dtype=float)
    s = np.array([sum(v) for v in by_episode.values()], dtype=float)
    rate, count = s.sum() / n.sum(), len(n)
    return float(z * np.sqrt(count / (count - 1) * np.sum((s - rate * n) ** 2)) / n.sum())


def _mean_std(values: list[float]) -> dict[str, float]:
    if not values:
        return {"mean": float("nan"), "std": float("nan")}
    return {"mean": float(np.mean(values)), "std": float(np.std(values))}


def summarize(records: list[UAVRecord]) -> dict:
    """Aggregate per-UAV records into the paper's metrics (mean/std over UAVs and episodes).

    * success_rate: fraction of UAVs that reached their goal without a collision in time,
      and ``success_ci95_half_width`` (:func:`success_half_width`);
    * spl: eq. 9;
    * extra_distance_m: p - l over the UAVs that succeeded (a failed flight has no
      comparable path);
    * average_speed_m_s: p / flight time over all UAVs ("the average speed of all UAVs");
    * rate of each outcome (collision with a UAV, with the ground, timeout, with a static
      obstacle), which add up to 1 - success_rate.
    """
    count = len(records)
    successes = [r for r in records if r.success]
    summary: dict = {
        "uav_episodes": count,
        "episodes": len({r.episode for r in records}),
        "success_rate": len(successes) / count if count else float("nan"),
        "success_ci95_half_width": success_half_width(records),
        "spl": spl(records),
        "extra_distance_m": _mean_std([r.path_length_m - r.straight_distance_m for r in successes]),
        "average_speed_m_s": _mean_std([r.path_length_m / r.duration_s for r in records if r.duration_s > 0]),
    }
    for outcome in OUTCOMES[1:]:
        summary[f"{outcome}_rate"] = sum(r.outcome == outcome for r in records) / count if count else float("nan")
    return summary


#: Goal altitude bins (m above the ground) of :func:`success_by_goal_altitude`: low flight, the
#: middle, and the paper's geometry (which starts at a 6 m floor).
GOAL_ALTITUDE_BINS_M: tuple[tuple[str, float, float], ...] = (("below 3 m", 0.0, 3.0), ("3-6 m", 3.0, 6.0),
                                                                ("above 6 m", 6.0, float("inf")))


def success_by_goal_altitude(records: list[UAVRecord]) -> dict[str, dict]:
    """Success split by the goal's altitude (:data:`GOAL_ALTITUDE_BINS_M`): per bin the UAV-episodes,
    the success rate and its clustered 95 % half-width, and the timeout rate (NaN for an empty bin)."""
    out = {}
    for label, lo, hi in GOAL_ALTITUDE_BINS_M:
        chosen = [r for r in records if lo <= -r.goal_ned[2] < hi]
        n = len(chosen)
        out[label] = {
            "uav_episodes": n,
            "success_rate": sum(r.success for r in chosen) / n if n else float("nan"),
            "success_ci95_half_width": success_half_width(chosen),
            "timeout_rate": sum(r.outcome == "timeout" for r in chosen) / n if n else float("nan"),
        }
    return out
