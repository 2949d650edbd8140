"""The one evaluation engine: fly N episodes of a controller and return its per-UAV records.

Everything that flies a controller in the batched simulator for a result — the trainer's
validation and final evaluation, ``swarm_test`` (and its ``paper`` reproduction),
``sitl.rescore`` and ``sitl.collision_anatomy`` — goes through :func:`run_episodes`, and
every controller is an :data:`Actor`: ``act(obs) -> actions [M, 3]``, built for one
environment by an :data:`ActorFactory` (policy files, training agents, the straight-to-goal
and ORCA references each have one).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from companion.face_goal import FaceGoalSpec, face_goal_commands
from companion.governor import GovernorSpec, SpeedGovernor
from sitl.sim.config import SimConfig
from sitl.sim.env import Observation, SwarmEnv
from sitl.sim.metrics import UAVRecord

#: A controller bound to one environment: the observation of every UAV -> float32 actions [M, 3]
#: ``(vel_fwd_m_s, vel_down_m_s, yaw_rate_rad_s)``; rows of UAVs that no longer act are ignored.
Actor = Callable[[Observation], np.ndarray]
#: Builds the controller's :data:`Actor` for an environment that was just reset (it may read the
#: environment's state each step, as the privileged ORCA reference does).
ActorFactory = Callable[[SwarmEnv], Actor]


class StepObserver(Protocol):
    """Sees every control step of an evaluation (for analyses that need more than the records)."""

    def before_step(self, env: SwarmEnv) -> None: ...

    def after_step(self, env: SwarmEnv, info: dict) -> None: ...


class ScenarioError(ValueError):
    """The environment cannot draw the configured scenario (e.g. a density too high to place the UAVs)."""


def depth_state_actor(act: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> ActorFactory:
    """The factory of a controller written as ``act(depth, state) -> actions`` over all rows.

    E.g. a training agent's deterministic actor or a loaded policy's ``act``.
    """
    return lambda env: (lambda obs: act(obs.depth, obs.state))


class SwarmGovernor:
    """The companion's speed governor (:mod:`companion.governor`) on the commands of every UAV of one
    environment, on each UAV's newest depth frame, as the companion applies it after the policy.

    Each UAV keeps its own turn in progress; a UAV whose flight has just started has none.
    """

    def __init__(self, env: SwarmEnv, spec: GovernorSpec) -> None:
        self.env = env
        self.governor = SpeedGovernor(env.config.camera, spec)
        self.turning = np.zeros(env.num_agents, dtype=np.float32)  # +1 right, -1 left, 0 none

    def __call__(self, obs: Observation, commands: np.ndarray) -> np.ndarray:
        """The governed commands [M, 3] (a copy); rows of UAVs that no longer act are left as they are."""
        out = np.array(commands, dtype=np.float32)  # a copy: the caller may reuse its array
        rows = np.flatnonzero(self.env.acting)
        if rows.size:
            self.turning[rows[self.env.flight_steps[rows] == 0]] = 0.0
            out[rows], _, _, self.turning[rows] = self.governor.apply(obs.depth[rows, -1], out[rows],
                                                                      self.turning[rows])
        return out


def governed_actor(actor: Actor, spec: GovernorSpec, env: SwarmEnv) -> Actor:
    """``actor`` with the speed governor ``spec`` after it (:class:`SwarmGovernor`)."""
    govern = SwarmGovernor(env, spec)
    return lambda obs: govern(obs, actor(obs))


def face_goal_actor(actor: Actor, spec: FaceGoalSpec, env: SwarmEnv, yaw_rate_limit_rad_s: float) -> Actor:
    """``actor`` whose commands wait ``spec.hold_s`` from each UAV's start while it turns in place to face its goal
    (:mod:`companion.face_goal`, as ``companion --face-goal`` does from the goal's arrival). The actor still runs
    every step; only its commands are replaced. Every UAV of a world starts together, so they fly together."""
    hold_steps = int(np.ceil(spec.hold_s / env.config.control_period_s - 1e-9))

    def act(obs: Observation) -> np.ndarray:
        out = np.array(actor(obs), dtype=np.float32)  # a copy: the actor may reuse its array
        rows = np.flatnonzero(env.acting & (env.flight_steps < hold_steps))
        if rows.size:
            d = env.dynamics
            out[rows] = face_goal_commands(d.pos_ned[rows], d.yaw_rad[rows], env.goal_ned[rows],
                                           yaw_rate_limit_rad_s, spec)
        return out

    return act


def run_episodes(make_actor: ActorFactory, sim_config: SimConfig, seed: int, episodes: int,
                 observer: StepObserver | None = None,
                 on_done: Callable[[int], object] | None = None) -> list[UAVRecord]:
    """Fly ``episodes`` episodes of ``make_actor``'s controller, ``sim_config.num_worlds`` at a time.

    The environment is seeded with ``seed``: episode ``k`` is the ``k``-th scenario drawn from
    it whatever the number of worlds (``SwarmEnv.fly_episodes``), so every controller flown
    with the same seed and scenario meets the same episodes (with perfect depth). ``observer``
    is called around every step, ``on_done(count)`` when ``count`` more episodes have ended.

    Raises:
        ScenarioError: the scenario cannot be built (e.g. a density too high to place the UAVs).
    """
    env = SwarmEnv(sim_config, seed=seed)
    try:
        obs = env.reset()
    except ValueError as err:
        raise ScenarioError(str(err)) from None
    return env.fly_episodes(obs, make_actor(env), episodes, observer, on_done)
