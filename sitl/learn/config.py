"""Configuration of a training run: :class:`TrainConfig`, the presets, and the worlds it trains in.

The agent's hyperparameters are :class:`sitl.learn.agent.AgentConfig`; :func:`resolve_configs`
applies a preset and explicit values to both (the command line, :mod:`sitl.learn.cli`, shows
the resolved values in ``--help``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from companion.governor import GOVERNOR_PRESETS, describe_presets
from companion.spec import (CAMERA_PRESETS, DEFAULT_TASK_SPEC, MAX_FRAME_STRIDE, MEMORY_MAX_STEPS, CameraSpec,
                            check_frame_ages, memory_for_steps)
from sitl.cli_args import MAX_THREADS
from sitl.eval.orca import RIGHT_HAND_PARAMS, OrcaParams
from sitl.learn.agent import METHODS, AgentConfig
from sitl.sim.camera import EDGE_HOLE_MODELS, StereoNoise
from sitl.sim.config import (CIRCLE_RADIUS_M, GEOMETRIES, LOW_FLOOR_BAND_M, OBSTACLE_SCENE_DENSITY,
                             TRAINING_SCENARIOS, RewardConfig, SimConfig, density_from_name, scenario_for)
from sitl.sim.dynamics import KinematicRandomization, parse_response

@dataclass(frozen=True)
class RecipeStage:
    """One stage of a training recipe (:mod:`sitl.learn.recipe`): a training run with these overrides.

    ``train``/``agent`` override the recipe's :class:`TrainConfig`/:class:`sitl.learn.agent.AgentConfig`
    fields (e.g. scenario mix, total updates, learning rates). ``rescore_scenes`` matter for the
    last stage only: the scenes its best snapshots are flown again in before the export, as
    ``(name, scenario, UAVs, density)`` rows of :func:`sitl.learn.rescore.scenes_of`; so do ``gates``
    (:class:`SelectionGate`), flown by every snapshot of the last stage.
    """

    name: str
    description: str
    train: dict = field(default_factory=dict)
    agent: dict = field(default_factory=dict)
    rescore_scenes: tuple = (("random-medium", "random", 8, "medium"),)
    gates: tuple[SelectionGate, ...] = ()  # last stage only: bars its snapshots must clear to be chosen


@dataclass(frozen=True)
class SelectionGate:
    """A bar every candidate of a recipe's final choice must clear, flown on the validation seeds.

    The final choice's score averages scene kinds; a target that must hold on its own (issue 15: the paper's
    circles of 8-14 UAVs >= 0.99) is a gate instead: a snapshot whose ``success`` here is below
    ``min_success`` does not compete, unless no snapshot clears it (then all compete, and the log says so).
    """

    name: str  # e.g. "paper-circle-n14"
    scenario: str  # "random", "circle" or "obstacles"
    num_uavs: int
    geometry: str  # "paper" or "flown" (sitl.sim.config.GEOMETRIES)
    camera_noise: bool
    min_success: float
    #: the gate's circles start on their ring, however the run scatters its own (``TrainConfig.circle_scatter_m``):
    #: the paper's circle is symmetric
    circle_scatter_m: float = 0.0


def _param(default, help: str):
    return field(default=default, metadata={"help": help})


class DeviceUnavailable(ValueError):
    """A run's torch device is unknown or not on this machine (a run trained on cuda, resumed on a laptop)."""


#: Where the training noise's depth edges leave holes (``StereoNoise.edge_holes``) unless ``--camera-noise-edges``
#: says otherwise: both sides of every edge, harsher than the sensor's occlusion shadow. Every recipe and result
#: so far was trained with it (docs/simulator.md "Stereo noise").
TRAINING_EDGE_HOLES = "both"


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on besides the agent's hyperparameters."""

    preset: str = _param("fast", "fast (CPU, < 2 h), flown (the task as flown: low altitudes, obstacles, randomized "
                                 "dynamics; 1024 units), flown-fast (flown in <= 45 min; the bundle's recipe), bundle-paper or paper "
                                 "(Table I literally); explicit flags override it")
    method: str = _param("sac_ae", f"learning method: {', '.join(METHODS)}")
    scenario: str = _param("random", "training scenario: random, circle or mixed (each episode one of the two)")
    circle_fraction: float = _param(0.5, "mixed scenario: probability that an episode is a circle episode")
    density: str = _param("medium", "random scenario density: small, medium, large or UAV/m^3")
    circle_radius_m: float = _param(CIRCLE_RADIUS_M, "circle scenario radius in m")
    circle_heading: str = _param("goal", "training worlds only: where circle UAVs face at the start: goal (each its "
                                         "own, the paper), common (one heading for the swarm), any (each its own "
                                         "random one) or mixed (one of the three per episode); validation and "
                                         "tests fly their own cells (docs/training.md 'Circle worlds that start on one heading')")
    circle_scatter_m: float = _param(0.0, "training and validation circles: starts moved horizontally to a uniform "
                                          "point within this many metres of the ring, goals at the nominal antipodes "
                                          "(swarm_test flown's circle-n8-scatter flies 3 m); 0: none")
    geometry: str = _param("paper", "scene geometry: paper (6 m floor, circle at 10 m) or flown (altitudes "
                                    "1.5-15 m, circles 8-20 m at 2-15 m, 0.5 m start jitter; sitl.sim.config)")
    obstacle_fraction: float = _param(0.0, "mixed scenario: probability that an episode is an obstacles episode")
    obstacle_density: str = _param("", "mixed scenario: UAV density of its obstacles episodes (small, medium, large or "
                                       "UAV/m^3; the obstacle scene that validation and swarm_test fly is "
                                       f"{OBSTACLE_SCENE_DENSITY:g}); empty: --density")
    low_floor_fraction: float = _param(0.0, "flown geometry, training worlds only: share of random/obstacle episodes "
                                            f"whose box floor is drawn within {LOW_FLOOR_BAND_M:g} m of the lowest altitude, so goals "
                                            "near the ground come up more often (validation and tests fly the "
                                            "uniform draw)")
    density_range: str = _param("", "training worlds only: LOW,HIGH densities (small, medium, large or UAV/m^3) between "
                                    "which each random episode's density is drawn log-uniformly instead of --density "
                                    "(e.g. large,small; validation and tests fly their own density); empty: --density")
    randomize_dynamics: bool = _param(False, "draw each UAV's velocity lag and acceleration limits per episode "
                                             "(sitl.sim.dynamics.KinematicRandomization)")
    velocity_lag_max_s: float = _param(0.0, "with --randomize-dynamics, training worlds only: the slowest horizontal and "
                                            "vertical velocity lag drawn, seconds (a first-order fit to PX4 SIH reads "
                                            "1.1-1.6 s, though its response is a PI loop against drag: "
                                            "docs/simulator.md); 0: KinematicRandomization's own range")
    response: str = _param("", "with --randomize-dynamics, training worlds only: response ranges layered over "
                               "KinematicRandomization's (after --velocity-lag-max-s): a preset (px4-sih: the "
                               "fitted spread of PX4 SIH's vehicles) or FIELD=LOW:HIGH items, comma-separated, as "
                               "swarm_test --response takes them (e.g. tau_horizontal_s=0.15:1,"
                               "drag_horizontal_per_s=0:0.8); empty: none")
    yaw_jitter_deg: float = _param(45.0, "random scenario: initial heading error from the goal bearing, up to +-deg")
    arrival_radius_m: float = _param(DEFAULT_TASK_SPEC.arrival_radius_m,
                                     "distance to the goal that counts as arrival (paper: 0.5 m)")
    num_uavs: int = _param(8, "UAVs per world")
    num_worlds: int = _param(4, "worlds stepped together (vectorised rollouts)")
    image_size: int = _param(32, "depth image side in pixels (the paper camera: square, 90 deg FOV)")
    camera: str = _param("paper", f"camera preset: {', '.join(CAMERA_PRESETS)} (realsense_d435: 87x58 deg, 32x20 px, "
                                  "0.2-10 m; docs/simulator.md)")
    camera_grid: str = _param("", "WIDTHxHEIGHT in pixels instead of the camera preset's own grid (a real "
                                  "sensor's field of view min-pooled to more or fewer pixels, e.g. 48x32 for "
                                  "realsense_d435; empty: the preset's; docs/training.md 'The depth image's grid')")
    camera_noise: bool = _param(False, "train with the stereo noise model (z^2 error, holes reported as 0; "
                                        "edge holes where the camera_noise_edges setting says: TRAINING_STEREO_NOISE, "
                                        "docs/simulator.md)")
    camera_noise_edges: str = _param(TRAINING_EDGE_HOLES, "with --camera-noise: where depth edges leave holes, both (both sides "
                                             "of every edge, rows and columns: every recipe so far) or shadow (the "
                                             "stereo occlusion shadow the evaluations fly; docs/training.md "
                                             "'Training with the occlusion shadow')")
    mount_pitch_jitter_deg: float = _param(0.0, "camera mount pitch drawn per episode within +-deg of the mount")
    governor: bool = _param(False, "fly the companion's speed governor (companion.governor, default settings) after "
                                   "the policy in training, validation and the final choice; the exported policy.json "
                                   "records it and swarm_test and the companion then apply it (docs/training.md "
                                   "'Training with the governor in the loop')")
    governor_setting: str = _param("default", "with governor: its named settings (companion.governor."
                                              f"GOVERNOR_PRESETS): {describe_presets()}")
    flight_governor_setting: str = _param("", "with governor: the named settings the exported policy flies with "
                                              "(policy.json), which validation, the snapshot choice and the final "
                                              "evaluation fly too; the training rollouts keep governor_setting "
                                              "(e.g. the climb cap's setting after training with swarm); empty: "
                                              "governor_setting (docs/training.md 'The climb cap in the loop')")
    frame_stride: int = _param(1, "control steps between two of the 3 stacked depth frames (1: consecutive, the "
                                  "paper; 3: the stack spans 0.6 s; docs/training.md 'A frame stack spanning longer')")
    frame_ages: str = _param("", "age in control steps of each of the 3 stacked frames, oldest first, ending in 0, "
                                 "e.g. 3,1,0 (ticks t-3, t-1, t); replaces --frame-stride; empty: --frame-stride "
                                 "(docs/training.md 'A stack with both spans')")
    memory_steps: int = _param(0, "remembered depth (companion.spec.MemorySpec, not in the paper): the policy also "
                                  "sees the nearest point its camera showed in the last this many control steps, "
                                  "per direction sector around it (10: 1 s); 0: off (docs/training.md "
                                  "'Remembered depth')")
    memory_outside_view: bool = _param(False, "with --memory-steps: the sectors count only remembered points "
                                              "outside the camera's view now (docs/training.md 'Remembered depth')")
    avoid_counts_ground: bool = _param(False, "eq. 4's d_min counts the ground, as in the paper (default: UAVs and "
                                              "obstacles only; docs/training.md)")
    collision_reward: float = _param(RewardConfig.r_collision,
                                     "eq. 4's r_collision, the reward of the step a UAV collides (paper: -10; "
                                     "docs/training.md 'The collision reward')")
    uav_collision_extra_reward: float = _param(RewardConfig.r_collision_uav_extra,
                                               "added to r_collision when a UAV hits another UAV (paper: 0; "
                                               "docs/training.md 'The collision reward')")
    avoid_weight: float = _param(RewardConfig.w_avoid,
                                 "eq. 4's w_avoid: reward per step and per metre that the nearest UAV or obstacle in "
                                 "view is closer than d_safe (paper: -0.05)")
    blind_motion_reward: float = _param(RewardConfig.w_blind,
                                        "reward per step and per m/s of speed while the UAV's velocity points "
                                        "outside its camera's view (paper: 0; docs/training.md 'Flying where the "
                                        "camera looks')")
    corridor_speed_reward: float = _param(RewardConfig.w_corridor,
                                          "reward per step and per m/s of forward command above the speed governor's "
                                          "cap on the new depth frame (paper: 0; docs/training.md 'A price on "
                                          "outrunning the corridor')")
    max_episode_steps: int = _param(200, "episode time limit in 0.1 s steps of training and of the trainer's own "
                                         "evaluations (validation unless --validation-steps, rescoring and "
                                         "policy.json's final evaluation unless the recipe sets its own); "
                                         "swarm_test flies its own --max-steps (default "
                                         f"{DEFAULT_TASK_SPEC.max_episode_steps})")
    validation_steps: int = _param(0, "time limit of the periodic validations in 0.1 s steps (0: max_episode_steps); "
                                      "the flown circles of up to 20 m radius need the protocol's 400 to be "
                                      "scored at all (docs/training.md 'From the distilled student to SAC')")
    batch_size: int = _param(128, "Table I: batch size")
    replay_capacity: int = _param(50_000, "transitions kept (Table I: 20000)")
    precollision_steps: int = _param(0, "mark each UAV's last this many transitions before a collision in the replay "
                                        "buffer (0: none; docs/training.md 'Replaying the approach to a collision')")
    precollision_fraction: float = _param(0.0, "share of every batch drawn from the marked transitions (0: uniform "
                                               "batches, as in the paper)")
    max_episodes: int = _param(0, "stop after this many world episodes (0: no limit; Table I: 200)")
    total_updates: int = _param(25_000, "stop after this many gradient updates (0: no limit)")
    updates_per_episode: int = _param(0, "updates owed per finished world episode (Table I: 400)")
    updates_per_env_step: float = _param(1.0, "updates owed per vectorised environment step")
    init_steps: int = _param(2_000, "transitions of uniform random actions before learning starts")
    eval_every_updates: int = _param(2_500, "validate the deterministic policy every so many updates (0: never)")
    eval_episodes: int = _param(20, "episodes per periodic validation (validation seeds, disjoint from training and test)")
    select_best: bool = _param(False, "keep the networks of every validation and export the best one (highest mean "
                                      "validation success over the evaluation scenarios; later wins ties)")
    final_eval_episodes: int = _param(500, "episodes of the final evaluation recorded in policy.json (the random scene's success needs ~500 for +-1 point)")
    checkpoint_every_s: float = _param(300.0, "seconds between checkpoints")
    seed: int = _param(0, "seed of the environment, the buffer and torch")
    device: str = _param("cpu", "torch device: cpu or cuda")
    threads: int = _param(2, "torch intra-op threads")
    run_dir: str = _param("", "run directory (default runs/<method>-<scenario>-<density>-s<seed>-<time>)")
    vae_policy: str = _param("", "vae method: policy.pt that flies while depth images are collected")
    vae_images: int = _param(20_000, "vae method: stacked depth images to collect")
    vae_epochs: int = _param(20, "vae method: training epochs of the VAE")
    teacher_bc_weight: float = _param(0.0, "weight of a behaviour-cloning term in the actor loss that pulls the actor's "
                                      "mean action towards privileged ORCA's (a teacher that knows every UAV and "
                                      "obstacle; circle worlds excluded: its circle manoeuvre needs UAVs out of "
                                      "view), in units of the critic's mean |Q| (at least 1); 0: the paper's "
                                      "SAC+AE (docs/training.md 'Teacher-guided SAC+AE')")
    circle_teacher_right: bool = _param(False, "with a teacher (distill, teacher_bc_weight): circle worlds are "
                                        "labelled by ORCA that knows only the UAVs in its camera's view and keeps "
                                        "right of those closing in (a convention the camera can explain, "
                                        "sitl.eval.orca.RIGHT_HAND_PARAMS) instead of privileged ORCA (distill) or "
                                        "no label (SAC's teacher pull)")
    circle_teacher_right_deg: float = _param(RIGHT_HAND_PARAMS.right_hand_deg,
                                             "with circle_teacher_right: how far that teacher turns its preferred "
                                             "velocity to the right, in degrees (0-90; 80 keeps scattered circles "
                                             "apart: docs/training.md 'A wider roundabout for scattered circles')")
    distill_data_scale: float = _param(1.0, "distill stages only: this many times the labelled transitions per update "
                                            "(updates_per_env_step divided by it) and a replay buffer this many times "
                                            "larger, so it spans the same number of episodes (session 32: the student "
                                            "is short of data; docs/training.md 'Twice the student's data')")
    teacher_camera_limited: bool = _param(False, "with a teacher (distill, teacher_bc_weight): the worlds other than "
                                          "circles are labelled by ORCA that knows only the UAVs in each UAV's camera "
                                          "view and still sees the obstacles (the camera limited ORCA reference, plus obstacles) "
                                          "instead of privileged ORCA that knows every UAV")
    teacher_time_horizon_s: float = _param(OrcaParams.time_horizon_s, "with a teacher: the look-ahead of the ORCA that labels the worlds other "
                                           "than circles, in seconds (sitl.eval.orca.OrcaParams.time_horizon_s; a longer "
                                           "one reacts earlier, while a neighbour is farther away and more often in view)")
    teacher_radius_margin_m: float = _param(OrcaParams.radius_margin_m, "with a teacher: the margin over the collision radius R that this ORCA "
                                            "keeps, in metres (sitl.eval.orca.OrcaParams.radius_margin_m)")
    teacher_bc_updates: int = _param(0, "the teacher's weight falls linearly to 0 over this many updates, counted "
                                        "from the first stage of a recipe (0: it stays constant)")
    dagger_beta_updates: int = _param(4_000, "distill method: the share of UAVs flying the teacher's command instead "
                                             "of the student's falls linearly from 1 to 0 over this many updates, "
                                             "counted from the first stage of a recipe (DAgger's beta)")
    init_from: str = _param("", "start from the networks of another run (a curriculum stage): its directory or "
                                "checkpoint.pt (optimiser states carried over) or a validated snapshot "
                                "snapshots/agent_<updates>.pt; its updates and wall time count in this run's provenance")

    def time_limit(self, evaluation_steps: int | None = None) -> int:
        """An evaluation's time limit in steps: ``evaluation_steps`` when given, else the training episodes'."""
        return evaluation_steps or self.max_episode_steps

    def validation_time_limit(self) -> int:
        """The periodic validations' time limit in steps: ``validation_steps``, else the training episodes'."""
        return self.time_limit(self.validation_steps or None)

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ValueError(f"unknown preset {self.preset!r}; choose one of {', '.join(PRESETS)}")
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; choose one of {', '.join(METHODS)}")
        if self.scenario not in TRAINING_SCENARIOS:
            raise ValueError(f"unknown scenario {self.scenario!r}; choose one of {', '.join(TRAINING_SCENARIOS)}")
        if not 0.0 <= self.circle_fraction <= 1.0:
            raise ValueError(f"circle_fraction must be in [0, 1], got {self.circle_fraction}")
        if not 0.0 <= self.obstacle_fraction <= 1.0 - self.circle_fraction:
            raise ValueError(f"obstacle_fraction must be in [0, 1 - circle_fraction], got {self.obstacle_fraction}")
        if self.camera_noise_edges not in EDGE_HOLE_MODELS:
            raise ValueError(f"unknown camera_noise_edges {self.camera_noise_edges!r}; "
                             f"choose one of {', '.join(EDGE_HOLE_MODELS)}")
        if self.geometry not in GEOMETRIES:
            raise ValueError(f"unknown geometry {self.geometry!r}; choose one of {', '.join(GEOMETRIES)}")
        if not 0.0 <= self.circle_scatter_m <= 10.0:
            raise ValueError(f"circle_scatter_m must be in [0, 10] m, got {self.circle_scatter_m}")
        if self.velocity_lag_max_s and not (KinematicRandomization().tau_horizontal_s[0] < self.velocity_lag_max_s <= 5.0):
            raise ValueError(f"velocity_lag_max_s must be 0 (the default range) or in "
                             f"({KinematicRandomization().tau_horizontal_s[0]:g}, 5] s, got {self.velocity_lag_max_s}")
        if self.response:
            if not self.randomize_dynamics:
                raise ValueError("response needs randomize_dynamics (--randomize-dynamics): it widens that draw")
            parse_response(self.response, KinematicRandomization())  # a bad item fails here, before the run
        # The scenario checks low_floor_fraction (its range, and a floor drawn per episode): here, so a
        # bad flag fails before the run starts.
        scenario = scenario_for(self.geometry, "random", low_floor_fraction=self.low_floor_fraction,
                                density_range=parse_density_range(self.density_range),
                                circle_heading=self.circle_heading)
        if scenario.density_range is not None:  # both ends must make a box the episodes fit in
            from sitl.sim.scenarios import sample_random

            for density in scenario.density_range:
                try:
                    sample_random(self.num_uavs, dataclasses.replace(scenario, density=density, density_range=None),
                                  np.random.default_rng(0))
                except ValueError as err:
                    raise ValueError(f"density_range: at {density:g} UAV/m^3 {err}") from None
        if not math.isfinite(density_from_name(self.density)):
            raise ValueError(f"density must be a finite number of UAV/m^3, got {self.density!r}")
        if self.obstacle_density:
            try:
                finite = math.isfinite(density_from_name(self.obstacle_density))
            except ValueError as err:
                raise ValueError(f"obstacle_density: {err}") from None
            if not finite:
                raise ValueError(f"obstacle_density must be a finite number of UAV/m^3, got {self.obstacle_density!r}")
        # Integer ranges: the upper ends keep a typo from allocating (or promising) the impossible.
        for name, low, high in TRAIN_INT_RANGES:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise ValueError(f"{name} must be an integer in {low}..{high}, got {value!r}")
        # Float ranges written so that NaN fails them too.
        if not 0.0 < self.arrival_radius_m <= 100.0:
            raise ValueError(f"arrival_radius_m must be in (0, 100], got {self.arrival_radius_m}")
        if not 0.0 < self.circle_radius_m <= 10_000.0:
            raise ValueError(f"circle_radius_m must be in (0, 10000], got {self.circle_radius_m}")
        if self.camera not in CAMERA_PRESETS:
            raise ValueError(f"unknown camera {self.camera!r}; choose one of {', '.join(CAMERA_PRESETS)}")
        if not 0.0 <= self.mount_pitch_jitter_deg <= 30.0:
            raise ValueError(f"mount_pitch_jitter_deg must be in [0, 30], got {self.mount_pitch_jitter_deg}")
        if not 0.0 <= self.yaw_jitter_deg <= 180.0:
            raise ValueError(f"yaw_jitter_deg must be in [0, 180], got {self.yaw_jitter_deg}")
        if not 0.0 <= self.precollision_fraction <= 1.0:
            raise ValueError(f"precollision_fraction must be in [0, 1], got {self.precollision_fraction}")
        if self.precollision_fraction > 0 and self.precollision_steps == 0:
            raise ValueError("precollision_fraction > 0 needs precollision_steps > 0 (no transition would be marked)")
        if not 0.0 <= self.updates_per_env_step <= 10_000.0:
            raise ValueError(f"updates_per_env_step must be in [0, 10000], got {self.updates_per_env_step}")
        if not 1.0 <= self.distill_data_scale <= 64.0:
            raise ValueError(f"distill_data_scale must be in [1, 64], got {self.distill_data_scale}")
        if not -1_000.0 <= self.collision_reward <= 0.0:
            raise ValueError(f"collision_reward must be in [-1000, 0], got {self.collision_reward}")
        if not -1_000.0 <= self.uav_collision_extra_reward <= 0.0:
            raise ValueError(f"uav_collision_extra_reward must be in [-1000, 0], got {self.uav_collision_extra_reward}")
        if not -10.0 <= self.avoid_weight <= 0.0:
            raise ValueError(f"avoid_weight must be in [-10, 0], got {self.avoid_weight}")
        if not -10.0 <= self.blind_motion_reward <= 0.0:
            raise ValueError(f"blind_motion_reward must be in [-10, 0], got {self.blind_motion_reward}")
        if not -10.0 <= self.corridor_speed_reward <= 0.0:
            raise ValueError(f"corridor_speed_reward must be in [-10, 0], got {self.corridor_speed_reward}")
        if not 0.0 <= self.teacher_bc_weight <= 100.0:
            raise ValueError(f"teacher_bc_weight must be in [0, 100], got {self.teacher_bc_weight}")
        if self.memory_outside_view and not self.memory_steps:
            raise ValueError("memory_outside_view needs remembered depth: set memory_steps (e.g. 10)")
        try:  # OrcaParams holds the angle's bounds
            OrcaParams(right_hand_deg=self.circle_teacher_right_deg)
        except ValueError as err:
            raise ValueError(f"circle_teacher_right_deg: {err}") from None
        if self.circle_teacher_right_deg != RIGHT_HAND_PARAMS.right_hand_deg and not self.circle_teacher_right:
            raise ValueError("circle_teacher_right_deg sets the circle teacher's turn: it needs circle_teacher_right "
                             "(the flown-distill preset has it)")
        if self.circle_teacher_right and self.method != "distill" and self.teacher_bc_weight <= 0:
            raise ValueError("circle_teacher_right needs a teacher: the distill method or teacher_bc_weight > 0")
        if self.governor_setting not in GOVERNOR_PRESETS:
            raise ValueError(f"unknown governor_setting {self.governor_setting!r}; choose one of "
                             f"{', '.join(GOVERNOR_PRESETS)}")
        if self.flight_governor_setting and self.flight_governor_setting not in GOVERNOR_PRESETS:
            raise ValueError(f"unknown flight_governor_setting {self.flight_governor_setting!r}; choose one of "
                             f"{', '.join(GOVERNOR_PRESETS)}")
        if self.flight_governor_setting and not self.governor:
            raise ValueError("flight_governor_setting names the governor the policy flies with: it needs governor")
        if self.teacher_camera_limited and self.method != "distill" and self.teacher_bc_weight <= 0:
            raise ValueError("teacher_camera_limited needs a teacher: the distill method or teacher_bc_weight > 0")
        if not (0.5 <= self.teacher_time_horizon_s <= 20.0):
            raise ValueError(f"teacher_time_horizon_s must be in [0.5, 20] s, got {self.teacher_time_horizon_s}")
        if not (0.0 <= self.teacher_radius_margin_m <= 3.0):
            raise ValueError(f"teacher_radius_margin_m must be in [0, 3] m, got {self.teacher_radius_margin_m}")
        if self.method == "distill" and self.teacher_bc_weight > 0:
            raise ValueError("teacher_bc_weight is SAC's behaviour-cloning term; the distill method is all teacher already")
        if not 0.0 < self.checkpoint_every_s < math.inf:
            raise ValueError(f"checkpoint_every_s must be a finite number > 0, got {self.checkpoint_every_s}")
        try:
            torch.device(self.device)
        except RuntimeError:
            raise DeviceUnavailable(f"unknown torch device {self.device!r}; use cpu or cuda") from None
        if self.frame_ages:
            parse_frame_ages(self.frame_ages)  # raises ValueError naming the problem
            if self.frame_stride != 1:
                raise ValueError(f"frame_ages {self.frame_ages!r} replace frame_stride; leave frame_stride at 1, "
                                 f"got {self.frame_stride}")
        if self.camera_grid:
            parse_camera_grid(self.camera_grid)  # raises ValueError naming the problem
            if self.camera == "paper":
                raise ValueError(f"camera_grid {self.camera_grid!r} is for a real sensor's preset; "
                                 f"the paper camera's grid is image_size ({self.image_size})")
        if self.image_size < 16:
            raise ValueError(f"image_size must be >= 16 (the encoder shrinks it by 14 pixels), got {self.image_size}")
        if self.max_episodes <= 0 and self.total_updates <= 0:
            raise ValueError("set max_episodes or total_updates: the run needs an end")
        if self.updates_per_episode <= 0 and self.updates_per_env_step <= 0:
            raise ValueError("set updates_per_episode or updates_per_env_step: the run needs updates")
        if self.device.startswith("cuda") and not torch.cuda.is_available():
            raise DeviceUnavailable("--device cuda asked for, but torch sees no CUDA device")


#: (field, lowest, highest) of TrainConfig's integers.
TRAIN_INT_RANGES = (
    ("num_uavs", 1, 1000), ("num_worlds", 1, 1000), ("image_size", 1, 256), ("max_episode_steps", 1, 100_000),
    ("validation_steps", 0, 100_000), ("memory_steps", 0, MEMORY_MAX_STEPS),
    ("frame_stride", 1, MAX_FRAME_STRIDE), ("batch_size", 1, 100_000), ("replay_capacity", 1, 10_000_000),
    ("precollision_steps", 0, 1000), ("max_episodes", 0, 10**9),
    ("total_updates", 0, 10**9), ("updates_per_episode", 0, 1_000_000), ("init_steps", 0, 10**9),
    ("eval_every_updates", 0, 10**9), ("eval_episodes", 1, 1_000_000), ("final_eval_episodes", 0, 1_000_000),
    ("seed", 0, 2**32 - 1), ("threads", 1, MAX_THREADS), ("vae_images", 1, 10_000_000), ("vae_epochs", 1, 100_000),
    ("teacher_bc_updates", 0, 10**9), ("dagger_beta_updates", 0, 10**9),
)

#: The camera noise of training and of the trainer's own validations (``--camera-noise``): the sensor's
#: (:class:`sitl.sim.camera.StereoNoise`) with the edge holes of ``--camera-noise-edges`` (by default on both
#: sides of every depth edge, harsher than the occlusion shadow the evaluations fly; it stays so that every
#: recipe reproduces; docs/simulator.md "Stereo noise").
TRAINING_STEREO_NOISE = StereoNoise(edge_holes=TRAINING_EDGE_HOLES)

#: Settings that say where a run computes, not what it learns: the only ones `--resume` may change
#: (a run started on a GPU machine can be continued on a laptop).
WHERE_SETTINGS = ("device", "threads")

#: The recipe that trains the bundled models/policy.pt (models/README.md); the training benchmarks' default.
BUNDLE_PRESET = "flown-fast"

#: Each preset sets training and agent fields; explicit flags override it. The dataclass
#: defaults are the fast preset's training values and the paper's agent values.
PRESETS: dict[str, dict] = {
    # Measured choices for a 2-core CPU (docs/training.md): 32x32 images (the paper's 1024
    # hidden units stay: at 32x32 they cost only ~4 % more than 256), a lower initial temperature
    # (the reference's 0.1 is tuned for DMC rewards of ~1 per step; here progress pays
    # <= 0.6 per step and the entropy bonus drowned it) and 5-step returns (one-step targets
    # with tau 0.01 propagated the arrival reward over the ~40-step episodes too slowly).
    "fast": {"train": {}, "agent": {"init_temperature": 0.01, "n_step": 5}},
    # The task as flown (issue 15) as one recipe: the RealSense D435 camera with its noise and a
    # +-5 deg mount pitch, starts and goals 1.5-15 m above the ground, randomized dynamics, the
    # ground left out of eq. 4's d_min. Stage 1 learns to fly low among other UAVs and
    # obstacles; stage 2 adds circles (2-15 m altitude, 8-20 m radius) at the same learning
    # rate; stage 3 settles at 3e-4. Stage budgets are planned for <= 2 h on 2 cores
    # (~20k updates at ~0.25 s each at 48x32) and not yet timed end to end: time them with
    # `--recipe-scale 0.05` and benchmarks/train_speed.py before a full run.
    "flown": {
        "train": {"geometry": "flown", "camera": "realsense_d435", "camera_noise": True,
                  "mount_pitch_jitter_deg": 5.0, "randomize_dynamics": True, "avoid_counts_ground": False,
                  "eval_episodes": 40},
        "agent": {"init_temperature": 0.01, "n_step": 5},
        "recipe": {"rescore_top": 3, "rescore_episodes": 200},
        "stages": (
            RecipeStage("low-random", "random scenes at 1.5-15 m, a fifth of them among obstacles",
                        {"scenario": "mixed", "circle_fraction": 0.0, "obstacle_fraction": 0.2,
                         "total_updates": 8_000, "eval_every_updates": 2_000}),
            RecipeStage("with-circles", "30 % circles, 20 % obstacles",
                        {"scenario": "mixed", "circle_fraction": 0.3, "obstacle_fraction": 0.2,
                         "total_updates": 6_000, "eval_every_updates": 1_500}),
            RecipeStage("settle", "the same mix at learning rates 3e-4",
                        {"scenario": "mixed", "circle_fraction": 0.3, "obstacle_fraction": 0.2,
                         "total_updates": 6_000, "eval_every_updates": 1_000, "eval_episodes": 60},
                        {"actor_lr": 3e-4, "critic_lr": 3e-4, "encoder_lr": 3e-4, "decoder_lr": 3e-4},
                        rescore_scenes=(("random-medium", "random", 8, "medium"), ("circle-n8", "circle", 8, "medium"))),
        ),
    },
    # The flown recipe within 45 min on 2 cores (issue 17): the same task and the same first three
    # stages (a fourth below), with the agent's MLPs at 512 hidden units (paper: 1024) and the autoencoder
    # updated every second update (reference: every update): an update at 32x20 is 1.6x
    # cheaper (`benchmarks/train_speed.py`, docs/training.md "flown-fast"). Validation
    # is sparser and the export's evaluation shorter; `python -m sitl.swarm_test flown` is the
    # full evaluation. The final choice flies the last stage's 3 best snapshots in all three kinds
    # of scene it trains on with the protocol's 40 s limit: at flown's 20 s, circles of up to 20 m
    # radius time out on the far side and their score was noise (docs/training.md "flown-fast").
    "flown-fast": {
        "train": {"final_eval_episodes": 200},
        "agent": {"hidden_dim": 512, "decoder_update_freq": 2},
        "recipe": {"rescore_top": 3, "rescore_episodes": 100, "evaluation_steps": DEFAULT_TASK_SPEC.max_episode_steps},
        # stages: flown's, validated less often (below)
    },
    "paper": {"train": {"num_worlds": 1, "image_size": 64, "replay_capacity": 20_000, "max_episodes": 200,
                        "total_updates": 0, "updates_per_episode": 400, "updates_per_env_step": 0.0,
                        "init_steps": 1_000, "avoid_counts_ground": True},
              "agent": {}},
    # The bundled models/policy.pt's curriculum (models/README.md) as one recipe: the paper's
    # medium random scene, then mixes of random and circle episodes at falling learning rates;
    # the last stage's best snapshots are rescored on 200 validation episodes before export.
    "bundle-paper": {
        "train": {"eval_episodes": 40},
        "agent": {"init_temperature": 0.01, "n_step": 5},
        "recipe": {"rescore_top": 3, "rescore_episodes": 200},
        "stages": (
            RecipeStage("random", "paper medium random scene",
                        {"scenario": "random", "total_updates": 7_500, "eval_every_updates": 2_500}),
            RecipeStage("mixed50", "50 % circle episodes: learns the roundabout large circles need",
                        {"scenario": "mixed", "circle_fraction": 0.5, "total_updates": 5_000,
                         "eval_every_updates": 1_000, "eval_episodes": 30}),
            RecipeStage("mixed30", "30 % circles at learning rates 3e-4",
                        {"scenario": "mixed", "circle_fraction": 0.3, "total_updates": 5_000,
                         "eval_every_updates": 500, "eval_episodes": 60},
                        {"actor_lr": 3e-4, "critic_lr": 3e-4, "encoder_lr": 3e-4, "decoder_lr": 3e-4}),
            RecipeStage("mixed15", "15 % circles at learning rates 1e-4: wins back random-scene success",
                        {"scenario": "mixed", "circle_fraction": 0.15, "total_updates": 10_000,
                         "eval_every_updates": 1_000, "eval_episodes": 100},
                        {"actor_lr": 1e-4, "critic_lr": 1e-4, "encoder_lr": 1e-4, "decoder_lr": 1e-4}),
        ),
    },
}


# flown-fast flies the flown task: its training and agent values start from flown's.
PRESETS["flown-fast"]["train"] = {**PRESETS["flown"]["train"], **PRESETS["flown-fast"]["train"]}
PRESETS["flown-fast"]["agent"] = {**PRESETS["flown"]["agent"], **PRESETS["flown-fast"]["agent"]}
# Its first three stages are flown's with sparser validation, and in the third a UAV-UAV collision
# costs -50 instead of eq. 4's -10 (obstacles and the ground stay at -10): over three seeds +0.9
# points in random scenes and +3.2 among obstacles at no extra time. A fourth stage at learning
# rates 1e-4 with half of its episodes circles pulls the seeds together (paper-medium spread 5.2 ->
# 2.8 points at the same means, 3.7 over five seeds; at 30 % circles it broke one seed's circle); the final choice also
# flies obstacles (docs/training.md "The collision reward" and "Seeds").
_SCENES_FLOWN_FAST = (("random-medium", "random", 8, "medium"), ("circle-n8", "circle", 8, "medium"),
                      ("obstacles", "obstacles", 8, "medium"))
PRESETS["flown-fast"]["stages"] = tuple(
    dataclasses.replace(stage, train={**stage.train, **train}, **other)
    for stage, train, other in zip(
        PRESETS["flown"]["stages"],
        ({"eval_every_updates": 2_000}, {"eval_every_updates": 2_000},
         {"eval_every_updates": 1_500, "eval_episodes": 50, "uav_collision_extra_reward": -40.0}),
        ({}, {}, {"description": "the same mix at learning rates 3e-4, a UAV-UAV collision at -50"}))) + (
    RecipeStage("anneal", "50 % circles at learning rates 1e-4, a UAV-UAV collision at -50",
                {"scenario": "mixed", "circle_fraction": 0.5, "obstacle_fraction": 0.2, "total_updates": 6_000,
                 "eval_every_updates": 1_500, "eval_episodes": 50, "uav_collision_extra_reward": -40.0},
                {"actor_lr": 1e-4, "critic_lr": 1e-4, "encoder_lr": 1e-4, "decoder_lr": 1e-4},
                rescore_scenes=_SCENES_FLOWN_FAST),)


# The distilled student handed over to reinforcement learning (issue 17's teacher-student candidate, beside
# SAC+AE; docs/training.md "From the distilled student to SAC"): stages 1-2 are flown-fast's as the `distill`
# method with four times the labelled transitions per update (the data gained 2-4 points in session 32);
# stages 3-4 are flown-fast's as SAC on the student's convolutions, frozen (its features stay what the actor
# head was trained on; no decoder), the critic learning the handed-over policy for 1,000 updates before the
# actor moves, and the teacher's pull (weight 1; in circle worlds the keep-right teacher) kept in the actor loss: in a trial at
# 2 % of the updates, an actor free of both collapsed to 0 success within 30 updates of a cold critic.
# Reinforcement learning is what taught SAC+AE the circle, where imitating privileged ORCA failed; since
# session 39 circle worlds are taught by camera-limited ORCA keeping right, which the camera can explain.
# Stages 3-4 validate with the protocol's 40 s limit, so the circle's score is a score (at 20 s a circle of
# 20 m radius times out after any detour). The final choice flies stage 4's snapshots that clear
# PAPER_CIRCLE_GATE (about 1 minute) again on more validation episodes (about 8.5 minutes; session 67, below) and
# exports the best.
#: Stage 4 validates in the flown circle of 8, which every snapshot flies at 1.000, so its score cannot see the
#: circle; the paper's circle of 14 (12 m radius, 10 m up) is denser, and a snapshot that loses it competes no
#: more (session 43: seed 2's chosen snapshot read 0.909 there on validation, 0.894 on test seeds, where its
#: later snapshots read 1.000; 0.97 leaves room for 100 episodes' noise below issue 15's 0.99).
PAPER_CIRCLE_GATE = SelectionGate("paper-circle-n14", "circle", 14, "paper", camera_noise=False, min_success=0.97)
#: The final choice (session 67; docs/training.md "Flying every last-stage snapshot again"): every stage-4 snapshot
#: that clears the gate is flown again on 500 validation episodes of random medium and of obstacles, and the best
#: mean of the two is exported. Stage 4's own validation (50 episodes per scene) resolves success to +-3-4 points,
#: and the snapshots it chooses between differ by about one (a run's four read 0.905-0.918 on 1,000 validation
#: episodes each, and the validation had chosen the 0.905 one). The circle is left to the gate: every snapshot
#: flies the flown circle of 8 at 1.000. Until session 67 the choice flew no candidate again.
_DISTILL_RESCORE_TOP = (PRESETS["flown-fast"]["stages"][3].train["total_updates"]  # all of stage 4's snapshots
                        // PRESETS["flown-fast"]["stages"][3].train["eval_every_updates"])
_DISTILL_RESCORE_EPISODES = 500
_DISTILL_RESCORE_SCENES = (("random-medium", "random", 8, "medium"), ("obstacles", "obstacles", 8, "medium"))
_IMITATE = {"method": "distill", "updates_per_env_step": 0.25, "replay_capacity": 200_000}
_REINFORCE = {"method": "cnn", "updates_per_env_step": 1.0, "replay_capacity": 50_000, "teacher_bc_weight": 1.0,
              "teacher_bc_updates": 0, "validation_steps": DEFAULT_TASK_SPEC.max_episode_steps}
PRESETS["flown-distill"] = {
    # circle worlds taught by camera-limited ORCA keeping right (session 39: the circle of 8 at 1.000 on four
    # seeds, where privileged ORCA's labels left it to SAC and two of five seeds lost it; docs/training.md
    # "A circle teacher the camera can explain")
    "train": {**PRESETS["flown-fast"]["train"], "method": "distill", "circle_teacher_right": True},
    "agent": dict(PRESETS["flown-fast"]["agent"]),
    "recipe": {**PRESETS["flown-fast"]["recipe"], "rescore_top": _DISTILL_RESCORE_TOP,
               "rescore_episodes": _DISTILL_RESCORE_EPISODES},
    "stages": tuple(dataclasses.replace(stage, train={**stage.train, **_IMITATE}, agent={"method": "distill"},
                                        description=f"distill: {stage.description}")
                    for stage in PRESETS["flown-fast"]["stages"][:2]) + (
        dataclasses.replace(PRESETS["flown-fast"]["stages"][2], name="reinforce",
                            description="SAC on the student's frozen convolutions, the critic first: "
                                        "the same mix, actor at 3e-4 pulled towards the teachers, "
                                        "a UAV-UAV collision at -50",
                            train={**PRESETS["flown-fast"]["stages"][2].train, **_REINFORCE},
                            agent={"method": "cnn", "freeze_convs": True, "actor_delay_updates": 1_000,
                                   "actor_lr": 3e-4, "critic_lr": 1e-3}),
        dataclasses.replace(PRESETS["flown-fast"]["stages"][3],
                            description="SAC on the frozen convolutions, pulled towards the teachers: "
                                        "50 % circles at 1e-4, a UAV-UAV collision at -50",
                            train={**PRESETS["flown-fast"]["stages"][3].train, **_REINFORCE},
                            agent={**PRESETS["flown-fast"]["stages"][3].agent, "method": "cnn", "freeze_convs": True},
                            gates=(PAPER_CIRCLE_GATE,), rescore_scenes=_DISTILL_RESCORE_SCENES),
    ),
}


def resolve_configs(train_values: dict, agent_values: dict) -> tuple[TrainConfig, AgentConfig]:
    """The two configs of a run: dataclass defaults, then the preset (``train_values["preset"]``), then the values given.

    Raises:
        ValueError: an unknown preset or an invalid value (the message names it).
    """
    preset = train_values.get("preset", TrainConfig.preset)
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    train_cfg = TrainConfig(**{**PRESETS[preset]["train"], **train_values})
    agent_cfg = AgentConfig(**{**PRESETS[preset]["agent"], "method": train_cfg.method, **agent_values})
    return train_cfg, agent_cfg


def make_sim_config(cfg: TrainConfig, num_worlds: int, record_paths: bool = False,
                    scenario_name: str | None = None) -> SimConfig:
    """The worlds of ``cfg`` (``scenario_name`` overrides its scenario, e.g. for evaluation)."""
    name = scenario_name or cfg.scenario
    values = dict(density=density_from_name(cfg.density), yaw_jitter_rad=math.radians(cfg.yaw_jitter_deg),
                  circle_fraction=cfg.circle_fraction, obstacle_fraction=cfg.obstacle_fraction)
    if cfg.geometry == "paper":
        values["circle_radius_m"] = cfg.circle_radius_m  # the flown geometry draws the radius per episode
    if name == "obstacles":
        values["density"] = OBSTACLE_SCENE_DENSITY  # the obstacle scene's own spacing, as swarm_test flown flies it
    if name == "mixed" and cfg.obstacle_density:
        values["obstacle_density"] = density_from_name(cfg.obstacle_density)
    training = scenario_name is None  # randomization trains robustness; evaluations fly the nominal vehicle
    if training and cfg.low_floor_fraction > 0:
        values["low_floor_fraction"] = cfg.low_floor_fraction
    if training and cfg.circle_heading != "goal":
        values["circle_heading"] = cfg.circle_heading
    if cfg.circle_scatter_m > 0 and (training or name == "circle"):
        # validation circles scattered too: symmetric ones fly at 1.000 for every snapshot and cannot choose
        values["circle_scatter_m"] = cfg.circle_scatter_m
    if training and cfg.density_range:
        values["density_range"] = parse_density_range(cfg.density_range)
    scenario = scenario_for(cfg.geometry, name, **values)
    camera = training_camera(cfg)
    randomization = None
    if cfg.randomize_dynamics and training:
        randomization = KinematicRandomization()
        if cfg.velocity_lag_max_s > 0:
            lag = (randomization.tau_horizontal_s[0], cfg.velocity_lag_max_s)
            randomization = dataclasses.replace(randomization, tau_horizontal_s=lag, tau_vertical_s=lag)
        if cfg.response:
            randomization = parse_response(cfg.response, randomization)
    return SimConfig(num_uavs=cfg.num_uavs, num_worlds=num_worlds, scenario=scenario, camera=camera,
                     dynamics_randomization=randomization,
                     camera_noise=dataclasses.replace(TRAINING_STEREO_NOISE, min_range_m=camera.min_range_m,
                                                      edge_holes=cfg.camera_noise_edges)
                     if cfg.camera_noise else None,
                     mount_pitch_jitter_deg=cfg.mount_pitch_jitter_deg if training else 0.0,
                     memory=memory_for_steps(cfg.memory_steps, cfg.memory_outside_view),
                     max_episode_steps=cfg.max_episode_steps, record_paths=record_paths,
                     reward=RewardConfig(arrival_radius_m=cfg.arrival_radius_m, r_collision=cfg.collision_reward,
                                         r_collision_uav_extra=cfg.uav_collision_extra_reward,
                                         w_avoid=cfg.avoid_weight, w_blind=cfg.blind_motion_reward,
                                         w_corridor=cfg.corridor_speed_reward,
                                         avoid_counts_ground=cfg.avoid_counts_ground))


def parse_density_range(text: str) -> tuple[float, float] | None:
    """``"large,small"`` -> ``(0.04, 0.1)`` UAV/m^3, sorted (``ScenarioConfig.density_range``); ``""`` -> None.

    Raises:
        ValueError: not two densities separated by a comma, or one that is not a finite density.
    """
    if not text:
        return None
    parts = text.split(",")
    if len(parts) != 2:
        raise ValueError(f"density_range must be two densities such as large,small, got {text!r}")
    try:
        low, high = sorted(density_from_name(part.strip()) for part in parts)
    except ValueError as err:
        raise ValueError(f"density_range: {err}") from None
    if not math.isfinite(high):
        raise ValueError(f"density_range must be finite densities in UAV/m^3, got {text!r}")
    return low, high


def parse_frame_ages(text: str) -> tuple[int, ...]:
    """``"3,1,0"`` -> ``(3, 1, 0)``: the stacked frames' ages (``CameraSpec.frame_ages``); ``ValueError`` if bad."""
    try:
        ages = tuple(int(part) for part in text.split(","))
    except ValueError:
        raise ValueError(f"frame_ages must be comma-separated integers such as 3,1,0, got {text!r}") from None
    check_frame_ages(ages, CameraSpec().frames)
    return ages


def training_camera(cfg: TrainConfig) -> CameraSpec:
    """The camera a run trains with: its preset (the paper camera at ``image_size`` pixels a side),
    its frames stacked ``frame_stride`` steps apart (or at ``frame_ages``)."""
    stack = {"frame_stride": cfg.frame_stride, "frame_ages": parse_frame_ages(cfg.frame_ages) if cfg.frame_ages else ()}
    if cfg.camera == "paper":
        return CameraSpec(width=cfg.image_size, height=cfg.image_size, **stack)
    camera = dataclasses.replace(CAMERA_PRESETS[cfg.camera], **stack)
    if cfg.camera_grid:
        width, height = parse_camera_grid(cfg.camera_grid)
        camera = dataclasses.replace(camera, width=width, height=height)
    return camera


def parse_camera_grid(text: str) -> tuple[int, int]:
    """``"48x32"`` -> (48, 32): a depth image's width and height in pixels, each >= 16 (the encoder
    shrinks each side by 14 pixels, as it does ``image_size``).

    Raises:
        ValueError: not WIDTHxHEIGHT, or a side below 16 or above 256.
    """
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"camera_grid must be WIDTHxHEIGHT in pixels, e.g. 48x32, got {text!r}") from None
    if not (16 <= width <= 256 and 16 <= height <= 256):
        raise ValueError(f"camera_grid sides must be 16..256 pixels (the encoder shrinks each by 14), got {text!r}")
    return width, height


def evaluation_scenarios(cfg: TrainConfig) -> tuple[str, ...]:
    """The scenarios a run is validated on (and its snapshots selected by): its own, or every part
    of a mixed one that it trains on. A mix without circles is not scored on circles: in the flown
    recipe's first stage the untrained circle score fell from 0.48 to 0.26 while random and
    obstacles rose, and the mean picked the 2,000-update snapshot of 8,000."""
    if cfg.scenario != "mixed":
        return (cfg.scenario,)
    return (("random",) + (("circle",) if cfg.circle_fraction > 0 else ())
            + (("obstacles",) if cfg.obstacle_fraction > 0 else ()))
