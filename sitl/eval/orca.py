"""ORCA in 3D as a privileged reference controller (``--policy orca``).

Optimal Reciprocal Collision Avoidance (van den Berg et al., 2011) computed with RVO2-3D
through its PyPI binding ``jt-pyrvo23d`` (module ``rvo23d``, the C++ library of Snape et
al.). Unlike the learned policy, which sees only its depth camera, ORCA here knows the
true positions and velocities of every UAV in its world: it is the classical reference
the policy is measured against, not a competitor under the same sensing.

ORCA assumes holonomic agents that reach any velocity within ``max_speed`` at once; our
UAVs only fly forward along their heading, turn at up to 0.5 rad/s, climb at up to
0.5 m/s and track commands with a lag. The velocity ORCA chooses is therefore mapped onto
the policy's command space (:func:`velocity_to_action`) and the gap is absorbed by a
radius margin above the collision radius R, as a real deployment of ORCA on multicopters
would do.

RVO2-3D has no static obstacles; with ``see_obstacles`` (``--policy orca``, and the ``distill``
method's teacher) each UAV's nearest point on a box or pole stands in its world as a static agent of
radius ``obstacle_point_radius_m``, which every UAV avoids. Since a static agent never does its half of
a reciprocal avoidance, the point is inflated rather than trusted to share the work.

``orca-fov`` (:func:`orca_actor` with ``camera_limited=True``) is the same ORCA limited to what the UAV's own camera
covers: each UAV avoids only the UAVs whose centres are inside its camera frustum (field of
view and range, :mod:`sitl.eval.visibility`) at that step, and the others no longer
reciprocate reliably since they may not see it. It still knows those UAVs' exact positions
and velocities, so it bounds what avoidance can do with a forward camera's *view*, not with
its pixels: the gap between ``orca`` and ``orca-fov`` is what the field of view alone costs.

``orca-fov-right`` adds a right-of-way convention to ``orca-fov`` (``OrcaParams.right_hand_deg``): whenever a
UAV in view is ahead and closing, the preferred velocity turns to the right. In a circle every UAV meets the
others head-on at once, a symmetric meeting that plain ORCA only resolves with reciprocity the camera cannot
give; with the rule every UAV veers the same way and the swarm flies a roundabout. The rule is a function of
the view, so a camera policy can imitate it (``python -m sitl.train --circle-teacher-right``).

``orca-fov-memory`` gives ``orca-fov`` a perfect memory (``OrcaParams.memory_s``): a UAV it has seen once stays
known, with its true state, for the rest of the episode (perfect tracking after one sighting: more than any
camera pipeline delivers). ``orca-fov-look-around`` adds, at an episode's first step, every UAV in the ring all
around it that the camera's vertical view and range cover (``OrcaParams.look_around``): a take-off that turns
once around before it moves, at no cost in time. The two bound what memory, and memory plus a look at the
start, can add to a forward camera's view (docs/results.md "What a forward D435 allows").
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from companion.frames import ned_to_frd
from companion.spec import DEFAULT_ACTION_SPEC, ActionSpec, CameraSpec
from sitl.eval.visibility import camera_fov_rad, in_view, in_view_all_around
from sitl.sim.collision import nearest_obstacle_points


@dataclass(frozen=True)
class OrcaParams:
    """ORCA settings and the mapping of its velocity to body-frame commands.

    The defaults were chosen on the circle (N = 8) and medium random scenes with the
    kinematic dynamics (docs/evaluation.md): a 0.2 m margin over R = 0.3 m covers the
    UAV's turn-rate limit and velocity lag; a 2.5 s horizon reacts early enough for a
    0.5 rad/s turn without freezing the swarm.
    """

    radius_margin_m: float = 0.2  # ORCA radius = collision radius R + margin
    time_horizon_s: float = 2.5  # look-ahead for other UAVs
    neighbor_dist_m: float = 10.0  # only UAVs this close are considered
    max_neighbors: int = 16
    max_speed_m_s: float = 2.0  # ORCA's speed sphere = the forward speed limit
    goal_slowdown_s: float = 1.0  # preferred speed = min(max_speed, distance / this): no overshoot
    yaw_gain: float = 2.0  # yaw rate = gain x bearing of the new velocity (rad/s per rad)
    #: ``see_obstacles``: the radius of the static agent standing at each UAV's nearest obstacle point.
    #: ORCA shares an avoidance half and half, and a static agent never does its half, so the point
    #: is inflated instead: the UAV then keeps about R + margin + this / 2 from the surface.
    obstacle_point_radius_m: float = 0.4
    #: Right-of-way convention: turn the preferred velocity this far to the right (seen from above) while a
    #: known UAV is ahead of it and closing; 0 = plain ORCA. 40 deg was chosen on the flown circle of 8
    #: (evaluation seed 900, 200 episodes: 20 deg 0.966, 30-60 deg 1.000; docs/training.md).
    right_hand_deg: float = 0.0
    #: Camera-limited only: a UAV seen within the last this many seconds stays known (its true state, as if
    #: tracked perfectly after the sighting); 0 = only what is in view now, inf = since the episode began.
    memory_s: float = 0.0
    #: Camera-limited only: at an episode's first step each UAV also knows every UAV in the ring all around it
    #: that its camera's vertical view and range cover (a take-off that turns once around before it moves).
    look_around: bool = False

    def __post_init__(self) -> None:
        if not 0.0 <= self.right_hand_deg <= 90.0:
            raise ValueError(f"right_hand_deg must be in [0, 90], got {self.right_hand_deg}")
        if math.isnan(self.memory_s) or self.memory_s < 0.0:
            raise ValueError(f"memory_s must be >= 0 (inf: the whole episode), got {self.memory_s}")

    def to_dict(self) -> dict:
        """The settings for JSON (an infinite memory as null: JSON has no infinity)."""
        return {k: (None if isinstance(v, float) and math.isinf(v) else v) for k, v in dataclasses.asdict(self).items()}

    @property
    def remembers(self) -> bool:
        """Whether a camera-limited UAV knows more than what is in its view at this step."""
        return self.memory_s > 0.0 or self.look_around


#: ``orca-fov-right``'s settings: orca-fov with the right-of-way convention.
RIGHT_HAND_PARAMS = OrcaParams(right_hand_deg=40.0)
#: ``orca-fov-right80``: the same convention turning twice as far, a wider roundabout. Chosen on circles whose starts
#: are scattered within 3 m of the ring (circle-n8-scatter, evaluation seed 900, 200 episodes: 40 deg 0.822,
#: 70 / 80 / 90 deg 0.956 / 0.965 / 0.969; the symmetric circle 1.000 at every angle; docs/training.md).
WIDE_RIGHT_HAND_PARAMS = OrcaParams(right_hand_deg=80.0)
#: ``orca-fov-memory``'s and ``orca-fov-look-around``'s settings: orca-fov that never forgets a UAV it saw.
MEMORY_PARAMS = OrcaParams(memory_s=math.inf)
LOOK_AROUND_PARAMS = OrcaParams(memory_s=math.inf, look_around=True)


#: The ORCA references by ``--policy`` name: (params, camera_limited, see_obstacles). The one list of them
#: (``sitl.eval.methods.ORCA_BASELINES`` is its keys).
ORCA_REFERENCES: dict[str, tuple[OrcaParams, bool, bool]] = {
    "orca": (OrcaParams(), False, True),
    "orca-fov": (OrcaParams(), True, False),
    "orca-fov-right": (RIGHT_HAND_PARAMS, True, False),
    "orca-fov-right80": (WIDE_RIGHT_HAND_PARAMS, True, False),
    "orca-fov-memory": (MEMORY_PARAMS, True, False),
    "orca-fov-look-around": (LOOK_AROUND_PARAMS, True, False),
}


def baseline_orca(name: str) -> tuple[OrcaParams, bool, bool]:
    """The reference ``name`` (a key of :data:`ORCA_REFERENCES`) as (params, camera_limited, see_obstacles)."""
    try:
        return ORCA_REFERENCES[name]
    except KeyError:
        raise ValueError(f"unknown ORCA reference {name!r}") from None


def _import_rvo():
    """Import the RVO2-3D binding, or explain how to install it."""
    try:
        import rvo23d  # noqa: PLC0415 - optional compiled dependency, needed only for --policy orca
    except ImportError as err:  # pragma: no cover - depends on the machine
        raise ImportError(
            "ORCA (--policy orca, a training teacher) needs the RVO2-3D binding from PyPI: pip install jt-pyrvo23d "
            "(wheels for Linux x86_64, CPython 3.10-3.13)"
        ) from err
    return rvo23d


def preferred_velocity(pos_ned: np.ndarray, goal_ned: np.ndarray, params: OrcaParams,
                       spec: ActionSpec = DEFAULT_ACTION_SPEC) -> np.ndarray:
    """Velocity [M, 3] (NED) straight at the goal: 2 m/s, slower near it, climb within its limit.

    The vertical part is clipped to the climb limit (0.5 m/s) rather than the whole vector
    being scaled, so that the preferred velocity is one the UAV can actually fly: ORCA's
    guarantee only holds for velocities that are executed.
    """
    delta = goal_ned - pos_ned
    horizontal = np.hypot(delta[:, 0], delta[:, 1])
    speed = np.minimum(params.max_speed_m_s, horizontal / params.goal_slowdown_s)
    out = np.zeros_like(delta)
    scale = np.divide(speed, horizontal, out=np.zeros_like(speed), where=horizontal > 1e-9)
    out[:, 0] = delta[:, 0] * scale
    out[:, 1] = delta[:, 1] * scale
    out[:, 2] = np.clip(delta[:, 2] / params.goal_slowdown_s, spec.low[1], spec.high[1])
    return out


def keep_right(pref_ned: np.ndarray, pos_ned: np.ndarray, vel_ned: np.ndarray, known: np.ndarray,
               angle_rad: float) -> np.ndarray:
    """``pref_ned`` [n, 3] of one world's UAVs with the horizontal part of row i turned ``angle_rad`` to the
    right wherever a UAV j with ``known[i, j]`` lies ahead of it (positive along its preferred velocity) and
    closes in (their distance shrinking at the current velocities). NED: a turn to the right is a positive yaw."""
    rel = pos_ned[None, :, :] - pos_ned[:, None, :]  # [i, j]: j seen from i
    closing = np.einsum("ijk,ijk->ij", rel, vel_ned[None, :, :] - vel_ned[:, None, :]) < 0.0
    ahead = np.einsum("ijk,ik->ij", rel[..., :2], pref_ned[:, :2]) > 0.0
    conflict = known & closing & ahead
    np.fill_diagonal(conflict, False)
    turn = conflict.any(axis=1)
    out = pref_ned.copy()
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    out[turn, 0] = c * pref_ned[turn, 0] - s * pref_ned[turn, 1]
    out[turn, 1] = s * pref_ned[turn, 0] + c * pref_ned[turn, 1]
    return out


def velocity_to_action(vel_ned: np.ndarray, yaw_rad: np.ndarray, params: OrcaParams,
                       spec: ActionSpec = DEFAULT_ACTION_SPEC) -> np.ndarray:
    """Map ORCA's new velocities [M, 3] (NED) to commands ``(fwd, down, yaw rate)`` [M, 3].

    forward = projection on the heading (so a UAV that must turn slows down instead of
    flying off the line ORCA chose), down = the vertical component, yaw rate = gain x the
    bearing of the new velocity; each clipped to the action bounds.
    """
    frd = ned_to_frd(vel_ned, yaw_rad)
    bearing = np.arctan2(frd[:, 1], frd[:, 0])
    bearing = np.where(np.hypot(frd[:, 0], frd[:, 1]) > 1e-3, bearing, 0.0)  # no direction: hold heading
    action = np.stack([frd[:, 0], frd[:, 2], params.yaw_gain * bearing], axis=1)
    return np.clip(action, spec.low_array(), spec.high_array()).astype(np.float32)


class OrcaController:
    """ORCA for every UAV of a :class:`sitl.sim.env.SwarmEnv` (one RVO2-3D simulator per world).

    Call it with the env after each reset or step; it reads the true state of the worlds
    (privileged sensing) and returns actions [M, 3]. UAVs that no longer act but are still
    present (arrived and hovering) are kept in ORCA as agents with zero velocity so others
    avoid them; removed UAVs are parked far away, out of everyone's neighbourhood.
    """

    _PARK_M = 1.0e5  # parked agents sit this far away, 1 km apart from each other

    def __init__(self, num_worlds: int, uavs_per_world: int, collision_radius_m: float,
                 control_period_s: float, params: OrcaParams = OrcaParams(),
                 spec: ActionSpec = DEFAULT_ACTION_SPEC, camera: CameraSpec | None = None,
                 see_obstacles: bool = False) -> None:
        """``camera``: avoid only the UAVs inside this camera's frustum (``orca-fov``); None: all of them.
        ``see_obstacles``: also avoid the static obstacles (boxes, poles), each UAV's nearest obstacle
        point standing in its world as a static agent (with ``camera`` too: a UAV flies forward, so the
        nearest point matters where it lies ahead, where the camera shows it)."""
        rvo = _import_rvo()
        self.params, self.spec, self.camera, self.see_obstacles = params, spec, camera, see_obstacles
        self.n = uavs_per_world
        self.control_period_s = control_period_s
        self._age_s: np.ndarray | None = None  # [worlds, n, n]: since UAV i last saw UAV j (with params.remembers)
        radius = collision_radius_m + params.radius_margin_m
        self._sims = []
        for _ in range(num_worlds):
            sim = rvo.PyRVOSimulator(control_period_s, params.neighbor_dist_m, params.max_neighbors,
                                     params.time_horizon_s, radius, params.max_speed_m_s)
            for _ in range(uavs_per_world):
                sim.addAgent((0.0, 0.0, 0.0))
            if see_obstacles:  # agents n..2n-1: the nearest obstacle point of UAV 0..n-1
                for _ in range(uavs_per_world):
                    sim.setAgentRadius(sim.addAgent((0.0, 0.0, 0.0)), params.obstacle_point_radius_m)
            self._sims.append(sim)

    @classmethod
    def for_env(cls, env, params: OrcaParams = OrcaParams(), camera_limited: bool = False,
                see_obstacles: bool = False) -> "OrcaController":
        """ORCA for ``env``; ``camera_limited``: each UAV avoids only what ``env``'s camera covers (``orca-fov``);
        ``see_obstacles``: it avoids the static obstacles too."""
        cfg = env.config
        return cls(env.num_worlds, env.uavs_per_world, cfg.collision_radius_m, cfg.control_period_s, params,
                   env.action_spec, cfg.camera if camera_limited else None, see_obstacles)

    def _load(self, sim, b: int, pos_ned: np.ndarray, vel: np.ndarray, pref: np.ndarray, known: np.ndarray) -> None:
        """World ``b``'s UAVs into its simulator; those not ``known`` (gone, or out of view) parked far away."""
        for i in range(self.n):
            r = b * self.n + i
            if known[i]:
                sim.setAgentPosition(i, tuple(pos_ned[r]))
                sim.setAgentVelocity(i, tuple(vel[r]))
            else:
                sim.setAgentPosition(i, (self._PARK_M + 1000.0 * i, self._PARK_M, 0.0))
                sim.setAgentVelocity(i, (0.0, 0.0, 0.0))
            sim.setAgentPrefVelocity(i, tuple(pref[r]))

    def _load_obstacle_points(self, sim, pos_ned: np.ndarray, points_ned: np.ndarray, acting: np.ndarray) -> None:
        """Agents n + i: UAV i's nearest obstacle point as a static agent where it is within ORCA's
        neighbourhood (every UAV avoids it: it is a point of an obstacle); else parked far away."""
        gap = np.linalg.norm(points_ned - pos_ned, axis=1)  # inf without obstacles
        for i in range(self.n):
            if acting[i] and gap[i] <= self.params.neighbor_dist_m:
                sim.setAgentPosition(self.n + i, tuple(points_ned[i]))
            else:
                sim.setAgentPosition(self.n + i, (self._PARK_M + 1000.0 * i, -self._PARK_M, 0.0))
            sim.setAgentVelocity(self.n + i, (0.0, 0.0, 0.0))
            sim.setAgentPrefVelocity(self.n + i, (0.0, 0.0, 0.0))

    def new_velocities(self, pos_ned: np.ndarray, vel_ned: np.ndarray, goal_ned: np.ndarray,
                       acting: np.ndarray, present: np.ndarray, yaw_rad: np.ndarray | None = None,
                       obstacle_points_ned: np.ndarray | None = None, known: np.ndarray | None = None) -> np.ndarray:
        """ORCA's collision-free velocities [M, 3] (NED) for the acting UAVs (zero elsewhere).

        With a ``camera`` each acting UAV is solved on its own, knowing only itself and the
        present UAVs inside its camera frustum (``yaw_rad`` [M] gives the headings).
        ``obstacle_points_ned`` [M, 3] (``see_obstacles``): each UAV's nearest obstacle point, ``inf``
        where its world has none. ``known`` [M, n] (with a ``camera``): the UAVs of its world each UAV knows,
        instead of those in its frustum now (:meth:`act_env` passes its memory).
        """
        if self.see_obstacles and obstacle_points_ned is None:
            raise ValueError("this ORCA sees the obstacles: give obstacle_points_ned (act_env computes them)")
        pref = preferred_velocity(pos_ned, goal_ned, self.params, self.spec)
        pref[~acting] = 0.0
        right = np.radians(self.params.right_hand_deg)
        vel = np.where(acting[:, None], vel_ned, 0.0)  # hovering UAVs: static obstacles
        out = np.zeros_like(pos_ned)
        n = self.n
        if self.camera is not None:
            hfov, vfov = camera_fov_rad(self.camera)
        for b, sim in enumerate(self._sims):
            rows = slice(b * n, (b + 1) * n)
            if not acting[rows].any():
                continue
            if self.camera is None:
                if right > 0.0:  # every present UAV within ORCA's neighbourhood is known
                    near = np.linalg.norm(pos_ned[rows][None] - pos_ned[rows][:, None], axis=-1) <= self.params.neighbor_dist_m
                    pref[rows] = keep_right(pref[rows], pos_ned[rows], vel[rows], near & present[rows][None], right)
                self._load(sim, b, pos_ned, vel, pref, present[rows])
                if self.see_obstacles:
                    self._load_obstacle_points(sim, pos_ned[rows], obstacle_points_ned[rows], acting[rows])
                sim.doStep()  # computes the new velocities (it also moves its own copies; we overwrite them)
                for i in np.flatnonzero(acting[rows]):
                    out[b * n + i] = sim.getAgentVelocity(int(i))
                continue
            p, yaw = pos_ned[rows], yaw_rad[rows]
            if known is not None:
                seen = known[rows]
            else:
                seen = in_view(p[:, None], yaw[:, None], p[None, :], hfov, vfov, self.camera.max_range_m)  # [i, j]
            if right > 0.0:
                pref[rows] = keep_right(pref[rows], p, vel[rows], seen & present[rows][None], right)
            for i in np.flatnonzero(acting[rows]):
                known_i = seen[i] & present[rows]
                known_i[i] = True
                self._load(sim, b, pos_ned, vel, pref, known_i)
                if self.see_obstacles:  # its own nearest obstacle point only (the others' are parked)
                    self._load_obstacle_points(sim, pos_ned[rows], obstacle_points_ned[rows], np.arange(n) == i)
                sim.doStep()
                out[b * n + i] = sim.getAgentVelocity(int(i))
        return out

    def act_env(self, env, acting: np.ndarray | None = None) -> np.ndarray:
        """Actions [M, 3] for every UAV of ``env`` from its true state; ``acting`` [M] (default ``env.acting``):
        the UAVs to solve for (the others get zeros but still count as present)."""
        d = env.dynamics
        points = None
        if self.see_obstacles:
            worlds = env.num_worlds
            points = nearest_obstacle_points(d.pos_ned.reshape(worlds, self.n, 3), env.boxes,
                                             env.cylinders).reshape(-1, 3)
        acting = env.acting if acting is None else acting
        known = self._remembered(env) if self.camera is not None and self.params.remembers else None
        vel = self.new_velocities(d.pos_ned, d.vel_ned, env.goal_ned, acting, env.present, d.yaw_rad, points, known)
        return velocity_to_action(vel, d.yaw_rad, self.params, self.spec)

    def _remembered(self, env) -> np.ndarray:
        """[M, n]: the UAVs each UAV has seen within ``params.memory_s`` (and, with ``look_around``, all around it
        at its episode's first step). Called once per control step; a world whose episode starts forgets."""
        w, n = env.num_worlds, self.n
        pos = env.dynamics.pos_ned.reshape(w, n, 3)
        yaw = env.dynamics.yaw_rad.reshape(w, n)
        hfov, vfov = camera_fov_rad(self.camera)
        rng = self.camera.max_range_m
        seen = in_view(pos[:, :, None], yaw[:, :, None], pos[:, None, :], hfov, vfov, rng)  # [w, i, j]
        if self._age_s is None or self._age_s.shape != seen.shape:
            self._age_s = np.full(seen.shape, np.inf)
        first = np.asarray(env.world_steps) == 0
        self._age_s[first] = np.inf
        if self.params.look_around and first.any():
            seen[first] |= in_view_all_around(pos[first][:, :, None], pos[first][:, None, :], vfov, rng)
        self._age_s += self.control_period_s
        self._age_s[seen] = 0.0
        known = np.isfinite(self._age_s) & (self._age_s <= self.params.memory_s)  # inf: never seen (this episode)
        return known.reshape(w * n, n)


def orca_actor(env, params: OrcaParams = OrcaParams(), camera_limited: bool = False, see_obstacles: bool = False):
    """ORCA as an :data:`sitl.sim.episodes.Actor` for ``env`` (an ``ActorFactory``): it reads the true states,
    of every UAV (privileged) or, ``camera_limited``, of those in each UAV's camera frustum (``orca-fov``);
    ``see_obstacles``: and the obstacles."""
    controller = OrcaController.for_env(env, params, camera_limited, see_obstacles)
    return lambda obs: controller.act_env(env)
