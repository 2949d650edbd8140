"""Face the goal, then fly: turn in place towards a new goal and start the policy a fixed time after it arrived.

Why. Every policy here was trained on flights that start facing the goal (circles exactly, random scenes within
+-45 deg), and autopilots' SITL spawns every vehicle facing north. A swarm that starts on one heading flies the
circle of 8 at 0.930 (the bundle) and 0.793 (`policy_flown_distill.pt`) instead of >= 0.99, because the vehicles
that must turn first fall out of step with the ones already facing the centre and meet neighbours outside the
camera's view (docs/results.md "The circle's start heading"). Turning first and starting each vehicle when its own
turn ends is worse still (0.837 / 0.735): the starts become staggered.

What. For ``hold_s`` seconds after a new goal (or after engaging, whichever is later) the vehicle holds its position
and turns towards the goal; only then do the policy's commands go out. The simulator turns it at the policy's own
yaw-rate limit (a proportional law on the bearing, ``gain_per_s``, clipped: :func:`face_goal_commands`); the
companion sends the autopilot the same as a position target (the point where the turn started, the heading to the
goal), because PX4 SIH drifted by metres in altitude on a zero velocity and a yaw rate. The hold is the same for every vehicle, however far it has to
turn, so vehicles that got their goals together (one mission start) start flying together, each facing its goal:
the start the policy was trained on, with no communication. The policy keeps running during the hold (its frame
stack stays fresh); its commands are replaced, not skipped. The simulator's evaluation (``swarm_test --face-goal``)
and the companion (``companion --face-goal``) use these functions on the same inputs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.frames import ned_to_frd

#: Half a turn at the policy's 0.5 rad/s yaw limit (6.3 s) and ~1.7 s to settle: every vehicle faces its goal by then.
DEFAULT_FACE_GOAL_S = 8.0


@dataclass(frozen=True)
class FaceGoalSpec:
    """The turn before the flight (module docstring)."""

    hold_s: float = DEFAULT_FACE_GOAL_S  # from the goal (or engagement) to the policy's first command
    gain_per_s: float = 2.0  # yaw rate (rad/s) per rad of bearing to the goal, before the clip to the policy's limit

    def __post_init__(self) -> None:
        if not (math.isfinite(self.hold_s) and self.hold_s > 0.0):
            raise ValueError(f"face-goal hold must be a finite number of seconds > 0, got {self.hold_s}")
        if not (math.isfinite(self.gain_per_s) and self.gain_per_s > 0.0):
            raise ValueError(f"face-goal gain must be a finite number > 0, got {self.gain_per_s}")

    def describe(self) -> str:
        return f"turn in place to face each new goal, fly {self.hold_s:g} s after it arrived"


def goal_bearing_frd_rad(pos_ned: np.ndarray, yaw_rad: np.ndarray, goal_ned: np.ndarray) -> np.ndarray:
    """[M] bearing of each goal in its vehicle's heading frame (rad, positive to the right, 0 straight ahead)."""
    rel_frd = ned_to_frd(np.asarray(goal_ned, dtype=np.float64) - np.asarray(pos_ned, dtype=np.float64), yaw_rad)
    return np.arctan2(rel_frd[..., 1], rel_frd[..., 0])


def goal_heading_rad(pos_ned: np.ndarray, goal_ned: np.ndarray) -> float:
    """The heading (rad from north) that faces ``goal_ned`` from ``pos_ned`` (NED, [3] each)."""
    to_goal = np.asarray(goal_ned, dtype=np.float64) - np.asarray(pos_ned, dtype=np.float64)
    return math.atan2(to_goal[1], to_goal[0])


def face_goal_commands(pos_ned: np.ndarray, yaw_rad: np.ndarray, goal_ned: np.ndarray, yaw_rate_limit_rad_s: float,
                       spec: FaceGoalSpec = FaceGoalSpec()) -> np.ndarray:
    """[M, 3] commands ``(vel_fwd_m_s, vel_down_m_s, yaw_rate_rad_s)`` that hold position and turn towards the goal.

    Args:
        pos_ned, goal_ned: [M, 3] positions and goals in the local NED frame.
        yaw_rad: [M] headings from north.
        yaw_rate_limit_rad_s: the policy's yaw-rate bound (its action space), so the turn is one it could command.
    """
    bearing = goal_bearing_frd_rad(pos_ned, yaw_rad, goal_ned)
    out = np.zeros(np.shape(bearing) + (3,), dtype=np.float32)
    out[..., 2] = np.clip(spec.gain_per_s * bearing, -yaw_rate_limit_rad_s, yaw_rate_limit_rad_s)
    return out


#: The longest hold ``--face-goal`` accepts (a minute: longer is a typo, not a turn).
MAX_FACE_GOAL_S = 60.0


def parse_face_goal_s(text: str) -> float:
    """``--face-goal``'s value: seconds in (0, :data:`MAX_FACE_GOAL_S`] (argparse's one-line error otherwise)."""
    import argparse

    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (0.0 < value <= MAX_FACE_GOAL_S):
        raise argparse.ArgumentTypeError(f"--face-goal must be seconds in (0, {MAX_FACE_GOAL_S:g}], got {text!r}")
    return value


def add_face_goal_argument(parser, help: str) -> None:
    """``--face-goal [SECONDS]`` on an argparse parser or group: the hold in seconds (:data:`DEFAULT_FACE_GOAL_S`
    when given alone), None when absent (the companion's and the simulator's command lines share it)."""
    parser.add_argument("--face-goal", nargs="?", const=DEFAULT_FACE_GOAL_S, default=None, type=parse_face_goal_s,
                        metavar="SECONDS", help=help)
