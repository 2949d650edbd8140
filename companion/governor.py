"""A speed governor on the policy's forward command: stop before what the camera shows straight ahead.

PX4's collision prevention (``CP_DIST``, fed by the companion's OBSTACLE_DISTANCE) acts only in
Position mode, and the companion flies in Offboard, so nothing but the policy slows the vehicle
before an obstacle. This governor is the companion-side equivalent, applied after the policy and
before the setpoint is sent, with the policy's own depth frame (so the simulator's evaluation and
the companion run the same code on the same input):

* **Cap.** The nearest depth ``d`` among the pixels of the newest frame whose point lies inside the
  flight corridor (``|x| <= corridor_half_width_m`` and ``|y| <= corridor_half_height_m`` around
  the optical axis: what a straight flight would touch) bounds the forward speed to the one from
  which the vehicle can still stop ``stop_distance_m`` short of it, braking at ``brake_acc_m_s2``
  after ``delay_s`` of lag: ``v = -a t + sqrt((a t)^2 + 2 a (d - stop))``.
* **Turn.** Where the cap takes more than half the policy's forward command and the policy is not
  turning decisively itself (``|yaw rate| < turn_when_policy_below_rad_s``), the governor turns at
  ``turn_rate_rad_s`` towards the image half with more free space in the corridor's height band (right
  on a tie: two UAVs meeting head-on both turn right). Without the turn a UAV in front of a pole waits
  for a yaw command the policy, trained without a governor, does not give.
* **Sticky turn** (``release_margin_m`` finite, the default). A turn, once started, keeps its
  direction and overrides the policy's yaw until the corridor is clear to
  ``stop_distance_m + release_margin_m``: otherwise the policy
  yaws back towards its goal behind the obstacle as soon as the corridor clears by a pixel, the
  obstacle is in the way again, and the vehicle dithers in front of it. The turn state is per vehicle
  (:meth:`SpeedGovernor.apply`'s ``turning`` in and out; 0 at the start of a flight).

* **Climb cap** (``max_climb_m_s`` finite; off by default). The climb and descent rate is clipped to
  ``+-max_climb_m_s`` whatever the forward speed. Most of the dense scenes' unseen collisions close
  vertically (docs/results.md "What a forward D435 allows"); a slower climb gives a neighbour above or
  below more time to move off before contact.
* **Climb in view** (``view_climb_margin_deg`` finite; off by default). A forward camera sees nothing
  above or below its vertical field of view, and a UAV climbing or descending steeply there meets
  neighbours it never had in its image (most of the dense scenes' collisions, docs/results.md "Climbing
  only where the camera looks"). The climb rate is then capped to what keeps the flight path inside the
  view, less the margin: ``|climb| <= forward * tan(vfov / 2 -+ mount pitch - margin)``, and at
  least ``blind_climb_m_s`` (so a UAV just below its goal still gets there).

Otherwise it only lowers the forward speed and sets the yaw rate; climb is the policy's, within those two
limits. "No data" pixels read as the camera's range (the policy's convention), i.e. free. It assumes the obstacle stands
still (two vehicles closing head-on need twice the room). Measured in docs/results.md ("The speed
governor"): it lifts random and obstacle scenes and costs dense converging traffic (a circle of 14
UAVs), so it is opt-in (``companion --governor``). :data:`GOVERNOR_PRESETS` names four settings: the
``default`` (stop and turn), ``swarm`` (0.6 m stop, no turn), which keeps dense circles for policies that
turn by themselves, ``swarm-view`` (``swarm`` plus climb in view) and ``swarm-slow-climb`` (``swarm`` plus
the climb cap at 0.25 m/s).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from companion.spec import CameraSpec


#: The settings that may be infinite ("never"; null in JSON, policy.json's ``governor``).
MAY_BE_INFINITE = ("release_margin_m", "view_climb_margin_deg", "max_climb_m_s")
#: Settings added after policy files already recorded a governor: a file that does not name them was
#: trained without them, i.e. with their defaults (which change nothing).
ADDED_SETTINGS = ("view_climb_margin_deg", "blind_climb_m_s", "max_climb_m_s")


@dataclass(frozen=True)
class GovernorSpec:
    """The governor's settings (the defaults are the measured ones, docs/results.md)."""

    corridor_half_width_m: float = 0.35  # the collision radius R = 0.3 m plus 5 cm
    corridor_half_height_m: float = 0.35
    stop_distance_m: float = 1.0  # depth (m) at which the forward speed reaches zero
    brake_acc_m_s2: float = 2.0  # deceleration assumed for the stopping distance
    delay_s: float = 0.35  # control period plus velocity-loop lag before braking starts
    turn_rate_rad_s: float = 0.5  # yaw rate of the turn away (the action limit)
    turn_when_capped_below: float = 0.5  # turn when the cap leaves less than this share of the command
    turn_when_policy_below_rad_s: float = 0.3  # ... and the policy's own |yaw rate| is below this
    free_space_clip_m: float = 5.0  # free space per column counted up to this depth when choosing a side
    release_margin_m: float = 1.0  # sticky turn: held until the corridor is clear to stop + this (inf: not sticky)
    view_climb_margin_deg: float = math.inf  # climb in view: path kept this far inside the vertical view (inf: off)
    blind_climb_m_s: float = 0.1  # climb in view: climb or descent always allowed, however slow the forward speed
    max_climb_m_s: float = math.inf  # climb cap: |climb| and |descent| at most this (m/s; inf: off)

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if math.isnan(value) or value < 0.0 or (math.isinf(value) and name not in MAY_BE_INFINITE):
                raise ValueError(f"governor {name} must be a finite number >= 0, got {value}")
        if self.brake_acc_m_s2 <= 0.0:
            raise ValueError(f"governor brake_acc_m_s2 must be > 0, got {self.brake_acc_m_s2}")

    @property
    def sticky(self) -> bool:
        return math.isfinite(self.release_margin_m)

    def to_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and math.isinf(v) else v) for k, v in asdict(self).items()}

    def describe(self) -> str:
        """What this setting does, in words (the help texts and the companion's log share them), e.g.
        ``stop 0.6 m short in a +-0.35 m corridor, never turn``."""
        turn = "turn to the freer side when stopped" if self.turn_when_capped_below > 0 else "never turn"
        climb = (f", climb only within the camera's vertical view less {self.view_climb_margin_deg:g} deg"
                 if math.isfinite(self.view_climb_margin_deg) else "")
        if math.isfinite(self.max_climb_m_s):
            climb += f", climb and descend at most {self.max_climb_m_s:g} m/s"
        return f"stop {self.stop_distance_m:g} m short in a +-{self.corridor_half_width_m:g} m corridor, {turn}{climb}"


#: Named settings (``companion --governor [NAME]``, ``swarm_test --governor [NAME]``), measured in docs/results.md
#: ("The governor's ``swarm`` setting"). ``default`` (``--governor`` alone) stops 1 m short and
#: turns away: what a policy that never turns by itself needs in front of a pole. ``swarm`` stops 0.6 m short and never
#: turns: the circle-teacher policies turn by themselves, and the default's turn and longer stop break their dense
#: converging traffic (circles of 12-14 UAVs), where a UAV stopped or turned at the centre is met by neighbours it
#: cannot see. ``swarm-view`` is ``swarm`` that also climbs only within the camera's view (docs/results.md "Climbing
#: only where the camera looks": it removes blind vertical flight but does not raise success). ``swarm-slow-climb`` is
#: ``swarm`` with climb and descent capped at 0.25 m/s (docs/results.md "A slower climb", session 63).
GOVERNOR_PRESETS: dict[str, GovernorSpec] = {
    "default": GovernorSpec(),
    "swarm": GovernorSpec(stop_distance_m=0.6, turn_when_capped_below=0.0),
    "swarm-view": GovernorSpec(stop_distance_m=0.6, turn_when_capped_below=0.0, view_climb_margin_deg=5.0),
    "swarm-slow-climb": GovernorSpec(stop_distance_m=0.6, turn_when_capped_below=0.0, max_climb_m_s=0.25),
}
DEFAULT_GOVERNOR = "default"


def add_governor_argument(parser, help: str) -> None:
    """``--governor [NAME]`` on an argparse parser or group: a :data:`GOVERNOR_PRESETS` name, the default when
    given alone, None when absent (the companion's and the simulator's command lines share it)."""
    parser.add_argument("--governor", nargs="?", const=DEFAULT_GOVERNOR, default=None, choices=list(GOVERNOR_PRESETS),
                        metavar="{" + ",".join(GOVERNOR_PRESETS) + "}", help=help)


def describe_presets() -> str:
    """Every named setting and what it does, e.g. ``default: stop 1 m short ..., turn ...; swarm: ...``."""
    return "; ".join(f"{name}: {spec.describe()}" for name, spec in GOVERNOR_PRESETS.items())


def governor_name(spec: GovernorSpec) -> str:
    """The preset ``spec`` is (:data:`GOVERNOR_PRESETS`), or ``custom``."""
    return next((name for name, preset in GOVERNOR_PRESETS.items() if preset == spec), "custom")


class SpeedGovernor:
    """Applies a :class:`GovernorSpec` to commands of UAVs carrying ``camera`` (the policy's camera).

    Args:
        camera: the policy's camera: its field of view and resolution place each pixel's point.
        spec: the settings.
    """

    def __init__(self, camera: CameraSpec, spec: GovernorSpec = GovernorSpec()) -> None:
        self.camera = camera
        self.spec = spec
        tan_u, tan_v = camera.pixel_tangents()  # x right = z * tan_u, y down = z * tan_v
        self.tan_u, self.tan_v = tan_u.astype(np.float32), tan_v.astype(np.float32)
        # climb in view: the steepest climb and descent (forward m/s -> m/s) that keep the path in the view
        half_v, pitch, margin = camera.vertical_fov_deg / 2.0, camera.mount_pitch_deg, spec.view_climb_margin_deg
        self.climb_per_forward = math.tan(math.radians(min(max(half_v + pitch - margin, 0.0), 89.0)))
        self.descent_per_forward = math.tan(math.radians(min(max(half_v - pitch - margin, 0.0), 89.0)))

    def forward_limit(self, depth_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For frames [k, H, W] (planar metres): the nearest depth in the corridor (m: the camera's range when
        nothing is nearer; inf only if no pixel's point lies in it) and the speed cap (m/s)."""
        s = self.spec
        z = np.asarray(depth_m, dtype=np.float32)
        inside = (np.abs(z * self.tan_u) <= s.corridor_half_width_m) & \
                 (np.abs(z * self.tan_v[:, None]) <= s.corridor_half_height_m)
        nearest = np.where(inside, z, np.inf).min(axis=(1, 2))
        a, t = s.brake_acc_m_s2, s.delay_s
        room = np.maximum(nearest - s.stop_distance_m, 0.0)
        cap = np.maximum(-a * t + np.sqrt((a * t) ** 2 + 2.0 * a * room), 0.0)
        return nearest, cap

    def turn_direction(self, depth_m: np.ndarray) -> np.ndarray:
        """+1 (right) or -1 (left) per frame [k, H, W]: the image half with more free space in the corridor's band."""
        s = self.spec
        z = np.asarray(depth_m, dtype=np.float32)
        band = np.abs(z * self.tan_v[:, None]) <= s.corridor_half_height_m
        free = np.minimum(np.where(band, z, np.inf).min(axis=1), s.free_space_clip_m)  # [k, W]
        half = free.shape[1] // 2
        right_minus_left = free[:, half:].mean(axis=1) - free[:, :half].mean(axis=1)
        return np.where(right_minus_left < 0.0, -1.0, 1.0)

    def apply(self, depth_m: np.ndarray, commands: np.ndarray, turning: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Govern ``commands`` [k, 3] (forward m/s, down m/s, yaw rate rad/s) with each UAV's newest frame [k, H, W].

        ``turning`` [k] is each UAV's turn in progress (+1 right, -1 left, 0 none; ``None``: none), as
        the previous call returned it; only a sticky governor keeps one. Returns the governed commands
        (a copy), whether the cap lowered each forward speed, the nearest depth in the corridor (m, as
        :meth:`forward_limit`) and the turns in progress after this step.
        """
        s = self.spec
        out = np.array(commands, dtype=np.float32, copy=True)
        depth_m = np.asarray(depth_m)
        turning = np.zeros(len(out), dtype=np.float32) if turning is None else np.array(turning, dtype=np.float32)
        nearest, cap = self.forward_limit(depth_m)
        forward = out[:, 0].copy()
        capped = cap < forward
        start = (turning == 0) & (cap < s.turn_when_capped_below * forward) & \
            (np.abs(out[:, 2]) < s.turn_when_policy_below_rad_s)
        if s.sticky:
            turning[nearest >= s.stop_distance_m + s.release_margin_m] = 0.0  # clear ahead: the policy steers again
        if np.any(start):
            turning[start] = self.turn_direction(depth_m[start])
        steer = turning != 0
        out[steer, 2] = s.turn_rate_rad_s * turning[steer]
        out[:, 0] = np.minimum(forward, cap)
        if math.isfinite(s.view_climb_margin_deg):  # down is NED: negative climbs
            ahead = np.maximum(out[:, 0], 0.0)
            out[:, 1] = np.clip(out[:, 1], -np.maximum(ahead * self.climb_per_forward, s.blind_climb_m_s),
                                np.maximum(ahead * self.descent_per_forward, s.blind_climb_m_s))
        if math.isfinite(s.max_climb_m_s):
            out[:, 1] = np.clip(out[:, 1], -s.max_climb_m_s, s.max_climb_m_s)
        if not s.sticky:
            turning[:] = 0.0  # each step decides afresh
        return out, capped, nearest, turning
