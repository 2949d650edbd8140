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

#: ``--link-timeout`` range (s): autopilots send HEARTBEAT at 1 Hz, so less than 1 s declares a
#: healthy link lost; more than 10 s leaves a dead link undetected while the vehicle flies on
#: its last setpoint stream's failsafe (``inf`` would disable link-loss detection).
LINK_TIMEOUT_MIN_S = 1.0
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


DEFAULT_ACTION_SPEC = ActionSpec()
DEFAULT_CAMERA_SPEC = CameraSpec()

