"""Configuration of a simulated swarm: one typed source of truth for every world parameter."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from companion.spec import DEFAULT_TASK_SPEC, CameraSpec, MemorySpec
from sitl.sim.camera import SceneGeometry, StereoNoise
from sitl.sim.dynamics import DYNAMICS_NAMES, KinematicRandomization

#: UAVs per cubic metre of the random scenarios' box (paper IV.B).
DENSITIES: dict[str, float] = {"small": 0.1, "medium": 0.06, "large": 0.04}
SCENARIOS = ("random", "circle", "obstacles")
#: Training may also draw each world's episode from any scenario ("mixed").
TRAINING_SCENARIOS = SCENARIOS + ("mixed",)
#: Where circle UAVs face at the start (``ScenarioConfig.circle_heading``); ``mixed`` draws one of the
#: other three per episode (training).
CIRCLE_HEADINGS = ("goal", "common", "any", "mixed")
#: The circle scenario's radius in m (paper IV.C: 8-32 UAVs on a circle, goals antipodal).
CIRCLE_RADIUS_M = 12.0
#: Static obstacles of the ``obstacles`` scene (a forest edge, a yard): vertical cylinders (poles,
#: trunks) and boxes (sheds, containers), all standing on the ground.
OBSTACLE_CYLINDER_RADIUS_M = (0.1, 0.5)  # a lamp post to a large trunk
OBSTACLE_CYLINDER_HEIGHT_M = (8.0, 25.0)  # above ground: trees and masts, mostly taller than the flight
OBSTACLE_BOX_HALF_SIDE_M = (0.4, 1.5)  # horizontal half-extents: a bin to a 3 m shed
OBSTACLE_BOX_HEIGHT_M = (1.0, 8.0)  # above ground
ARRIVED_BEHAVIOURS = ("hover", "remove")
CRASHED_BEHAVIOURS = ("remove", "freeze")


@dataclass(frozen=True)
class RewardConfig:
    """Reward of paper eqs. 2-4 with the paper's constants."""

    r_arrival: float = 50.0
    r_collision: float = -10.0
    #: Added to r_collision when the collision is with another UAV (0, the paper: every collision
    #: costs the same). A training option (docs/training.md "The collision reward").
    r_collision_uav_extra: float = 0.0
    w_goal: float = 3.0
    w_avoid: float = -0.05
    d_safe_m: float = 5.0
    arrival_radius_m: float = DEFAULT_TASK_SPEC.arrival_radius_m
    #: Whether eq. 4's d_min counts the ground. The paper takes the smallest depth of the whole
    #: image (True reproduces it), so a UAV flying lower than d_safe = 5 m is punished every step
    #: for the ground below it and learns not to fly low. False (the default, a documented
    #: deviation: docs/training.md) takes d_min over other UAVs and obstacles only, as the
    #: camera kernel reports them; the ground stays in the collision term (altitude < R).
    avoid_counts_ground: bool = False
    #: Reward per step and per m/s of the UAV's speed while its velocity points outside its own
    #: camera's field of view (0, the paper: no such term). A training option against flying blind
    #: (climbing or descending steeply at low forward speed): docs/training.md "Flying where the camera looks".
    w_blind: float = 0.0
    #: Reward per step and per m/s that the commanded forward speed exceeds the speed governor's cap
    #: (:mod:`companion.governor`, default settings) on the UAV's new depth frame: a price on flying at
    #: what the corridor ahead shows faster than one could stop (0, the paper: no such term). A training
    #: option: docs/training.md "A price on outrunning the corridor".
    w_corridor: float = 0.0


@dataclass(frozen=True)
class ScenarioConfig:
    """Where UAVs start and where they must go (paper IV.B).

    Random: starts and goals are drawn uniformly in a box of volume ``N / density`` whose
    height is ``box_aspect`` times its (square) side, floating ``box_floor_alt_m`` above
    the ground (high enough that the ground stays beyond d_safe in the camera). Starts are
    at least ``min_separation_m`` apart, goals too, and every goal is at least
    ``min_goal_distance_m`` from its start. Initial heading: towards the goal plus a
    uniform error of up to ``yaw_jitter_rad``.

    Circle: N UAVs evenly on a horizontal circle of ``circle_radius_m`` at
    ``circle_alt_m``, each facing its goal on the opposite side. Each episode rotates the
    formation by a uniform random angle and moves each start by a uniform random offset of
    up to ``circle_jitter_m`` per axis (goals stay exactly antipodal to the nominal starts),
    so episodes differ even for a deterministic policy. ``circle_scatter_m`` (0 in the paper and
    in training) moves each start further, horizontally, to a point drawn uniformly in a disc of
    that radius (redrawn while it would come closer than ``min_separation_m`` to another): a swarm
    whose starts are off by what GPS errors and a takeoff's drift leave, the goals still at the
    nominal antipodes (``circle-n8-scatter`` in ``swarm_test flown``). ``circle_heading`` sets where the UAVs
    face at the start (:data:`CIRCLE_HEADINGS`): ``goal`` (the paper: each its own goal),
    ``common`` (one heading drawn per episode for the whole swarm, as a swarm set out on a field
    or spawned by an autopilot's SITL faces one way), ``any`` (each UAV its own uniform heading) or,
    for training, ``mixed`` (each circle episode one of the three, equally likely).

    Obstacles: a random scene (same box, altitudes and jitter) among static obstacles standing
    on the ground, drawn anew every episode over the box's footprint widened by
    ``obstacle_margin_m`` on each side: ``obstacle_density_per_100m2`` obstacles per 100 m^2
    of that area (rounded), a fraction ``obstacle_box_fraction`` of them boxes, the rest
    vertical cylinders (sizes: the ``OBSTACLE_*`` ranges above). No obstacle comes closer than
    ``obstacle_clearance_m`` to any start or goal (so no UAV starts or ends inside one); the
    straight line between them may well be blocked — that is the point.

    The task as flown (``altitude_range_m``, ``circle_alt_range_m``, ``circle_radius_range_m``
    set, :func:`flown_scenario`): the random box floats at a floor drawn per episode uniformly in
    ``[lo, hi - box height]``, so every start and goal lies between ``lo`` and ``hi`` above the
    ground (the paper's geometry is ``altitude_range_m=None``: a fixed floor of
    ``box_floor_alt_m``); the circle's altitude and radius are drawn per episode uniformly in
    their ranges. ``start_jitter_m`` moves each random-scene start by a uniform offset of up to
    that much per axis (redrawn while it would bring two starts closer than ``min_separation_m``
    or a start below ``lo``), as ``circle_jitter_m`` does for the circle. ``low_floor_fraction``
    (training only; 0 in every evaluation) draws the floor instead within the lowest
    ``LOW_FLOOR_BAND_M`` of its range in that share of episodes, so that goals near the ground,
    3.6 % of a uniform draw in the medium scene, are practised more often.

    Mixed (training only): each episode is a circle episode with probability
    ``circle_fraction``, an obstacles one with probability ``obstacle_fraction`` (at
    ``obstacle_density`` UAV/m^3 when set, e.g. the obstacle scene's own
    :data:`OBSTACLE_SCENE_DENSITY`, else at ``density``), else a random one.
    """

    name: str = "random"
    density: float = DENSITIES["medium"]
    box_aspect: float = 0.5
    box_floor_alt_m: float = 6.0
    min_separation_m: float = 1.0
    min_goal_distance_m: float = 2.0
    yaw_jitter_rad: float = 0.785398  # pi / 4
    circle_radius_m: float = CIRCLE_RADIUS_M
    circle_alt_m: float = 10.0
    circle_jitter_m: float = 0.25
    circle_scatter_m: float = 0.0  # circle: horizontal start offsets drawn in a disc of this radius (0: none)
    circle_heading: str = "goal"  # circle starts: goal, common, any or mixed (CIRCLE_HEADINGS)
    circle_fraction: float = 0.5
    altitude_range_m: tuple[float, float] | None = None  # random/obstacles: None = fixed floor box_floor_alt_m
    start_jitter_m: float = 0.0  # random/obstacles: per-axis start offset, up to +-m
    low_floor_fraction: float = 0.0  # random/obstacles with altitude_range_m: P(floor in the lowest LOW_FLOOR_BAND_M)
    circle_alt_range_m: tuple[float, float] | None = None  # None: circle_alt_m
    circle_radius_range_m: tuple[float, float] | None = None  # None: circle_radius_m
    obstacle_density_per_100m2: float = 10.0  # ~1000 per hectare: a dense orchard or forest edge
    obstacle_box_fraction: float = 0.25
    obstacle_margin_m: float = 1.0
    obstacle_clearance_m: float = 1.0  # > R + margin: free space around every start and goal
    obstacle_fraction: float = 0.0  # mixed: probability of an obstacles episode
    obstacle_density: float | None = None  # mixed: UAV/m^3 of its obstacles episodes (None: density)
    #: random episodes (alone or in mixed): (low, high) UAV/m^3, each episode's density drawn log-uniformly
    #: between them instead of ``density`` (a swarm is not always equally crowded); None: ``density``
    density_range: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.name not in TRAINING_SCENARIOS:
            raise ValueError(f"unknown scenario {self.name!r}; choose one of {', '.join(TRAINING_SCENARIOS)}")
        if not 0.0 <= self.circle_fraction <= 1.0:
            raise ValueError(f"circle_fraction must be in [0, 1], got {self.circle_fraction}")
        if self.circle_heading not in CIRCLE_HEADINGS:
            raise ValueError(f"unknown circle_heading {self.circle_heading!r}; choose one of {', '.join(CIRCLE_HEADINGS)}")
        if not 0.0 <= self.obstacle_fraction <= 1.0 - self.circle_fraction:
            raise ValueError(f"obstacle_fraction must be in [0, 1 - circle_fraction], got {self.obstacle_fraction}")
        for name in ("altitude_range_m", "circle_alt_range_m", "circle_radius_range_m", "density_range"):
            value = getattr(self, name)
            if value is not None:
                lo, hi = value
                if not 0.0 < lo <= hi < 100_000.0:
                    raise ValueError(f"{name} must be (low, high) with 0 < low <= high, got {value}")
                object.__setattr__(self, name, (float(lo), float(hi)))  # JSON round trips give lists
        if not 0.0 <= self.start_jitter_m <= 10.0:
            raise ValueError(f"start_jitter_m must be in [0, 10], got {self.start_jitter_m}")
        if not 0.0 <= self.low_floor_fraction <= 1.0:
            raise ValueError(f"low_floor_fraction must be in [0, 1], got {self.low_floor_fraction}")
        if self.low_floor_fraction > 0 and self.altitude_range_m is None:
            raise ValueError(f"low_floor_fraction needs altitude_range_m (a floor drawn per episode: the flown geometry); "
                             f"this box's floor is fixed at {self.box_floor_alt_m:g} m")
        if not 0.0 <= self.obstacle_density_per_100m2 <= 100.0:
            raise ValueError(f"obstacle_density_per_100m2 must be in [0, 100], got {self.obstacle_density_per_100m2}")
        if not 0.0 <= self.obstacle_box_fraction <= 1.0:
            raise ValueError(f"obstacle_box_fraction must be in [0, 1], got {self.obstacle_box_fraction}")
        if not 0.0 <= self.obstacle_margin_m <= 1000.0:
            raise ValueError(f"obstacle_margin_m must be in [0, 1000], got {self.obstacle_margin_m}")
        if not 0.5 <= self.obstacle_clearance_m <= 100.0:
            raise ValueError(f"obstacle_clearance_m must be in [0.5, 100] (more than R plus a margin), "
                             f"got {self.obstacle_clearance_m}")
        if not self.density > 0:
            raise ValueError(f"density must be > 0 UAV/m^3, got {self.density}")
        if self.obstacle_density is not None and not self.obstacle_density > 0:
            raise ValueError(f"obstacle_density must be > 0 UAV/m^3, got {self.obstacle_density}")
        if not self.circle_radius_m > 0:
            raise ValueError(f"circle radius must be > 0 m, got {self.circle_radius_m}")


#: The task as flown by drone builders (issue 15): starts and goals 1.5-15 m above the ground,
#: circles at 2-15 m with radii 8-20 m, starts off by up to 0.5 m per axis.
FLOWN_ALTITUDE_RANGE_M = (1.5, 15.0)
FLOWN_CIRCLE_ALT_RANGE_M = (2.0, 15.0)
FLOWN_CIRCLE_RADIUS_RANGE_M = (8.0, 20.0)
FLOWN_START_JITTER_M = 0.5
#: ``circle-n8-scatter``'s start scatter (disc radius, m): PX4 SIH vehicles stood 0.4-3.3 m from their points on the
#: ring when their circles started before the companion kept station (docs/real_autopilots.md); GPS without RTK
#: leaves 1-3 m between vehicles on a field.
FLOWN_CIRCLE_SCATTER_M = 3.0
#: ``ScenarioConfig.low_floor_fraction``: a low-floor episode's floor lies within this many metres
#: above the lowest altitude (medium box 3.2 m tall: ~30 % of its goals then lie below 3 m).
LOW_FLOOR_BAND_M = 1.0
#: UAVs per cubic metre of the obstacle scene: sparser than the paper's ``large`` (0.04), so the
#: 8 UAVs' lines are ~4.9 m long on average (~9 m at the 99th percentile) and cross the obstacles
#: (flying straight, ~11 % of UAVs hit one).
OBSTACLE_SCENE_DENSITY = 0.03
#: The geometries a protocol or a training run names: ``paper`` (IV.B-C: 6 m floor, circle r = 12 m
#: at 10 m, 0.25 m circle jitter) and ``flown`` (above).
GEOMETRIES = ("paper", "flown")


def scenario_for(geometry: str, name: str, **values) -> ScenarioConfig:
    """The :class:`ScenarioConfig` of scenario ``name`` in ``geometry`` (``paper`` or ``flown``); ``values`` override fields."""
    if geometry == "paper":
        return ScenarioConfig(name=name, **values)
    if geometry == "flown":
        flown = dict(altitude_range_m=FLOWN_ALTITUDE_RANGE_M, start_jitter_m=FLOWN_START_JITTER_M,
                     circle_alt_range_m=FLOWN_CIRCLE_ALT_RANGE_M, circle_radius_range_m=FLOWN_CIRCLE_RADIUS_RANGE_M,
                     circle_jitter_m=FLOWN_START_JITTER_M)
        return ScenarioConfig(name=name, **(flown | values))
    raise ValueError(f"unknown geometry {geometry!r}; choose one of {', '.join(GEOMETRIES)}")


def density_from_name(density: str | float) -> float:
    """Turn ``small``/``medium``/``large`` or a number into UAVs per cubic metre."""
    if isinstance(density, str):
        if density in DENSITIES:
            return DENSITIES[density]
        try:
            density = float(density)
        except ValueError:
            raise ValueError(f"unknown density {density!r}; use {', '.join(DENSITIES)} or a number of UAV/m^3") from None
    if not density > 0:
        raise ValueError(f"density must be > 0 UAV/m^3, got {density}")
    return float(density)


@dataclass(frozen=True)
class SimConfig:
    """A batch of ``num_worlds`` independent worlds of ``num_uavs`` UAVs each."""

    num_uavs: int = 8
    num_worlds: int = 1
    scenario: ScenarioConfig = field(default_factory=ScenarioConfig)
    dynamics: str = "kinematic"
    dynamics_randomization: KinematicRandomization | None = None  # kinematic only; None: nominal
    control_period_s: float = 0.1  # one policy step; dynamics sub-step below it
    max_episode_steps: int = DEFAULT_TASK_SPEC.max_episode_steps  # 40 s at 10 Hz: > 3x the longest circle flight at full speed
    camera: CameraSpec = field(default_factory=CameraSpec)
    camera_supersample: int = 4  # sub-rays per pixel side, min-pooled (render high, pool down)
    camera_noise: StereoNoise | None = None  # None: perfect depth
    #: Remembered depth appended to each UAV's state (companion.spec.MemorySpec); None: the paper's state only.
    memory: MemorySpec | None = None
    #: Each UAV's camera mount pitch is drawn per episode uniformly within +-this many degrees of
    #: ``camera.mount_pitch_deg`` (a body-fixed camera pitches with the airframe; 0: exactly the mount).
    mount_pitch_jitter_deg: float = 0.0
    body: SceneGeometry = field(default_factory=SceneGeometry)
    collision_radius_m: float = DEFAULT_TASK_SPEC.collision_radius_m  # R: two UAVs collide when their centres are within 2R
    reward: RewardConfig = field(default_factory=RewardConfig)
    arrived: str = "hover"  # "hover": stop at the goal and stay visible; "remove": vanish
    crashed: str = "remove"  # "remove": vanish; "freeze": stay where it crashed, visible
    record_paths: bool = True  # keep every UAV's path for metrics plots (off for training)

    def __post_init__(self) -> None:
        if self.num_uavs < 1:
            raise ValueError(f"num_uavs must be >= 1, got {self.num_uavs}")
        if self.num_worlds < 1:
            raise ValueError(f"num_worlds must be >= 1, got {self.num_worlds}")
        if not self.control_period_s > 0:
            raise ValueError(f"control_period_s must be > 0, got {self.control_period_s}")
        if self.max_episode_steps < 1:
            raise ValueError(f"max_episode_steps must be >= 1, got {self.max_episode_steps}")
        if self.collision_radius_m < 0.25:
            raise ValueError(f"collision_radius_m must be a real quadrotor's (>= 0.25 m), got {self.collision_radius_m}")
        if self.arrived not in ARRIVED_BEHAVIOURS:
            raise ValueError(f"arrived must be one of {ARRIVED_BEHAVIOURS}, got {self.arrived!r}")
        if self.crashed not in CRASHED_BEHAVIOURS:
            raise ValueError(f"crashed must be one of {CRASHED_BEHAVIOURS}, got {self.crashed!r}")
        if not 0.0 <= self.mount_pitch_jitter_deg <= 30.0:
            raise ValueError(f"mount_pitch_jitter_deg must be in [0, 30] deg, got {self.mount_pitch_jitter_deg}")
        if self.dynamics not in DYNAMICS_NAMES:
            raise ValueError(f"unknown dynamics {self.dynamics!r}; choose {' or '.join(DYNAMICS_NAMES)}")
        if self.dynamics_randomization is not None and self.dynamics != "kinematic":
            raise ValueError("dynamics_randomization applies to the kinematic backend only "
                             f"(jsbsim flies its own airframe), got dynamics {self.dynamics!r}")

    def to_dict(self) -> dict:
        return asdict(self)
