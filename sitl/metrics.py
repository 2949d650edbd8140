"""Evaluation metrics of paper IV.B: success rate, SPL (eq. 9), extra distance, average speed."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

OUTCOMES = ("arrived", "collision_uav", "collision_ground", "timeout")


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


def _mean_std(values: list[float]) -> dict[str, float]:
    if not values:
        return {"mean": float("nan"), "std": float("nan")}
    return {"mean": float(np.mean(values)), "std": float(np.std(values))}


def summarize(records: list[UAVRecord]) -> dict:
    """Aggregate per-UAV records into the paper's metrics (mean/std over UAVs and episodes).

    * success_rate: fraction of UAVs that reached their goal without a collision in time;
    * spl: eq. 9;
    * extra_distance_m: p - l over the UAVs that succeeded (a failed flight has no
      comparable path);
    * average_speed_m_s: p / flight time over all UAVs ("the average speed of all UAVs");
    * rate of each outcome (collision with a UAV, with the ground, timeout), which add up
      to 1 - success_rate.
    """
    count = len(records)
    successes = [r for r in records if r.success]
    summary: dict = {
        "uav_episodes": count,
        "episodes": len({r.episode for r in records}),
        "success_rate": len(successes) / count if count else float("nan"),
        "spl": spl(records),
        "extra_distance_m": _mean_std([r.path_length_m - r.straight_distance_m for r in successes]),
        "average_speed_m_s": _mean_std([r.path_length_m / r.duration_s for r in records if r.duration_s > 0]),
    }
    for outcome in OUTCOMES[1:]:
        summary[f"{outcome}_rate"] = sum(r.outcome == outcome for r in records) / count if count else float("nan")
    return summary
