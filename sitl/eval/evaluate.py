"""The evaluation engine of ``swarm_test``: which episodes (:class:`EvalSettings`), one controller's run
(:func:`evaluate_method`, through :func:`sitl.sim.episodes.run_episodes`) and its result (:class:`EvalResult`).

Evaluation seeds are ``EVAL_SEED_OFFSET + seed``, disjoint from training seeds; episodes run as
parallel worlds and a policy is evaluated in one batch over every acting UAV of every world.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from dataclasses import dataclass, field

from companion.spec import DEFAULT_TASK_SPEC
from sitl.eval.methods import EvaluationError, Method
from sitl.eval.report import collision_rate
from companion.spec import CAMERA_PRESETS
from sitl.cli_args import fits_camera
from sitl.sim.camera import StereoNoise
from sitl.sim.config import DENSITIES, ScenarioConfig, SimConfig
from sitl.sim.dynamics import KinematicRandomization, describe_response, nominal_ranges
from sitl.sim.episodes import ScenarioError, StepObserver, run_episodes
from sitl.sim.metrics import UAVRecord, summarize
from sitl.sim.scenarios import EVAL_SEED_OFFSET

@dataclass(frozen=True)
class EvalSettings:
    """Which episodes to fly (the same for every controller compared)."""

    scenario: ScenarioConfig = field(default_factory=lambda: ScenarioConfig(name="circle"))
    num_uavs: int = 8
    episodes: int = 100
    seed: int = 0  # evaluation seed = EVAL_SEED_OFFSET + seed
    dynamics: str = "kinematic"
    camera_noise: bool = False
    noise_model: StereoNoise = field(default_factory=StereoNoise)  # the camera's errors when camera_noise is on
    camera: str | None = None  # camera preset (companion.spec.CAMERA_PRESETS); None: the policy's own, or paper
    max_episode_steps: int = DEFAULT_TASK_SPEC.max_episode_steps
    batch_worlds: int = 100  # episodes flown at once (parallel worlds)
    record_paths: bool = True
    #: Each UAV's velocity response drawn per UAV and episode from these ranges (kinematic only; ``swarm_test
    #: --response``); None: every UAV flies the nominal one.
    response: KinematicRandomization | None = None

    @property
    def env_seed(self) -> int:
        return EVAL_SEED_OFFSET + self.seed

    def describe(self) -> str:
        s = self.scenario
        if s.name == "circle":
            radius = "{:g}-{:g}".format(*s.circle_radius_range_m) if s.circle_radius_range_m else f"{s.circle_radius_m:g}"
            alt = "{:g}-{:g}".format(*s.circle_alt_range_m) if s.circle_alt_range_m else f"{s.circle_alt_m:g}"
            where = f"circle r={radius} m at {alt} m"
            if s.circle_heading != "goal":
                where += f", facing {s.circle_heading}"
        else:
            where = f"{s.name} {density_label(s.density)}"
            if s.altitude_range_m:
                where += " at {:g}-{:g} m".format(*s.altitude_range_m)
        dynamics = self.dynamics
        if self.response is not None:
            dynamics += f" (response {describe_response(self.response, nominal_ranges())})"
        return f"{where}, N={self.num_uavs}, {self.episodes} episodes, {dynamics}"


def density_label(density: float) -> str:
    """``small``/``medium``/``large`` for the named densities, else the number."""
    for name, value in DENSITIES.items():
        if math.isclose(value, density):
            return name
    return f"{density:g}/m3"


def sim_config_for(method: Method, settings: EvalSettings, num_worlds: int) -> SimConfig:
    """The simulator configuration for ``method``: its camera and control period when it is a policy."""
    extra = {}
    sensor = CAMERA_PRESETS[settings.camera] if settings.camera else None
    if method.camera is not None:
        # The simulated camera is the policy's: what the companion cuts from the sensor's wider image.
        problem = fits_camera(method.camera, sensor) if sensor is not None else None
        if problem:
            raise EvaluationError(f"{method.label}: {problem}")
        extra["camera"] = method.camera
    elif sensor is not None:
        extra["camera"] = sensor
    min_range_m = extra["camera"].min_range_m if "camera" in extra else 0.0
    if method.control_period_s is not None:
        extra["control_period_s"] = method.control_period_s
    if method.memory is not None:
        extra["memory"] = method.memory
    return SimConfig(num_uavs=settings.num_uavs, num_worlds=num_worlds, scenario=settings.scenario,
                     dynamics=settings.dynamics, max_episode_steps=settings.max_episode_steps,
                     # the noise model's "too near" cut is the simulated camera's (0 for the paper camera)
                     camera_noise=dataclasses.replace(settings.noise_model, min_range_m=max(
                         min_range_m, sensor.min_range_m if sensor else 0.0))
                     if settings.camera_noise else None,
                     record_paths=settings.record_paths, dynamics_randomization=settings.response, **extra)


@dataclass
class EvalResult:
    """One controller's evaluation."""

    method: Method
    settings: EvalSettings
    sim_config: SimConfig
    records: list[UAVRecord]
    summary: dict
    wall_s: float

    @property
    def episodes_per_s(self) -> float:
        return self.settings.episodes / self.wall_s if self.wall_s > 0 else float("inf")

    def to_json(self, with_records: bool = True, with_paths: bool = True) -> dict:
        out = {
            "method": self.method.info(),
            "summary": self.summary,
            "collision_rate": collision_rate(self.summary),
            "wall_s": round(self.wall_s, 3),
            "episodes_per_s": round(self.episodes_per_s, 3),
        }
        if with_records:
            out["records"] = [dataclasses.asdict(r) if with_paths else {**dataclasses.asdict(r), "path_ned": None}
                              for r in self.records]
        return out


def evaluate_method(method: Method, settings: EvalSettings, progress: bool = True, desc: str | None = None,
                    leave: bool = True, observer: StepObserver | None = None) -> EvalResult:
    """Fly ``settings.episodes`` episodes with ``method`` and summarise them.

    Up to ``batch_worlds`` episodes fly at once as parallel worlds (:func:`sitl.sim.episodes.run_episodes`:
    a finished world starts the next episode). Scenarios come from the env's generator
    seeded with ``EVAL_SEED_OFFSET + seed``: with perfect depth every controller meets the
    same sequence of episodes (episode ``k`` is the ``k``-th drawn) — the starts and goals of
    the trainer's final evaluation of that scenario, though the trainer flies its own time
    limit (``TrainConfig.max_episode_steps``, 200 steps by default; here 400). ``observer`` is called around every
    ``env.step`` (worlds that restart do so between two steps).
    """
    from tqdm import tqdm

    num_worlds = max(1, min(settings.episodes, settings.batch_worlds))
    config = sim_config_for(method, settings, num_worlds)
    started = time.perf_counter()
    bar = tqdm(total=settings.episodes, unit="episode", desc=desc or method.label, disable=not progress,
               file=sys.stderr, leave=leave, dynamic_ncols=True, mininterval=0.5)
    with bar:
        try:
            records = run_episodes(method.make_actor, config, settings.env_seed, settings.episodes, observer,
                                   bar.update)
        except ScenarioError as err:
            raise EvaluationError(f"cannot build the scenario: {err}") from None
    wall = time.perf_counter() - started
    return EvalResult(method, settings, config, records, summarize(records), wall)
