"""What the policy sees and commands: the observation and action layout (paper III.B).

These specs are the shared vocabulary of the simulator, the trainer, the policy file's
metadata and the onboard companion. Frames are defined in :mod:`companion.frames`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

#: Layout of the policy's low-dimensional input ``state`` (float32 [B, 6]): the goal in the
#: heading FRD frame (metres), then the vehicle's own velocity (paper's o_g and o_v).
#: Note the vertical velocity is *down* (FRD), so the paper's "climb" is ``-vel_down_m_s``.
STATE_NAMES: tuple[str, ...] = (
    "goal_fwd_m",
    "goal_right_m",
    "goal_down_m",
    "vel_fwd_m_s",
    "vel_down_m_s",
    "yaw_rate_rad_s",
)
STATE_DIM = len(STATE_NAMES)

#: The policy's control period must lie in this range (seconds). Below 20 ms the loop only burns
#: CPU and fills the log (no depth camera or autopilot link keeps up); above 1 s the vehicle flies
#: open-loop for too long between decisions and the systemd watchdog is fed too rarely. ``inf``
#: would never tick at all.
CONTROL_PERIOD_MIN_S = 0.02
CONTROL_PERIOD_MAX_S = 1.0

#: ``--link-timeout`` range (s): autopilots send HEARTBEAT at 1 Hz, so anything under 1.5 heartbeat
#: periods declares a healthy link lost on ordinary jitter (and a lost link ends an engaged flight
#: for good); more than 10 s leaves a dead link undetected while the vehicle flies on its last
#: setpoint stream's failsafe (``inf`` would disable link-loss detection).
LINK_TIMEOUT_MIN_S = 1.5
LINK_TIMEOUT_MAX_S = 10.0
#: Longest ``--heartbeat-timeout`` (s) for the first heartbeat at start-up (an autopilot boots in
#: well under a minute; a systemd unit should fail and restart rather than wait for ever).
HEARTBEAT_TIMEOUT_MAX_S = 600.0

#: Largest depth image a policy may ask for (pixels per side) and most stacked frames: a bigger
#: observation cannot be rendered, sent or inferred within a control period on a companion computer
#: (and a hostile file could otherwise make the loader allocate gigabytes).
POLICY_MAX_IMAGE_SIDE_PX = 1024
POLICY_MAX_FRAMES = 16
#: Largest depth range a policy may declare (metres); depth cameras read far less.
POLICY_MAX_RANGE_M = 1000.0


@dataclass(frozen=True)
class ActionSpec:
    """Body-frame velocity command and its bounds (paper III.B.2).

    Components are forward speed, down speed (FRD: positive descends, so the paper's
    climb in (-0.5, 0.5) m/s is the same interval with the sign flipped) and yaw rate
    (positive turns right). Forward speed is never negative: the camera only looks ahead.
    """

    names: tuple[str, ...] = ("vel_fwd_m_s", "vel_down_m_s", "yaw_rate_rad_s")
    low: tuple[float, ...] = (0.0, -0.5, -0.5)
    high: tuple[float, ...] = (2.0, 0.5, 0.5)

    @property
    def dim(self) -> int:
        return len(self.names)

    def low_array(self) -> np.ndarray:
        return np.asarray(self.low, dtype=np.float32)

    def high_array(self) -> np.ndarray:
        return np.asarray(self.high, dtype=np.float32)

    def validate(self, action: np.ndarray, *, clip: bool = True) -> np.ndarray:
        """Check a batch of actions [..., 3] and return it clipped to the bounds.

        Non-finite values are always an error (a NaN command must never reach a motor
        or a simulated world). Out-of-bounds values are clipped when ``clip`` is true,
        which is the documented behaviour of the simulator and the companion; with
        ``clip=False`` they raise instead.
        """
        action = np.asarray(action, dtype=np.float64)
        if action.shape[-1:] != (self.dim,):
            raise ValueError(f"action must have shape [..., {self.dim}] ({', '.join(self.names)}), got {action.shape}")
        if not np.all(np.isfinite(action)):
            bad = np.argwhere(~np.isfinite(action))[0]
            raise ValueError(f"action contains a non-finite value at index {tuple(int(i) for i in bad)}")
        low, high = self.low_array(), self.high_array()
        if not clip and (np.any(action < low) or np.any(action > high)):
            raise ValueError(f"action out of bounds: low={self.low}, high={self.high}")
        return np.clip(action, low, high)


@dataclass(frozen=True)
class CameraSpec:
    """A forward-looking pinhole depth camera giving *planar* depth in metres.

    Planar depth (AirSim's DepthPlanar, a RealSense's z16) is the distance along the
    optical axis, not along the ray. Pixels are square, so the vertical field of view
    follows from the horizontal one and the aspect ratio. Row 0 is the top of the image,
    column 0 its left edge. Pixels with nothing within ``max_range_m`` read ``max_range_m``.
    """

    width: int = 32
    height: int = 32
    hfov_deg: float = 90.0
    max_range_m: float = 20.0
    frames: int = 3  # frames stacked into one observation, oldest first

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1:
            raise ValueError(f"camera resolution must be positive, got {self.width}x{self.height}")
        if not 1.0 <= self.hfov_deg < 179.0:
            raise ValueError(f"camera hfov_deg must be in [1, 179), got {self.hfov_deg}")
        if not self.max_range_m > 0:
            raise ValueError(f"camera max_range_m must be > 0, got {self.max_range_m}")
        if self.frames < 1:
            raise ValueError(f"camera frames must be >= 1, got {self.frames}")

    @property
    def tan_half_hfov(self) -> float:
        return math.tan(math.radians(self.hfov_deg) / 2.0)

    @property
    def tan_half_vfov(self) -> float:
        return self.tan_half_hfov * self.height / self.width

    @property
    def vfov_deg(self) -> float:
        return math.degrees(2.0 * math.atan(self.tan_half_vfov))

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class TaskSpec:
    """The task a policy is trained for and flown on: what counts as a collision, an arrival, a time-out.

    The simulator, the trainer, the evaluation and the companion all read these values from
    here (and a policy file records the ones it was trained with in ``policy.json``'s ``task``).
    """

    collision_radius_m: float = 0.3  # R: an F450-class quadrotor with props (0.6 m tip to tip); UAVs collide within 2R
    arrival_radius_m: float = 0.5  # paper: arrival within 0.5 m of the goal
    #: Episode time limit in control periods: 400 (40 s at 10 Hz) is the evaluation's (swarm_test, the
    #: paper protocol). The trainer's own episodes may be shorter (the fast preset's 200); a policy
    #: file's ``task`` records the limit it was trained with.
    max_episode_steps: int = 400

    def to_dict(self) -> dict:
        return asdict(self)


DEFAULT_ACTION_SPEC = ActionSpec()
DEFAULT_CAMERA_SPEC = CameraSpec()
DEFAULT_TASK_SPEC = TaskSpec()



# --------------------------------------------------------------------------- onboard safety limits (issue 16)

#: A depth frame with more than this fraction of invalid pixels (0, negative or non-finite,
#: counted on the camera's raw image before any conversion) is a blinded or dead sensor, not
#: an empty sky: the companion holds. A RealSense reports 0 where it has no stereo match. A
#: level camera in open sky loses the sky (at most the upper half of the image) plus
#: textureless patches below the horizon: typically 40-70 % invalid, so 50 % would hold in
#: normal flight. A covered lens, a lens against a wall (inside the ~0.3 m minimum range),
#: darkness or a dead sensor read 95-100 % invalid. 90 % separates the two with a margin on
#: each side; the 10 % that must remain valid is still ~100 pixels of the 32x32 policy view.
MAX_INVALID_DEPTH_FRACTION = 0.90

#: Goals (``--goal`` and run-time SET_POSITION_TARGET_LOCAL_NED) must be finite and within
#: these limits, or they are refused. Altitude is -D in the local NED frame, whose origin is
#: the autopilot's home (the take-off point): at least 0.5 m above it (never underground or
#: at ground level, where the policy cannot fly) and at most 120 m (the legal ceiling of the
#: open category, EU and US).
MIN_GOAL_ALTITUDE_M = 0.5
MAX_GOAL_ALTITUDE_M = 120.0
#: Horizontal distance (m) from the vehicle's current position (from home for ``--goal``,
#: checked before any odometry): farther than one battery (~20 min) at the 2 m/s forward
#: bound is a typo or an attack, not a mission.
MAX_GOAL_DISTANCE_M = 2500.0


def goal_problem(goal_ned, from_ned=None) -> str | None:
    """Why ``goal_ned`` (N, E, D in metres, local NED) is not an acceptable goal, or None.

    Args:
        goal_ned: the goal, three numbers.
        from_ned: the vehicle's position (local NED, m) for the distance check; None measures
            from home (the NED origin).
    """
    try:
        goal = np.asarray(goal_ned, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        return f"goal must be three numbers N,E,D in metres, got {goal_ned!r}"
    if goal.shape != (3,) or not np.all(np.isfinite(goal)):
        return f"goal must be three finite numbers N,E,D in metres, got {np.asarray(goal_ned).tolist()!r}"
    altitude_m = -goal[2] + 0.0  # + 0.0: no "-0 m"
    if not MIN_GOAL_ALTITUDE_M <= altitude_m <= MAX_GOAL_ALTITUDE_M:
        return (f"goal altitude {altitude_m:g} m (D = {goal[2]:g}) is outside {MIN_GOAL_ALTITUDE_M:g} to "
                f"{MAX_GOAL_ALTITUDE_M:g} m above home")
    origin = np.zeros(3) if from_ned is None else np.asarray(from_ned, dtype=np.float64)
    distance_m = float(np.hypot(goal[0] - origin[0], goal[1] - origin[1]))
    if not distance_m <= MAX_GOAL_DISTANCE_M:
        where = "home" if from_ned is None else "the vehicle"
        return f"goal is {distance_m:.6g} m from {where} horizontally (max {MAX_GOAL_DISTANCE_M:g} m)"
    return None
