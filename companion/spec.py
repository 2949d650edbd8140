"""What the policy sees and commands: the observation and action layout (paper III.B).

These specs are the shared vocabulary of the simulator, the trainer, the policy file's
metadata and the onboard companion. Frames are defined in :mod:`companion.frames`.
"""

from __future__ import annotations

import dataclasses
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


#: What a depth pixel with no measurement reads on the wire and in a raw frame (metres): 0, as
#: the RealSense SDK reports a pixel without a stereo match, one beyond the sensor's range or
#: nearer than its minimum distance. Negative and non-finite values are invalid too (never a
#: distance). :func:`companion.observation.clean_depth` turns every invalid pixel into
#: ``max_range_m`` before the policy sees it, in training and in flight alike.
INVALID_DEPTH_M = 0.0


@dataclass(frozen=True)
class CameraSpec:
    """A forward-looking pinhole depth camera giving *planar* depth in metres.

    Planar depth (AirSim's DepthPlanar, a RealSense's z16) is the distance along the
    optical axis, not along the ray. Row 0 is the top of the image, column 0 its left edge.
    The pixel grid samples ``hfov_deg`` x ``vfov_deg`` evenly; ``vfov_deg=None`` means square
    pixels (the vertical field of view follows from ``hfov_deg`` and the aspect ratio: the
    policy-file version-1 camera). A camera image is a min-pool of a real sensor's pixels
    over this grid, so the policy's pixels need not be square.

    The camera sits at the vehicle's centre, pitched ``mount_pitch_deg`` up (positive) or
    down (negative) from the heading frame's forward axis (no roll, no yaw offset).

    Range: a real sensor measures from ``min_range_m`` to ``max_range_m``; anything else is
    "no data", reported as :data:`INVALID_DEPTH_M` (0). The policy sees every invalid pixel
    and every farther one as ``max_range_m`` (:func:`companion.observation.clean_depth`).
    """

    width: int = 32
    height: int = 32
    hfov_deg: float = 90.0
    max_range_m: float = 20.0
    frames: int = 3  # frames stacked into one observation, oldest first
    vfov_deg: float | None = None  # None: square pixels (derived from hfov and aspect)
    mount_pitch_deg: float = 0.0  # optical axis above (+) / below (-) the heading frame's forward axis
    min_range_m: float = 0.0  # nearer returns are invalid on the sensor (0 m: an ideal camera)
    frame_stride: int = 1  # control steps between two stacked frames (1: consecutive frames)
    #: Age in control steps of each stacked frame, oldest first, the newest 0 (e.g. (3, 1, 0): ticks
    #: t-3, t-1 and t). Empty: evenly ``frame_stride`` apart. Given, it replaces ``frame_stride`` (which must be 1).
    frame_ages: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1:
            raise ValueError(f"camera resolution must be positive, got {self.width}x{self.height}")
        if not 1.0 <= self.hfov_deg < 179.0:
            raise ValueError(f"camera hfov_deg must be in [1, 179), got {self.hfov_deg}")
        if self.vfov_deg is not None and not 1.0 <= self.vfov_deg < 179.0:
            raise ValueError(f"camera vfov_deg must be in [1, 179), got {self.vfov_deg}")
        if not self.max_range_m > 0:
            raise ValueError(f"camera max_range_m must be > 0, got {self.max_range_m}")
        if not 0.0 <= self.min_range_m < self.max_range_m:
            raise ValueError(f"camera min_range_m must be in [0, max_range_m = {self.max_range_m:g}), "
                             f"got {self.min_range_m}")
        if not -MAX_MOUNT_PITCH_DEG <= self.mount_pitch_deg <= MAX_MOUNT_PITCH_DEG:
            raise ValueError(f"camera mount_pitch_deg must be in [-{MAX_MOUNT_PITCH_DEG:g}, {MAX_MOUNT_PITCH_DEG:g}], "
                             f"got {self.mount_pitch_deg}")
        if self.frames < 1:
            raise ValueError(f"camera frames must be >= 1, got {self.frames}")
        if not 1 <= self.frame_stride <= MAX_FRAME_STRIDE:
            raise ValueError(f"camera frame_stride must be in [1, {MAX_FRAME_STRIDE}], got {self.frame_stride}")
        object.__setattr__(self, "frame_ages", tuple(int(a) for a in self.frame_ages))  # a JSON list reads back
        if self.frame_ages:
            check_frame_ages(self.frame_ages, self.frames)
            if self.frame_stride != 1:
                raise ValueError(f"camera frame_ages {list(self.frame_ages)} replace frame_stride, which must then be 1, "
                                 f"got {self.frame_stride}")

    @property
    def stack_ages(self) -> tuple[int, ...]:
        """Age in control steps of each stacked frame, oldest first (the newest 0)."""
        if self.frame_ages:
            return self.frame_ages
        return tuple((self.frames - 1 - i) * self.frame_stride for i in range(self.frames))

    @property
    def history_frames(self) -> int:
        """Frames a stack must remember to serve one observation: the oldest stacked one's age + 1."""
        return self.stack_ages[0] + 1

    @property
    def history_columns(self) -> tuple[int, ...]:
        """Where each stacked frame sits in a history of :attr:`history_frames` images (oldest first)."""
        return tuple(self.history_frames - 1 - age for age in self.stack_ages)

    def describe_stack(self) -> str:
        """How the stacked frames are spaced in time, for people: '' (consecutive), ' 3 periods apart'
        or ' at ticks t-3, t-1, t'."""
        if self.frame_ages:
            return " at ticks " + ", ".join(f"t-{a}" if a else "t" for a in self.frame_ages)
        return f" {self.frame_stride} periods apart" if self.frame_stride != 1 else ""

    @property
    def tan_half_hfov(self) -> float:
        return math.tan(math.radians(self.hfov_deg) / 2.0)

    @property
    def tan_half_vfov(self) -> float:
        if self.vfov_deg is None:
            return self.tan_half_hfov * self.height / self.width
        return math.tan(math.radians(self.vfov_deg) / 2.0)

    def pixel_tangents(self) -> tuple[np.ndarray, np.ndarray]:
        """Pixel-centre tangents ``(tan_u [W], tan_v [H])``: a point at planar depth z in column c and row r
        lies z * tan_u[c] right of and z * tan_v[r] below the optical axis (centred axis, rows top down)."""
        edges_u = (2.0 * np.arange(self.width + 1) / self.width - 1.0) * self.tan_half_hfov
        tan_v = ((2.0 * np.arange(self.height) + 1.0) / self.height - 1.0) * self.tan_half_vfov
        return 0.5 * (edges_u[:-1] + edges_u[1:]), tan_v

    @property
    def vertical_fov_deg(self) -> float:
        """The vertical field of view in degrees, given or derived from square pixels."""
        return math.degrees(2.0 * math.atan(self.tan_half_vfov))

    @property
    def mount_pitch_rad(self) -> float:
        return math.radians(self.mount_pitch_deg)

    def to_dict(self) -> dict:
        """The fields as JSON-native values (``frame_ages`` a list), so a JSON round trip compares equal."""
        return {**asdict(self), "frame_ages": list(self.frame_ages)}


#: Largest number of control steps between two stacked frames a spec or a policy file may declare.
MAX_FRAME_STRIDE = 10


#: Oldest age (control steps) a stacked frame may have: the most a uniform stride reaches with 3 frames.
MAX_FRAME_AGE = 2 * MAX_FRAME_STRIDE


def check_frame_ages(ages: tuple[int, ...], frames: int) -> None:
    """Raise ``ValueError`` unless ``ages`` are ``frames`` strictly decreasing integers ending in 0,
    none older than :data:`MAX_FRAME_AGE`."""
    listed = list(ages)
    if len(listed) != frames:
        raise ValueError(f"camera frame_ages {listed} must give one age per stacked frame ({frames})")
    if listed[-1] != 0 or any(a <= b for a, b in zip(listed, listed[1:])) or listed[0] > MAX_FRAME_AGE:
        raise ValueError(f"camera frame_ages {listed} must decrease strictly to 0 (the newest frame), "
                         f"oldest at most {MAX_FRAME_AGE}")


#: Largest camera mount pitch (deg) a spec or a policy file may declare: beyond it the camera
#: looks at the ground or the sky rather than ahead.
MAX_MOUNT_PITCH_DEG = 45.0

#: Intel RealSense D435 (and D455: same 87 x 58 deg depth field of view) as the policy sees it:
#: 87 x 58 deg (datasheet), min-pooled to 32 x 20 pixels: ~2.7 deg per pixel, the angular
#: resolution of the paper camera at 32x32, and a SAC+AE update 2.7x cheaper than at 48x32
#: (``benchmarks/camera_resolution.py``, ``benchmarks/train_speed.py``; docs/simulator.md), level mount, usable range
#: 0.2-10 m (Min-Z ~0.2 m at 848x480; depth error ~2 % at 2 m growing with z^2, so beyond
#: ~10 m the stereo match is noise: Intel D400 series datasheet and product page).
REALSENSE_D435 = CameraSpec(width=32, height=20, hfov_deg=87.0, vfov_deg=58.0, max_range_m=10.0,
                            min_range_m=0.2, frames=3, mount_pitch_deg=0.0)
#: The image a simulated D435 sends to the companion (``sitl.vehicle --camera realsense_d435``):
#: square pixels at 16:9 like the sensor's 848x480 / 1280x720 modes, downscaled to 160x90 to fit one
#: UDP datagram, at the ~90 deg horizontal FOV a typical unit's intrinsics give (fx ~ width / 2;
#: the datasheet's 87 x 58 deg is the guaranteed field, 90 x 58.7 deg what units deliver). The
#: companion crops it to the policy's 87 x 58 deg and min-pools it to 32x20.
REALSENSE_D435_SENSOR = CameraSpec(width=160, height=90, hfov_deg=90.0, max_range_m=10.0, min_range_m=0.2)
#: A wide-angle stereo depth camera as the policy sees it: 110 x 70 deg, usable range 0.2-12 m,
#: the depth field of view ("up to 110 (H) x 70 (V)") and ideal depth range Stereolabs states for
#: its wide-lens ZED X / ZED 2i (docs "Depth Sensing" and "Depth Settings"). Rectification can
#: cut a unit's field below that: check your unit's intrinsics (the companion refuses a camera
#: narrower than the policy's). Min-pooled to the D435 preset's 32 x 20 pixels (~3.4 deg per
#: pixel, coarser than the D435's 2.7) so that training costs the same. The simulator gives it
#: the D435's stereo noise model (50 mm baseline), a conservative stand-in for a 120 mm baseline.
WIDE_STEREO = CameraSpec(width=32, height=20, hfov_deg=110.0, vfov_deg=70.0, max_range_m=12.0,
                         min_range_m=0.2, frames=3, mount_pitch_deg=0.0)
#: The image a simulated wide stereo camera sends to the companion (``sitl.vehicle --camera
#: wide_stereo``): 160 x 90 square pixels at 112 deg horizontal (79.7 deg vertical), which the
#: companion crops to the policy's 110 x 70 deg.
WIDE_STEREO_SENSOR = CameraSpec(width=160, height=90, hfov_deg=112.0, max_range_m=12.0, min_range_m=0.2)
#: The camera presets by name (``--camera NAME`` in sitl's command lines). ``paper``: the
#: paper's 90 x 90 deg square camera with a 20 m range, the version-1 policy file's camera.
CAMERA_PRESETS: dict[str, CameraSpec] = {"paper": CameraSpec(), "realsense_d435": REALSENSE_D435,
                                         "wide_stereo": WIDE_STEREO}
#: The image each preset's sensor delivers (what ``sitl.vehicle`` renders and sends): the paper
#: camera is rendered at the policy's own resolution, a real sensor at its own, wider, geometry.
SENSOR_PRESETS: dict[str, CameraSpec] = {"paper": CameraSpec(), "realsense_d435": REALSENSE_D435_SENSOR,
                                         "wide_stereo": WIDE_STEREO_SENSOR}


#: Direction sectors of the remembered-depth input (:class:`MemorySpec`), in the heading FRD frame:
#: elevation band edges in degrees (up positive, bottom to top) and the azimuth sectors of each band
#: (1: the whole ring, a cap). Azimuth sectors are centred on forward, 0, 45, ... deg, positive right.
MEMORY_ELEVATION_EDGES_DEG: tuple[float, ...] = (-90.0, -45.0, -15.0, 15.0, 45.0, 90.0)
MEMORY_AZIMUTH_SECTORS: tuple[int, ...] = (1, 8, 8, 8, 1)
MEMORY_BAND_NAMES: tuple[str, ...] = ("down", "low", "level", "high", "up")
#: Most control steps a policy file may ask to remember (10 s at 0.1 s).
MEMORY_MAX_STEPS = 100


@dataclass(frozen=True)
class MemorySpec:
    """Remembered depth: what the camera showed in the last ``steps`` control steps, moved with odometry.

    The companion keeps the points of recent depth frames in local NED (each frame min-pooled by
    ``pool`` first, one frame kept every ``every_steps`` steps, the newest frame always), and gives the
    policy, in each direction sector of :data:`MEMORY_AZIMUTH_SECTORS`, the range of the nearest
    remembered point from where the vehicle is now, clipped to ``range_m`` (nothing remembered reads
    ``range_m``). The ranges are appended to the state after :data:`STATE_NAMES`, named by
    :meth:`state_names`. It lets a policy keep avoiding a UAV that has left its camera's view (above,
    below or beside it). ``companion.observation.RememberedDepth`` is the one implementation.
    """

    steps: int = 10  # control steps remembered (1 s at 0.1 s)
    every_steps: int = 2  # one frame kept every this many steps (the newest always)
    range_m: float = 5.0  # remembered ranges are clipped here
    pool: int = 2  # frames are min-pooled by this factor before they are remembered
    #: Count only remembered points outside the camera's view now (what the image cannot show); False: all.
    outside_view: bool = False

    def __post_init__(self) -> None:
        if not 1 <= self.steps <= MEMORY_MAX_STEPS:
            raise ValueError(f"memory steps must be in 1..{MEMORY_MAX_STEPS}, got {self.steps}")
        if not 1 <= self.every_steps <= self.steps:
            raise ValueError(f"memory every_steps must be in 1..steps ({self.steps}), got {self.every_steps}")
        if not 0.0 < self.range_m <= 100.0:
            raise ValueError(f"memory range_m must be in (0, 100] m, got {self.range_m}")
        if not 1 <= self.pool <= 16:
            raise ValueError(f"memory pool must be in 1..16, got {self.pool}")
        if not isinstance(self.outside_view, bool):
            raise ValueError(f"memory outside_view must be true or false, got {self.outside_view!r}")

    @property
    def slots(self) -> int:
        """Frames remembered at once: ``ceil(steps / every_steps)``."""
        return -(-self.steps // self.every_steps)

    @property
    def num_sectors(self) -> int:
        return sum(MEMORY_AZIMUTH_SECTORS)

    @staticmethod
    def state_names() -> tuple[str, ...]:
        """The names of the sector ranges appended to the state, e.g. ``memory_level_az045_m`` (45 deg right)."""
        names = []
        for band, count in zip(MEMORY_BAND_NAMES, MEMORY_AZIMUTH_SECTORS):
            names += [f"memory_{band}_m"] if count == 1 else [f"memory_{band}_az{round(360 * k / count):03d}_m"
                                                               for k in range(count)]
        return tuple(names)

    def to_dict(self) -> dict:
        return asdict(self)


def memory_for_steps(steps: int, outside_view: bool = False) -> MemorySpec | None:
    """Remembered depth over ``steps`` control steps (``outside_view``: of what is out of view now only),
    every other setting the default (0 steps: none)."""
    return MemorySpec(steps=steps, every_steps=min(MemorySpec.every_steps, steps),
                      outside_view=outside_view) if steps else None


def state_names_for(memory: MemorySpec | None) -> tuple[str, ...]:
    """The state layout of a policy with (or without) remembered depth."""
    return STATE_NAMES + (memory.state_names() if memory is not None else ())


def state_dim_for(memory: MemorySpec | None) -> int:
    """Entries of the state of a policy with (or without) remembered depth: 6, or 6 + its sectors."""
    return STATE_DIM + (memory.num_sectors if memory is not None else 0)


def preset_for_camera(camera: CameraSpec) -> str:
    """The name of the camera preset whose field of view and range ``camera`` has (resolution, stack and
    mount pitch aside): which sensor ``sitl.vehicle --camera`` must carry for a policy. Raises
    ``ValueError`` when no preset matches."""
    def view(c: CameraSpec) -> tuple[float, float, float]:
        return round(c.hfov_deg, 3), round(c.vertical_fov_deg, 3), round(c.max_range_m, 3)

    for name, preset in CAMERA_PRESETS.items():
        if view(preset) == view(dataclasses.replace(camera, width=preset.width, height=preset.height)):
            return name
    raise ValueError(f"no camera preset has a {camera.hfov_deg:g} x {camera.vertical_fov_deg:.1f} deg field of view "
                     f"with a {camera.max_range_m:g} m range; presets: {', '.join(CAMERA_PRESETS)}")


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
#: counted on the camera's raw image before any conversion) is a blinded or dead sensor: the
#: companion holds. This is the limit for policies of an ideal camera (``min_range_m`` 0, the
#: simulator's perfect depth, where only a dead or covered sensor reads 0). A real stereo
#: sensor reports the sky and everything beyond its range as 0: a level D435 more than ~6 m
#: above the ground reads > 90 % invalid in 99 % of normal frames (``benchmarks/camera_model.py``),
#: so for a real sensor's policy the default is off
#: (:func:`companion.observation.default_max_invalid_fraction`, docs/companion.md).
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
