"""Scripted controllers that act on the policy's own inputs (reference points for evaluation)."""

from __future__ import annotations

import numpy as np

from typing import TYPE_CHECKING

from companion.spec import DEFAULT_ACTION_SPEC, ActionSpec

if TYPE_CHECKING:  # the simulator is needed only to bind an actor to an environment
    from sitl.sim.env import SwarmEnv
    from sitl.sim.episodes import Actor


def straight_to_goal(state: np.ndarray, spec: ActionSpec = DEFAULT_ACTION_SPEC) -> np.ndarray:
    """The no-avoidance reference: turn towards the goal and fly straight at it.

    Uses only the goal in the body frame (``state[:, 0:3]``); slows down while the goal
    is off to the side so it turns onto the line instead of circling it. Returns
    actions [M, 3] within ``spec``.
    """
    goal_fwd, goal_right, goal_down = state[:, 0], state[:, 1], state[:, 2]
    bearing = np.arctan2(goal_right, goal_fwd)  # > 0: goal to the right
    horizontal = np.hypot(goal_fwd, goal_right)
    action = np.empty((state.shape[0], 3), dtype=np.float32)
    action[:, 0] = spec.high[0] * np.clip(np.cos(bearing), 0.0, 1.0) * np.clip(horizontal / 1.0, 0.0, 1.0)
    action[:, 1] = goal_down  # proportional in z, saturated by the clip below
    action[:, 2] = 2.0 * bearing
    return np.clip(action, spec.low_array(), spec.high_array())


def straight_actor(env: "SwarmEnv") -> "Actor":
    """The straight-to-goal reference as an :data:`sitl.sim.episodes.Actor` for ``env`` (an ``ActorFactory``)."""
    return lambda obs: straight_to_goal(obs.state, env.action_spec)
