"""The batched swarm environment: B independent worlds of N UAVs, stepped together as arrays.

This is the core every other interface builds on (the PettingZoo wrapper, training,
evaluation, the MAVLink vehicle). Arrays are flat over all UAVs of all worlds,
``M = B * N``, world-major: UAV ``i`` of world ``b`` is row ``b * N + i``.

Per step and per UAV (paper III.B):

* observation: ``depth`` float32 [M, 3, H, W] (planar metres, oldest frame first) and
  ``state`` float32 [M, 6] (:data:`companion.spec.STATE_NAMES`; then the remembered sector ranges
  with ``SimConfig.memory``), built with
  :mod:`companion.observation`, the code the onboard companion runs;
* action: float32 [M, 3] ``(vel_fwd_m_s, vel_down_m_s, yaw_rate_rad_s)``; non-finite
  actions raise, out-of-bounds ones are clipped to the bounds;
* reward: eqs. 2-4 (:mod:`sitl.sim.reward`).

A UAV's episode ends on arrival (terminated), on a collision with another UAV within 2R,
with the ground or with a static obstacle (terminated), or when its world reaches ``max_episode_steps``
(truncated). Afterwards it no longer acts: an arrived UAV hovers (or is removed, see
``SimConfig.arrived``), a crashed one is removed (or frozen in place, ``SimConfig.crashed``).
Only the rows in ``acting`` (before the step) produced a real transition. A world whose
UAVs are all done stays as it is until :meth:`SwarmEnv.reset_worlds` starts a new episode.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.governor import SpeedGovernor
from companion.observation import DepthFrameStack, RememberedDepth, build_state, clean_depth
from companion.spec import DEFAULT_ACTION_SPEC, ActionSpec
from sitl.sim.camera import DepthCamera, blind_speed_m_s
from sitl.sim.collision import (DISABLED_BOX, DISABLED_CYLINDER, ground_collisions, obstacle_collisions,
                                uav_uav_collisions)
from sitl.sim.config import SimConfig
from sitl.sim.dynamics import make_dynamics
from sitl.sim.metrics import Outcome, UAVRecord
from sitl.sim.reward import nearest_depth_m, step_reward
from sitl.sim.scenarios import max_obstacles, sample_scenario

# Outcome codes kept per UAV while an episode runs.
# The per-row outcome codes of ``SwarmEnv.outcome`` (see :class:`sitl.sim.metrics.Outcome`).
RUNNING, ARRIVED, COLLISION_UAV, COLLISION_GROUND, TIMEOUT, COLLISION_OBSTACLE = Outcome


@dataclass
class Observation:
    """The policy's input for every UAV."""

    depth: np.ndarray  # float32 [M, frames, H, W], metres
    state: np.ndarray  # float32 [M, 6] (+ the remembered sector ranges with SimConfig.memory)


class SwarmEnv:
    """B worlds of N UAVs with depth cameras, stepped as one batch.

    Args:
        config: the worlds' configuration.
        seed: seed of the environment's random generator (scenarios and camera noise).
        boxes, cylinders: optional static obstacles per world (see :mod:`sitl.sim.camera`), in
            every episode; the ``obstacles`` scenario adds its own, drawn per episode. UAVs
            collide with both (:func:`sitl.sim.collision.obstacle_collisions`).
    """

    def __init__(self, config: SimConfig, seed: int | None = None,
                 boxes: np.ndarray | None = None, cylinders: np.ndarray | None = None) -> None:
        self.config = config
        self.action_spec: ActionSpec = DEFAULT_ACTION_SPEC
        self.num_worlds = config.num_worlds
        self.uavs_per_world = config.num_uavs
        self.num_agents = config.num_worlds * config.num_uavs
        self.rng = np.random.default_rng(seed)
        self.dynamics = make_dynamics(config.dynamics, self.num_agents)
        self.camera = DepthCamera(config.camera, config.camera_supersample, config.body)
        self.frames = DepthFrameStack(self.num_agents, config.camera)
        # What each UAV's companion remembers of its camera (None: the paper's observation).
        self.memory = RememberedDepth(self.num_agents, config.camera, config.memory) if config.memory else None
        # Per-world obstacle arrays: the fixed ones given here, then room for the scenario's own
        # (rows DISABLED_* until an episode places them).
        b = config.num_worlds
        fixed_boxes = np.zeros((b, 0, 6)) if boxes is None else np.asarray(boxes, dtype=np.float64)
        fixed_cylinders = np.zeros((b, 0, 5)) if cylinders is None else np.asarray(cylinders, dtype=np.float64)
        if fixed_boxes.shape[0] != b or fixed_cylinders.shape[0] != b:
            raise ValueError(f"boxes and cylinders need one (possibly empty) row per world ({b})")
        self._fixed_obstacles = (fixed_boxes.shape[1], fixed_cylinders.shape[1])
        k_boxes, k_cylinders = max_obstacles(config.num_uavs, config.scenario)
        self.boxes = np.concatenate([fixed_boxes, np.tile(DISABLED_BOX, (b, k_boxes, 1))], axis=1)
        self.cylinders = np.concatenate([fixed_cylinders, np.tile(DISABLED_CYLINDER, (b, k_cylinders, 1))], axis=1)
        # Each camera's mount pitch (rad, positive up), drawn per episode (SimConfig.mount_pitch_jitter_deg).
        self.mount_pitch_rad = np.full(self.num_agents, config.camera.mount_pitch_rad)
        self.nearest_object_m = np.full(self.num_agents, config.camera.max_range_m)  # d_min without the ground
        # The corridor price's judge (RewardConfig.w_corridor): the companion's governor, default settings.
        self._corridor_governor = SpeedGovernor(config.camera) if config.reward.w_corridor else None

        m = self.num_agents
        self.goal_ned = np.zeros((m, 3))
        self.start_ned = np.zeros((m, 3))
        self.acting = np.zeros(m, dtype=bool)  # still flying its episode, takes actions
        self.present = np.zeros(m, dtype=bool)  # physically in the world (visible, collidable)
        self.outcome = np.full(m, RUNNING, dtype=np.int8)
        self.path_length_m = np.zeros(m)
        self.flight_steps = np.zeros(m, dtype=np.int64)
        self.world_steps = np.zeros(self.num_worlds, dtype=np.int64)
        self.world_episode = np.full(self.num_worlds, -1, dtype=np.int64)
        self.world_is_circle = np.zeros(self.num_worlds, dtype=bool)  # [B] the episode is a circle
        self._episodes_started = 0
        self._paths: list[list[np.ndarray]] = [[] for _ in range(m)]
        self.completed: list[UAVRecord] = []  # records of finished episodes, in order

    # ------------------------------------------------------------------ properties
    @property
    def world_done(self) -> np.ndarray:
        """[B] bool: worlds in which no UAV acts any more."""
        return ~self.acting.reshape(self.num_worlds, self.uavs_per_world).any(axis=1)

    @property
    def world_has_obstacles(self) -> np.ndarray:
        """[B] bool: worlds with at least one box or cylinder in place (rows that are not padding)."""
        placed_boxes = (self.boxes != DISABLED_BOX).any(axis=2).any(axis=1)
        return placed_boxes | (self.cylinders != DISABLED_CYLINDER).any(axis=2).any(axis=1)

    def observation(self) -> Observation:
        """The current observation of every UAV (a fresh state array; depth is a view for consecutive frames)."""
        d = self.dynamics
        state = build_state(d.pos_ned, d.yaw_rad, d.vel_ned, d.yaw_rate_rad_s, self.goal_ned)
        if self.memory is not None:
            state = np.concatenate([state, self.memory.sector_ranges(d.pos_ned, d.yaw_rad)], axis=1)
        return Observation(self.frames.frames, state)

    def distance_to_goal_m(self) -> np.ndarray:
        return np.linalg.norm(self.goal_ned - self.dynamics.pos_ned, axis=1)

    # ------------------------------------------------------------------ reset
    def reset(self, seed: int | None = None) -> Observation:
        """Start a new episode in every world."""
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        self.completed = []
        self._episodes_started = 0
        self.world_episode[:] = -1
        return self.reset_worlds(np.ones(self.num_worlds, dtype=bool))

    def reset_worlds(self, worlds: np.ndarray) -> Observation:
        """Start a new episode in the worlds where ``worlds`` ([B] bool) is true.

        Finished episodes of those worlds are recorded in :attr:`completed` first.
        """
        n = self.uavs_per_world
        for b in np.flatnonzero(worlds):
            rows = np.arange(b * n, (b + 1) * n)
            self._record_world(b)
            sample = sample_scenario(n, self.config.scenario, self.rng)
            self.dynamics.reset(rows, sample.start_ned, sample.yaw_rad)
            if self.config.dynamics_randomization is not None:
                self.dynamics.randomize(rows, self.config.dynamics_randomization, self.rng)
            self._place_obstacles(b, sample.boxes, sample.cylinders)
            self.world_is_circle[b] = sample.circle
            if self.config.mount_pitch_jitter_deg > 0:
                jitter = np.radians(self.config.mount_pitch_jitter_deg)
                self.mount_pitch_rad[rows] = self.config.camera.mount_pitch_rad + self.rng.uniform(-jitter, jitter, n)
            self.start_ned[rows] = sample.start_ned
            self.goal_ned[rows] = sample.goal_ned
            self.acting[rows] = True
            self.present[rows] = True
            self.outcome[rows] = RUNNING
            self.path_length_m[rows] = 0.0
            self.flight_steps[rows] = 0
            self.world_steps[b] = 0
            self.world_episode[b] = self._episodes_started
            self._episodes_started += 1
            if self.config.record_paths:
                for r in rows:
                    self._paths[r] = [sample.start_ned[r - b * n].copy()]
        rows = np.flatnonzero(np.repeat(worlds, n))
        depth = self._render()
        self.frames.reset(depth[rows], rows)
        if self.memory is not None:
            self.memory.reset(depth[rows], self.dynamics.pos_ned[rows], self.dynamics.yaw_rad[rows], rows)
        return self.observation()

    # ------------------------------------------------------------------ step
    def step(self, action: np.ndarray) -> tuple[Observation, np.ndarray, np.ndarray, np.ndarray, dict]:
        """Advance every world by one control period.

        Args:
            action: [M, 3] commands; rows of UAVs that no longer act are ignored.

        Returns:
            ``(obs, reward [M], terminated [M], truncated [M], info)``; ``info["acting"]``
            is the [M] mask of UAVs that acted in this step (the rows that are real
            transitions), ``info["outcome"]`` the [M] outcome codes.
        """
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (self.num_agents, 3):
            raise ValueError(f"action must have shape ({self.num_agents}, 3), got {action.shape}")
        acting = self.acting.copy()
        if not np.all(np.isfinite(action[acting])):
            raise ValueError("action contains a non-finite value (NaN or inf) for an acting UAV")
        cmd = np.zeros_like(action)
        cmd[acting] = self.action_spec.validate(action[acting])  # documented clip to the bounds
        cfg = self.config
        dynamics = self.dynamics

        prev_pos = dynamics.pos_ned.copy()
        prev_dist = self.distance_to_goal_m()
        movable = self.present & ~((self.outcome != RUNNING) & (self.outcome != ARRIVED))  # frozen wrecks stay
        dynamics.step(cmd, cfg.control_period_s, movable)
        step_len = np.linalg.norm(dynamics.pos_ned - prev_pos, axis=1)
        self.path_length_m[acting] += step_len[acting]
        self.flight_steps[acting] += 1
        self.world_steps += ~self.world_done
        if cfg.record_paths:
            for r in np.flatnonzero(acting):
                self._paths[r].append(dynamics.pos_ned[r].copy())

        hit_uav = uav_uav_collisions(prev_pos, dynamics.pos_ned, self.present, self.uavs_per_world,
                                     cfg.collision_radius_m) & acting
        hit_ground = ground_collisions(dynamics.pos_ned, cfg.collision_radius_m) & acting
        hit_obstacle = obstacle_collisions(prev_pos, dynamics.pos_ned, self.boxes, self.cylinders,
                                           self.uavs_per_world, cfg.collision_radius_m) & acting
        collided = hit_uav | hit_ground | hit_obstacle
        dist = self.distance_to_goal_m()
        arrived = (dist < cfg.reward.arrival_radius_m) & acting & ~collided

        self.outcome[hit_obstacle] = COLLISION_OBSTACLE
        self.outcome[hit_ground] = COLLISION_GROUND
        self.outcome[hit_uav] = COLLISION_UAV
        self.outcome[arrived] = ARRIVED
        timed_out = acting & ~collided & ~arrived & np.repeat(self.world_steps >= cfg.max_episode_steps, self.uavs_per_world)
        self.outcome[timed_out] = TIMEOUT
        self.acting &= ~(collided | arrived | timed_out)
        if cfg.crashed == "remove":
            self.present &= ~collided
        if cfg.arrived == "remove":
            self.present &= ~arrived

        depth = self._render()
        self.frames.push(depth)
        if self.memory is not None:
            self.memory.push(depth, dynamics.pos_ned, dynamics.yaw_rad)
        d_min = nearest_depth_m(depth) if cfg.reward.avoid_counts_ground else self.nearest_object_m
        blind = (blind_speed_m_s(dynamics.vel_ned, dynamics.yaw_rad, self.mount_pitch_rad, cfg.camera)
                 if cfg.reward.w_blind else None)
        excess = None
        if cfg.reward.w_corridor:  # on the frame the policy will see next, as the governor would judge it
            excess = np.maximum(cmd[:, 0] - self._corridor_governor.forward_limit(depth)[1], 0.0)
        reward = step_reward(prev_dist, dist, arrived, collided, d_min, cfg.reward, hit_uav, blind, excess)
        reward = np.where(acting, reward, 0.0).astype(np.float32)
        terminated = collided | arrived
        info = {"acting": acting, "outcome": self.outcome.copy(), "collided": collided, "arrived": arrived}
        return self.observation(), reward, terminated, timed_out, info

    # ------------------------------------------------------------------ internals
    def _render(self) -> np.ndarray:
        """The policy's view of every camera now: render, sensor noise, then the companion's conversion.

        Also updates :attr:`nearest_object_m` (the kernel's nearest non-ground surface per camera,
        noise-free: the reward's d_min when the ground does not count).
        """
        cfg = self.config
        depth, self.nearest_object_m = self.camera.render_with_objects(
            self.dynamics.pos_ned, self.dynamics.yaw_rad, self.uavs_per_world, visible=self.present,
            boxes=self.boxes, cylinders=self.cylinders, pitch_rad=self.mount_pitch_rad)
        if cfg.camera_noise is not None:
            depth = cfg.camera_noise.apply(depth, cfg.camera.max_range_m, self.rng)  # raw: invalid pixels read 0
        return clean_depth(depth, cfg.camera.max_range_m)  # exactly what the companion feeds the policy

    def _place_obstacles(self, b: int, boxes: np.ndarray, cylinders: np.ndarray) -> None:
        """World b's scenario obstacles for the new episode (the fixed ones stay; unused rows disabled)."""
        kb, kc = self._fixed_obstacles
        if len(boxes) > self.boxes.shape[1] - kb or len(cylinders) > self.cylinders.shape[1] - kc:
            raise ValueError("the scenario placed more obstacles than the environment holds")
        self.boxes[b, kb:] = DISABLED_BOX
        self.boxes[b, kb:kb + len(boxes)] = boxes
        self.cylinders[b, kc:] = DISABLED_CYLINDER
        self.cylinders[b, kc:kc + len(cylinders)] = cylinders

    def _record_world(self, b: int) -> None:
        """Append the per-UAV records of world b's finished episode to :attr:`completed`."""
        if self.world_episode[b] < 0:
            return
        n = self.uavs_per_world
        dt = self.config.control_period_s
        if np.any(self.outcome[b * n:(b + 1) * n] == RUNNING):
            return  # episode abandoned by an early reset: it has no result
        for i in range(n):
            r = b * n + i
            outcome = self.outcome[r]
            self.completed.append(UAVRecord(
                episode=int(self.world_episode[b]), uav=i,
                start_ned=self.start_ned[r].tolist(), goal_ned=self.goal_ned[r].tolist(),
                outcome=Outcome(int(outcome)).code,
                path_length_m=float(self.path_length_m[r]),
                straight_distance_m=float(np.linalg.norm(self.goal_ned[r] - self.start_ned[r])),
                duration_s=float(self.flight_steps[r] * dt),
                path_ned=np.asarray(self._paths[r]).round(3).tolist() if self.config.record_paths else None,
            ))

    def fly_episodes(self, obs: Observation, act, episodes: int, observer=None, on_done=None) -> list[UAVRecord]:
        """Fly ``episodes`` episodes from the just-reset ``obs``: ``act(obs) -> actions [M, 3]``.

        The worlds fly in parallel; a world that finishes starts the next episode while
        episodes remain, so episode ``k`` is always the ``k``-th scenario drawn whatever the
        number of worlds, and slow episodes do not hold back a whole batch. ``observer``
        (``before_step(env)``, ``after_step(env, info)``) is called around every step;
        ``on_done(count)`` whenever ``count`` more episodes have ended. Returns every record.
        """
        started = self.num_worlds
        was_done = np.zeros(self.num_worlds, dtype=bool)
        while True:
            done = self.world_done
            if on_done is not None and (done & ~was_done).any():
                on_done(int(np.count_nonzero(done & ~was_done)))
            was_done = done.copy()
            if done.any() and started < episodes:
                restart = np.zeros(self.num_worlds, dtype=bool)
                restart[np.flatnonzero(done)[: episodes - started]] = True
                started += int(restart.sum())
                obs = self.reset_worlds(restart)
                was_done &= ~restart
                done = self.world_done
            if done.all():
                return self.finish()
            if observer is not None:
                observer.before_step(self)
            obs, _, _, _, info = self.step(act(obs))
            if observer is not None:
                observer.after_step(self, info)

    def finish(self) -> list[UAVRecord]:
        """Record every world whose episode is over and return all records so far."""
        for b in np.flatnonzero(self.world_done):
            self._record_world(b)
            self.world_episode[b] = -1  # recorded once
        return self.completed
