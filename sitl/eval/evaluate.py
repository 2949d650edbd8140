"""``python -m sitl.swarm_test``: evaluate a policy in the paper's scenarios (paper IV.B-C).

Flies a policy file (default ``models/policy.pt``) or a reference controller in the circle
or random scenario for many episodes at once, prints the paper's metrics beside the
no-avoidance reference, and writes trajectory figures and a JSON of every metric and
per-UAV record into an output folder::

    python -m sitl.swarm_test --n 8                         # models/policy.pt, circle r = 12 m
    python -m sitl.swarm_test --policy orca --scenario random --density large
    python -m sitl.swarm_test --policy runs/x/policy.pt --episodes 200 --camera-noise
    python -m sitl.swarm_test --n 8 --mavlink               # N real companion processes over MAVLink

Controllers (``--policy``): a policy file (TorchScript, see docs/policy_file.md; it sees
only its depth camera, goal and own velocity), ``straight`` (flies straight at its goal:
what a scenario gives for free) or ``orca`` (ORCA in 3D with perfect knowledge of every
UAV: the privileged classical reference, :mod:`sitl.eval.orca`).

``--mavlink`` flies the same episodes with the whole product instead: the SITL vehicles
(``sitl.vehicle``) and one real ``companion`` process per UAV, in real time over MAVLink
(:mod:`sitl.mavlink_swarm`), and reports it beside the in-process evaluation of the same
episodes.

``python -m sitl.swarm_test paper`` reproduces the paper's Table II and Fig. 6 (resumable;
``paper --help``). Evaluation seeds are ``EVAL_SEED_OFFSET + --seed``, disjoint from
training seeds; episodes run as parallel worlds and the policy is evaluated in one batch
over every acting UAV of every world.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Protocol

import numpy as np

from companion.spec import CameraSpec
from sitl.cli_args import (
    ArgumentParser,
    MAX_THREADS,
    MAX_VEHICLES,
    float_range,
    int_range,
    output_dir,
    output_file_in_new_dir,
)

#: Bounds of the evaluation's sizes: beyond them a run would only exhaust memory or never end.
MAX_EPISODES = 1_000_000
MAX_EPISODE_STEPS = 100_000
MAX_BATCH = 10_000
MAX_RADIUS_M = 10_000.0
from sitl.sim.camera import StereoNoise
from sitl.sim.config import DENSITIES, SCENARIOS, ScenarioConfig, SimConfig, density_from_name
from sitl.sim.env import Observation, SwarmEnv
from sitl.sim.metrics import UAVRecord, summarize

# Kept equal to sitl.train.EVAL_SEED_OFFSET (a test checks it); importing sitl.train here
# would pull in tensorboard and the trainer for every evaluation.
EVAL_SEED_OFFSET = 1_000_000

DEFAULT_POLICY = Path("models/policy.pt")
BASELINES = ("straight", "orca")
#: Learning methods of Table II whose policy files ``paper`` looks for.
PAPER_METHODS = ("sac_ae", "cnn", "vae")
DEFAULT_FIG6_NS = (8, 10, 12, 14, 16, 20, 24, 28, 32)

Actor = Callable[[SwarmEnv, Observation], np.ndarray]


class EvaluationError(ValueError):
    """A request the evaluation cannot serve (missing policy, impossible scenario...), with the reason."""


# --------------------------------------------------------------------------- controllers

@dataclass
class Method:
    """Something that flies the swarm: a policy file or a reference controller."""

    label: str  # short name in tables: "straight", "orca" or the policy's method ("sac_ae")
    kind: str  # "policy" or "baseline"
    path: str | None = None  # policy file
    camera: CameraSpec | None = None  # the policy's camera: the simulated camera must match it
    control_period_s: float | None = None
    provenance: dict = field(default_factory=dict)
    _policy: object = field(default=None, repr=False)

    def info(self) -> dict:
        """What the JSON says about the controller."""
        out = {"label": self.label, "kind": self.kind}
        if self.path:
            out |= {"path": self.path, "sha256": file_digest(self.path),
                    "camera": self.camera.to_dict() if self.camera else None, "provenance": self.provenance}
        if self.kind == "baseline" and self.label == "orca":
            from sitl.eval.orca import OrcaParams

            out["orca"] = dataclasses.asdict(OrcaParams())
        return out

    def make_actor(self, env: SwarmEnv) -> Actor:
        """A function ``(env, obs) -> actions [M, 3]`` for every UAV of ``env``."""
        if self.kind == "baseline" and self.label == "straight":
            from sitl.eval.baselines import straight_to_goal

            return lambda env_, obs: straight_to_goal(obs.state, env_.action_spec)
        if self.label == "orca" and self.kind == "baseline":
            from sitl.eval.orca import OrcaController

            controller = OrcaController.for_env(env)
            return lambda env_, obs: controller.act_env(env_)
        module = _fast_module(self._policy)

        def act(env_: SwarmEnv, obs: Observation) -> np.ndarray:
            # One batch over the acting UAVs of every world: the finished ones cost nothing.
            import torch

            out = np.zeros((env_.num_agents, 3), dtype=np.float32)
            rows = np.flatnonzero(env_.acting)
            if rows.size:
                depth = torch.from_numpy(np.ascontiguousarray(obs.depth[rows], dtype=np.float32))
                state = torch.from_numpy(np.ascontiguousarray(obs.state[rows], dtype=np.float32))
                with torch.inference_mode():
                    out[rows] = module(depth, state).numpy()
            return out

        return act


def _fast_module(policy):
    """The policy's TorchScript module frozen and optimised for inference (~25 % faster on CPU).

    Falls back to the module as loaded if the optimisation fails; the output is the same
    to float32 rounding either way.
    """
    import torch

    from companion.policy import _QuietJitDeprecation

    try:
        with _QuietJitDeprecation():
            return torch.jit.optimize_for_inference(torch.jit.freeze(policy.module.eval()))
    except Exception:  # noqa: BLE001 - an optimisation, never a reason to fail
        return policy.module


def file_digest(path: str | Path) -> str:
    """First 16 hex digits of a file's SHA-256 (identifies the policy a result belongs to)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:16]


def missing_policy_message(path: str | Path) -> str:
    return (f"policy file {path} not found. Train one (python -m sitl.train, which writes RUN_DIR/policy.pt, "
            f"then copy it to {DEFAULT_POLICY}) or choose another controller: --policy straight (no avoidance), "
            "--policy orca (privileged ORCA) or --policy PATH (a policy file)")


def resolve_method(spec: str | Path) -> Method:
    """``straight``, ``orca`` or a policy file (loaded and validated) as a :class:`Method`."""
    if str(spec) in BASELINES:
        if str(spec) == "orca":
            from sitl.eval.orca import _import_rvo

            try:
                _import_rvo()
            except ImportError as err:
                raise EvaluationError(str(err)) from None
        return Method(label=str(spec), kind="baseline")
    from companion.policy import PolicyFileError, load_policy

    path = Path(spec)
    if not path.exists():
        raise EvaluationError(missing_policy_message(path))
    try:
        policy = load_policy(path)
    except PolicyFileError as err:
        raise EvaluationError(f"cannot use {path} as a policy: {err}") from None
    provenance = policy.metadata.get("provenance", {}) or {}
    label = str(provenance.get("method") or path.stem)
    return Method(label=label, kind="policy", path=str(path), camera=policy.camera,
                  control_period_s=policy.control_period_s, provenance=provenance, _policy=policy)


# --------------------------------------------------------------------------- evaluation

@dataclass(frozen=True)
class EvalSettings:
    """Which episodes to fly (the same for every controller compared)."""

    scenario: ScenarioConfig = field(default_factory=lambda: ScenarioConfig(name="circle"))
    num_uavs: int = 8
    episodes: int = 100
    seed: int = 0  # evaluation seed = EVAL_SEED_OFFSET + seed
    dynamics: str = "kinematic"
    camera_noise: bool = False
    max_episode_steps: int = 400
    batch_worlds: int = 100  # episodes flown at once (parallel worlds)
    record_paths: bool = True

    @property
    def env_seed(self) -> int:
        return EVAL_SEED_OFFSET + self.seed

    def describe(self) -> str:
        s = self.scenario
        where = f"circle r={s.circle_radius_m:g} m" if s.name == "circle" else f"random {density_label(s.density)}"
        return f"{where}, N={self.num_uavs}, {self.episodes} episodes, {self.dynamics}"


def density_label(density: float) -> str:
    """``small``/``medium``/``large`` for the named densities, else the number."""
    for name, value in DENSITIES.items():
        if math.isclose(value, density):
            return name
    return f"{density:g}/m3"


def sim_config_for(method: Method, settings: EvalSettings, num_worlds: int) -> SimConfig:
    """The simulator configuration for ``method``: its camera and control period when it is a policy."""
    extra = {}
    if method.camera is not None:
        extra["camera"] = method.camera
    if method.control_period_s is not None:
        extra["control_period_s"] = method.control_period_s
    return SimConfig(num_uavs=settings.num_uavs, num_worlds=num_worlds, scenario=settings.scenario,
                     dynamics=settings.dynamics, max_episode_steps=settings.max_episode_steps,
                     camera_noise=StereoNoise() if settings.camera_noise else None,
                     record_paths=settings.record_paths, **extra)


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


def collision_rate(summary: dict) -> float:
    """1 - success: every failure (UAV-UAV, ground, timeout), as the issue reports it."""
    if not summary.get("uav_episodes") or summary.get("success_rate") is None:
        return float("nan")
    return 1.0 - summary["success_rate"]


class StepObserver(Protocol):
    """Sees every control step of an evaluation (for analyses that need more than the records)."""

    def before_step(self, env: SwarmEnv) -> None: ...

    def after_step(self, env: SwarmEnv, info: dict) -> None: ...


def evaluate_method(method: Method, settings: EvalSettings, progress: bool = True, desc: str | None = None,
                    leave: bool = True, observer: StepObserver | None = None) -> EvalResult:
    """Fly ``settings.episodes`` episodes with ``method`` and summarise them.

    Up to ``batch_worlds`` episodes fly at once as parallel worlds (``SwarmEnv.fly_episodes``:
    a finished world starts the next episode). Scenarios come from the env's generator
    seeded with ``EVAL_SEED_OFFSET + seed``: with perfect depth every controller meets the
    same sequence of episodes (episode ``k`` is the ``k``-th drawn), the same as the
    trainer's final evaluation of that scenario. ``observer`` is called around every
    ``env.step`` (worlds that restart do so between two steps).
    """
    from tqdm import tqdm

    num_worlds = max(1, min(settings.episodes, settings.batch_worlds))
    config = sim_config_for(method, settings, num_worlds)
    env = SwarmEnv(config, seed=settings.env_seed)
    started = time.perf_counter()
    try:
        obs = env.reset()
    except ValueError as err:  # e.g. a density too high to place N UAVs 1 m apart
        raise EvaluationError(f"cannot build the scenario: {err}") from None
    actor = method.make_actor(env)
    bar = tqdm(total=settings.episodes, unit="episode", desc=desc or method.label, disable=not progress,
               file=sys.stderr, leave=leave, dynamic_ncols=True, mininterval=0.5)
    with bar:
        records = env.fly_episodes(obs, lambda o: actor(env, o), settings.episodes, observer, bar.update)
    wall = time.perf_counter() - started
    return EvalResult(method, settings, config, records, summarize(records), wall)


# --------------------------------------------------------------------------- tables

_TABLE_HEAD = ("success (± 95% CI)", "collision: all / UAV / ground / timeout", "SPL", "extra distance (m)",
               "average speed (m/s)")


def _num(value, digits: int) -> str:
    """A number for a table; '-' for a missing one (NaN, or null read back from JSON)."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.{digits}f}"


def _metric_cells(summary: dict | None, note: str = "not trained") -> list[str]:
    if summary is None:
        return [note] + ["-"] * (len(_TABLE_HEAD) - 1)
    ed, sp = summary["extra_distance_m"], summary["average_speed_m_s"]

    def mean_std(d: dict) -> str:
        return "-" if _num(d["mean"], 2) == "-" else f"{_num(d['mean'], 2)} ± {_num(d['std'], 2)}"

    half_width = summary.get("success_ci95_half_width")  # absent from cells saved before it existed
    success = _num(summary["success_rate"], 3)
    if _num(half_width, 3) != "-" and success != "-":
        success += f" ± {half_width:.3f}"
    return [
        success,
        f"{_num(collision_rate(summary), 3)} / {_num(summary['collision_uav_rate'], 3)} / "
        f"{_num(summary['collision_ground_rate'], 3)} / {_num(summary['timeout_rate'], 3)}",
        _num(summary["spl"], 3),
        mean_std(ed),
        mean_std(sp),
    ]


def markdown_table(key_names: list[str], rows: list[tuple[list[str], dict | None]]) -> str:
    """A Markdown table of summaries; a row whose summary is None reads 'not trained'.

    Columns: the key columns, success rate, collision rate (1 - success) with its split,
    SPL, extra distance and average speed as mean ± std over UAVs and episodes.
    """
    head = list(key_names) + list(_TABLE_HEAD)
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for keys, summary in rows:
        lines.append("| " + " | ".join(list(keys) + _metric_cells(summary)) + " |")
    return "\n".join(lines)


# --------------------------------------------------------------------------- command line


def _add_common(parser: argparse.ArgumentParser) -> None:
    """Options shared by the single evaluation and ``paper``."""
    parser.add_argument("--episodes", type=int_range(1, MAX_EPISODES), default=None,
                        help="episodes per evaluation (default 100; 10 with --mavlink, which flies in real time)")
    parser.add_argument("--seed", type=int_range(0), default=0,
                        help=f"evaluation seed; the simulator uses {EVAL_SEED_OFFSET} + SEED, disjoint from training")
    parser.add_argument("--dynamics", choices=("kinematic", "jsbsim"), default="kinematic",
                        help="UAV dynamics (default kinematic)")
    parser.add_argument("--camera-noise", action=argparse.BooleanOptionalAction, default=False,
                        help="stereo depth noise and dropouts (default off: perfect depth)")
    parser.add_argument("--max-steps", type=int_range(1, MAX_EPISODE_STEPS), default=400,
                        help="episode time limit in control steps (default 400 = 40 s)")
    parser.add_argument("--batch", type=int_range(1, MAX_BATCH), default=100,
                        help="episodes flown at once as parallel worlds (default 100)")
    parser.add_argument("--threads", type=int_range(1, MAX_THREADS), default=2, help="torch threads for the policy (default 2)")
    parser.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = ArgumentParser(prog="python -m sitl.swarm_test", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", default=str(DEFAULT_POLICY),
                        help=f"policy file, or a reference: {', '.join(BASELINES)} (default {DEFAULT_POLICY})")
    parser.add_argument("--n", type=int_range(1, MAX_VEHICLES), default=8, help="UAVs per world (default 8)")
    parser.add_argument("--scenario", choices=SCENARIOS, default="circle", help="scenario (default circle)")
    parser.add_argument("--density", type=_density, default="medium",
                        help=f"random scenario density: {', '.join(DENSITIES)} or UAV/m^3 (default medium)")
    parser.add_argument("--radius", type=float_range(0.0, MAX_RADIUS_M, low_open=True), default=12.0,
                        help="circle radius in m (default 12)")
    _add_common(parser)
    parser.add_argument("--out", type=output_dir, default=None,
                        help="output folder (default runs/swarm_test/<method>-<scenario>-n<N>)")
    parser.add_argument("--json", type=output_file_in_new_dir, default=None, help="also write the metrics JSON to this file")
    parser.add_argument("--no-reference", dest="reference", action="store_false",
                        help="do not fly the straight-to-goal reference beside the controller")
    parser.add_argument("--plot-episodes", type=int_range(0), default=1,
                        help="episodes to draw as trajectory figures (default 1; 0: none)")
    mav = parser.add_argument_group("the whole stack over MAVLink (--mavlink)")
    mav.add_argument("--mavlink", action="store_true",
                     help="fly the episodes with sitl.vehicle and N real companion processes in real time")
    mav.add_argument("--start", choices=("ground", "airborne"), default=None,
                     help="ground: each companion arms and takes off (--arm --takeoff); airborne: the vehicles "
                          "start hovering at the episode's start (default ground for circle, airborne for random)")
    mav.add_argument("--base-port", type=_port, default=14540, help="companion i <-> vehicle i on UDP base-port + i")
    mav.add_argument("--depth-port", type=_port, default=14640, help="vehicle i's depth frames to UDP depth-port + i")
    mav.add_argument("--gcs-port", type=_port, default=14550, help="ground-station port of every vehicle (this process)")
    args = parser.parse_args(argv)
    if args.episodes is None:
        args.episodes = 10 if args.mavlink else 100
    if args.mavlink:
        if args.policy in BASELINES:
            parser.error(f"--mavlink flies a policy file in the companion; {args.policy!r} is an in-process reference")
        if args.camera_noise:
            parser.error("--mavlink: sitl.vehicle renders perfect depth; --camera-noise is in-process only")
        if args.start is None:
            args.start = "ground" if args.scenario == "circle" else "airborne"
        if args.start == "ground" and args.scenario == "random":
            parser.error("--start ground needs the circle scenario: random starts can be stacked vertically within "
                         "2R, so climbing from the ground below them would collide; use --start airborne")
        ports = {"--base-port": args.base_port, "--depth-port": args.depth_port}
        for name, first in ports.items():
            if first + args.n > 65536:
                parser.error(f"{name} {first} + {args.n} vehicles runs past port 65535")
        blocks = [(args.base_port, args.base_port + args.n), (args.depth_port, args.depth_port + args.n),
                  (args.gcs_port, args.gcs_port + 1)]
        for a, (lo, hi) in enumerate(blocks):
            for lo2, hi2 in blocks[a + 1:]:
                if lo < hi2 and lo2 < hi:
                    free = max(hi for _, hi in blocks)
                    parser.error(f"port ranges overlap: base {args.base_port}..{args.base_port + args.n - 1}, depth "
                                 f"{args.depth_port}..{args.depth_port + args.n - 1}, gcs {args.gcs_port} (with more "
                                 f"than 10 UAVs the default GCS port 14550 is inside the base range: e.g. "
                                 f"--gcs-port {free})")
        args.batch = max(args.batch, args.episodes)  # the in-process run then meets exactly the same episodes
    try:
        density = density_from_name(args.density)
        args.scenario_config = ScenarioConfig(name=args.scenario, density=density, circle_radius_m=args.radius)
    except ValueError as err:
        parser.error(str(err))
    args.parser = parser
    return args


def _density(text: str) -> str:
    """A density name or a finite number of UAV/m^3 > 0 (kept as text: reports name it as given)."""
    try:
        value = density_from_name(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"density must be a finite number of UAV/m^3, got {text!r}")
    return text


def _port(text: str) -> int:
    if not text.isdigit() or not 1024 <= int(text) <= 65535:
        raise argparse.ArgumentTypeError(f"port must be a number in 1024..65535, got {text!r}")
    return int(text)


def _scenario_tag(scenario: ScenarioConfig) -> str:
    if scenario.name == "circle":
        return f"circle-r{scenario.circle_radius_m:g}"
    return f"random-{density_label(scenario.density).replace('/', '')}"


def _json_safe(value):
    """NaN/inf (e.g. the extra distance when no UAV succeeded) as null: strict JSON for any reader."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


def _write_json(path: Path, data: dict) -> None:
    """Write atomically: an interrupted run never leaves half a file (``paper`` resumes from them)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(_json_safe(data), indent=1, allow_nan=False))
    os.replace(tmp, path)


def run_single(args: argparse.Namespace) -> int:
    """The default command: one controller (+ the straight reference) in one scenario."""
    try:
        method = resolve_method(args.policy)
    except EvaluationError as err:
        args.parser.error(str(err))
    if method.kind == "policy":
        import torch

        torch.set_num_threads(args.threads)
    settings = EvalSettings(scenario=args.scenario_config, num_uavs=args.n, episodes=args.episodes, seed=args.seed,
                            dynamics=args.dynamics, camera_noise=args.camera_noise, max_episode_steps=args.max_steps,
                            batch_worlds=args.batch)
    methods = [method]
    if args.reference and not (method.kind == "baseline" and method.label == "straight"):
        methods.append(resolve_method("straight"))
    results: list[EvalResult] = []
    try:
        for m in methods:
            results.append(evaluate_method(m, settings, progress=args.progress))
    except EvaluationError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2

    default_name = f"{method.label}-{_scenario_tag(settings.scenario)}-n{settings.num_uavs}"
    out = args.out or Path("runs/swarm_test") / (default_name + ("-mavlink" if args.mavlink else ""))
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        print(f"error: cannot create the output folder {out}: {err.strerror}", file=sys.stderr)
        return 2
    mavlink_info = None
    if args.mavlink:
        try:
            mav_result, mavlink_info = _run_over_mavlink(args, method, settings, results[0], out)
        except Exception as err:  # noqa: BLE001 - reported with its reason; every process is already stopped
            from sitl.mavlink_swarm import MavlinkSwarmError

            if not isinstance(err, (MavlinkSwarmError, OSError, ValueError)):
                raise
            print(f"error: MAVLink evaluation stopped: {err}", file=sys.stderr)
            return 1
        results.insert(0, mav_result)
    main_result = results[0]
    figures = []
    if args.plot_episodes:
        from sitl.eval.plots import plot_trajectories

        episodes = sorted({r.episode for r in main_result.records})[: args.plot_episodes]
        for k, episode in enumerate(episodes):
            name = "trajectories.png" if k == 0 else f"trajectories_ep{episode}.png"
            figures.append(plot_trajectories(main_result.records, out / name,
                                             f"{method.label}, {settings.describe()}", episode=episode))
    data = {
        "command": " ".join(["python -m sitl.swarm_test", *args.argv]),
        "settings": {**dataclasses.asdict(settings), "eval_seed": settings.env_seed},
        "config": main_result.sim_config.to_dict(),
        **main_result.to_json(),
        # The reference's records without paths: they would double the file for no figure.
        "references": {r.method.label: r.to_json(with_paths=False) for r in results[1:]},
    }
    if mavlink_info is not None:
        data["mavlink"] = mavlink_info
    metrics_path = out / "metrics.json"
    try:
        _write_json(metrics_path, data)
        if args.json:
            _write_json(args.json, data)
    except OSError as err:  # e.g. the disk filled during the run
        print(f"error: cannot write the metrics: {err}", file=sys.stderr)
        return 1

    rows = [([r.method.label], r.summary) for r in results]
    print(f"\n{settings.describe()}, eval seed {settings.env_seed}")
    print(markdown_table(["method"], rows))
    for r in results:
        sim_s = sum(rec.duration_s for rec in r.records) / settings.num_uavs
        print(f"{r.method.label}: {settings.episodes} episodes in {r.wall_s:.1f} s "
              f"({r.episodes_per_s:.1f} episodes/s, ~{sim_s:.0f} swarm-seconds)")
    if mavlink_info is not None:
        agree, costs = mavlink_info["agreement"], mavlink_info["costs"]
        print(f"MAVLink vs in-process on the same episodes: success {agree['success_mavlink']:.3f} vs "
              f"{agree['success_in_process']:.3f} ({agree['success_difference_points']:+.1f} points), SPL "
              f"{agree['spl_mavlink']:.3f} vs {agree['spl_in_process']:.3f}")
        print(f"cost: companion CPU median {100 * (costs['companion_cpu_fraction_median'] or 0):.1f} % of a core, "
              f"missed control ticks {costs['missed_ticks_total']} of "
              f"{costs['missed_ticks_total'] + costs['policy_steps_total']}, frame-to-setpoint p99 median "
              f"{costs['frame_to_setpoint_p99_ms_median']} ms, world CPU median "
              f"{100 * (costs['world_cpu_fraction_median'] or 0):.1f} %; logs in {out / 'episodes'}")
    names = [p.name for p in figures] + [metrics_path.name]
    print(f"output folder {out}: {', '.join(names)}" + (f"; metrics also in {args.json}" if args.json else ""))
    return 0


def _run_over_mavlink(args: argparse.Namespace, method: Method, settings: EvalSettings, in_process: EvalResult,
                      out: Path) -> tuple[EvalResult, dict]:
    """Fly the evaluation's episodes with the real processes (:mod:`sitl.mavlink_swarm`).

    Returns the MAVLink result and what the JSON says about it: settings, costs, each
    episode's processes, and the agreement with ``in_process`` (same policy, same episodes).
    """
    from sitl.mavlink_swarm import MavlinkSettings, evaluate_over_mavlink
    from sitl.sim.scenarios import sample_scenario

    # The in-process evaluation draws its episodes in this order from this seed, so both
    # runs meet the same starts and goals.
    rng = np.random.default_rng(settings.env_seed)
    samples = [sample_scenario(settings.num_uavs, settings.scenario, rng) for _ in range(settings.episodes)]
    sim_config = in_process.sim_config
    camera = sim_config.camera
    mav_settings = MavlinkSettings(
        policy_path=str(method.path), start=args.start, base_port=args.base_port, depth_port=args.depth_port,
        gcs_port=args.gcs_port, dynamics=settings.dynamics, camera_size=(camera.width, camera.height),
        hfov_deg=camera.hfov_deg, max_range_m=camera.max_range_m,
        time_limit_s=settings.max_episode_steps * sim_config.control_period_s)
    evaluation = evaluate_over_mavlink(samples, mav_settings, out, progress=args.progress)
    label = f"{method.label} (MAVLink)"
    result = EvalResult(replace(method, label=label), settings, sim_config, evaluation.records,
                        summarize(evaluation.records), evaluation.wall_s)
    ours, theirs = result.summary, in_process.summary
    info = {
        "agreement": {"success_mavlink": ours["success_rate"], "success_in_process": theirs["success_rate"],
                      "success_difference_points": 100.0 * (ours["success_rate"] - theirs["success_rate"]),
                      "spl_mavlink": ours["spl"], "spl_in_process": theirs["spl"]},
        "settings": dataclasses.asdict(mav_settings),
        "costs": evaluation.costs(),
        "episodes": [{"episode": k, "wall_s": round(e.wall_s, 2), "ready_s": round(e.ready_s, 2),
                      "companions": e.companions, "world": e.world} for k, e in enumerate(evaluation.episodes)],
    }
    return result, info


# --------------------------------------------------------------------------- paper

def parse_policies(text: str) -> dict[str, Path]:
    """``sac_ae=PATH,cnn=PATH`` -> paths, defaulting to ``models/policy_<method>.pt``.

    sac_ae, when not given and ``models/policy_sac_ae.pt`` does not exist, falls back to
    the bundled ``models/policy.pt`` (the project's SAC+AE policy).
    """
    paths = {m: Path(f"models/policy_{m}.pt") for m in PAPER_METHODS}
    given = set()
    for item in filter(None, (s.strip() for s in text.split(","))):
        name, sep, value = item.partition("=")
        if not sep or not value:
            raise ValueError(f"--policies items are METHOD=PATH, got {item!r}")
        if name not in PAPER_METHODS:
            raise ValueError(f"--policies: unknown method {name!r}; the paper's methods are {', '.join(PAPER_METHODS)}")
        paths[name] = Path(value)
        given.add(name)
    if "sac_ae" not in given and not paths["sac_ae"].exists() and DEFAULT_POLICY.exists():
        paths["sac_ae"] = DEFAULT_POLICY
    return paths


def _int_list(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not values or min(values) < 1 or max(values) > MAX_VEHICLES:
        raise argparse.ArgumentTypeError(f"expected integers in 1..{MAX_VEHICLES}, got {text!r}")
    return values


def _density_list(text: str) -> list[str]:
    names = [v.strip() for v in text.split(",") if v.strip()]
    for name in names:
        _density(name)
    if not names:
        raise argparse.ArgumentTypeError("expected at least one density")
    return names


def parse_paper_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = ArgumentParser(
        prog="python -m sitl.swarm_test paper",
        description="Reproduce the paper's Table II (random scenes x densities x methods) and Fig. 6 "
                    "(circle, success against N). One JSON per cell under OUT/cells; a cell already "
                    "computed with the same settings and policy file is skipped, so an interrupted run resumes.")
    parser.add_argument("--out", type=output_dir, default=Path("runs/paper"), help="output folder (default runs/paper)")
    parser.add_argument("--policies", default="",
                        help="METHOD=PATH,... for " + ", ".join(PAPER_METHODS) +
                             " (default models/policy_<method>.pt; a missing file is a 'not trained' row)")
    parser.add_argument("--table-n", type=int_range(1, MAX_VEHICLES), default=8, help="UAVs in the Table II scenes (default 8)")
    parser.add_argument("--densities", type=_density_list, default=list(DENSITIES),
                        help="Table II densities (default small,medium,large)")
    parser.add_argument("--ns", type=_int_list, default=list(DEFAULT_FIG6_NS),
                        help="Fig. 6 swarm sizes (default " + ",".join(map(str, DEFAULT_FIG6_NS)) + ")")
    parser.add_argument("--radius", type=float_range(0.0, MAX_RADIUS_M, low_open=True), default=12.0, help="Fig. 6 circle radius in m (default 12)")
    parser.add_argument("--table-episodes", type=int_range(1, MAX_EPISODES), default=None,
                        help="episodes per Table II cell (default 500: random-scene success differs between "
                             "methods by a few points, which 100 episodes cannot resolve; cells are cheap)")
    _add_common(parser)
    args = parser.parse_args(argv)
    if args.episodes is None:
        args.episodes = 100
    if args.table_episodes is None:
        args.table_episodes = max(500, args.episodes)
    try:
        args.policy_paths = parse_policies(args.policies)
    except ValueError as err:
        parser.error(str(err))
    return args


@dataclass
class PaperCell:
    """One evaluation of the reproduction: a method in one scene."""

    name: str  # file stem under OUT/cells
    method: str  # sac_ae, cnn, vae, orca, straight
    spec: str | None  # what resolve_method gets; None: policy file missing
    settings: EvalSettings
    plot: bool = False  # also draw the first episode's trajectories


def _cell_key(cell: PaperCell, method: Method | None) -> dict:
    """What a stored cell must match to be reused: the settings and the exact policy file."""
    s = cell.settings
    return {"method": cell.method, "scenario": dataclasses.asdict(s.scenario), "num_uavs": s.num_uavs,
            "episodes": s.episodes, "seed": s.seed, "dynamics": s.dynamics, "camera_noise": s.camera_noise,
            "max_episode_steps": s.max_episode_steps,
            "policy_sha256": file_digest(method.path) if method is not None and method.path else None}


def run_cell(cell: PaperCell, out: Path, progress: bool = True) -> tuple[dict | None, str]:
    """Evaluate one cell unless an identical one is stored; return (summary or None, status)."""
    if cell.spec is None:
        return None, "not trained"
    method = resolve_method(cell.spec)
    if method.kind == "policy" and method.provenance.get("method") not in (None, cell.method):
        print(f"warning: {method.path} was trained with method {method.provenance['method']!r} "
              f"but is evaluated as {cell.method!r}", file=sys.stderr)
    path = out / "cells" / f"{cell.name}.json"
    key = _cell_key(cell, method)
    if path.is_file():
        try:
            stored = json.loads(path.read_text())
            if stored.get("key") == key:
                return stored["summary"], "stored"
        except (json.JSONDecodeError, KeyError):
            pass  # unreadable: compute it again
    settings = replace(cell.settings, record_paths=cell.plot)
    result = evaluate_method(method, settings, progress=progress, desc=cell.name, leave=False)
    if cell.plot:
        from sitl.eval.plots import plot_trajectories

        plot_trajectories(result.records, out / "trajectories" / f"{cell.name}.png",
                          f"{cell.method}, {settings.describe()}")
    data = {"key": key, "settings": {**dataclasses.asdict(settings), "eval_seed": settings.env_seed},
            **result.to_json(with_records=False)}
    _write_json(path, data)
    return result.summary, "computed"


def paper_cells(episodes: int, seed: int, dynamics: str, camera_noise: bool, max_steps: int, batch: int,
                policy_paths: dict[str, Path], table_n: int = 8, densities: list[str] | None = None,
                ns: list[int] | None = None, radius: float = 12.0,
                table_episodes: int | None = None) -> tuple[list[PaperCell], list[PaperCell]]:
    """The cells of Table II (``table_episodes`` each, default ``episodes``) and of Fig. 6 (``episodes``)."""
    densities = list(DENSITIES) if densities is None else densities
    ns = list(DEFAULT_FIG6_NS) if ns is None else ns
    common = dict(episodes=episodes, seed=seed, dynamics=dynamics, camera_noise=camera_noise,
                  max_episode_steps=max_steps, batch_worlds=batch, record_paths=False)
    specs: dict[str, str | None] = {m: (str(p) if p.exists() else None) for m, p in policy_paths.items()}
    specs |= {"orca": "orca", "straight": "straight"}
    table = []
    for density in densities:
        scen = ScenarioConfig(name="random", density=density_from_name(density))
        for m in (*PAPER_METHODS, "orca", "straight"):
            table.append(PaperCell(f"table2-{density}-{m}", m, specs[m],
                                   EvalSettings(scenario=scen, num_uavs=table_n,
                                                **(common | {"episodes": table_episodes or episodes}))))
    fig6 = []
    circle = ScenarioConfig(name="circle", circle_radius_m=radius)
    for n in ns:
        for m in ("sac_ae", "vae", "orca", "straight"):  # the paper's Fig. 6 compares ours with RL+VAE
            fig6.append(PaperCell(f"fig6-n{n}-{m}", m, specs[m], EvalSettings(scenario=circle, num_uavs=n, **common),
                                  plot=True))
    return table, fig6


def run_paper(out: Path, table: list[PaperCell], fig6: list[PaperCell], progress: bool = True,
              policy_paths: dict[str, Path] | None = None) -> dict:
    """Evaluate every cell (skipping stored ones), then write ``paper.md``, ``paper.json`` and ``fig6_scaling.png``."""
    from tqdm import tqdm

    from sitl.eval.plots import plot_scaling

    out.mkdir(parents=True, exist_ok=True)
    summaries: dict[str, dict | None] = {}
    status: dict[str, str] = {}
    cells = table + fig6
    with tqdm(total=len(cells), unit="cell", desc="paper", disable=not progress, file=sys.stderr) as bar:
        for cell in cells:
            bar.set_postfix_str(cell.name)
            summaries[cell.name], status[cell.name] = run_cell(cell, out, progress)
            bar.update(1)

    lines = ["# Reproduction of Huang et al., Table II and Fig. 6", "",
             "Generated by `python -m sitl.swarm_test paper`. Success with the half-width of its ~95 % "
             "confidence interval (clustered by episode); other columns mean ± std over UAVs and episodes; "
             "collision = 1 - success, split into UAV-UAV, ground and timeout. `orca` is privileged "
             "(true states of all UAVs); `straight` flies at its goal without avoiding anyone.", ""]
    if cells:
        s = cells[0].settings
        lines += [f"Settings: episodes per cell: Table II {table[0].settings.episodes if table else '-'}, Fig. 6 "
                  f"{fig6[0].settings.episodes if fig6 else '-'}; evaluation seed {s.env_seed}, {s.dynamics} dynamics, "
                  f"camera noise {'on' if s.camera_noise else 'off'}, time limit {s.max_episode_steps} steps.", ""]
    if policy_paths:
        lines += ["Policy files: " + ", ".join(f"{m} = `{p}`" + ("" if p.exists() else " (not trained)")
                                              for m, p in policy_paths.items()), ""]
    if table:
        lines += [f"## Table II: random scenes, N = {table[0].settings.num_uavs}", "",
                  markdown_table(["density", "method"],
                                 [([density_label(c.settings.scenario.density), c.method], summaries[c.name])
                                  for c in table]), ""]
    scaling: dict[str, dict[int, dict]] = {}
    if fig6:
        lines += [f"## Fig. 6: circle scenario, radius {fig6[0].settings.scenario.circle_radius_m:g} m", "",
                  markdown_table(["N", "method"],
                                 [([str(c.settings.num_uavs), c.method], summaries[c.name]) for c in fig6]), "",
                  "![success rate and SPL against N](fig6_scaling.png)", ""]
        for c in fig6:
            by_n = scaling.setdefault(c.method, {})
            if summaries[c.name] is not None:
                by_n[c.settings.num_uavs] = summaries[c.name]
        plot_scaling(scaling, out / "fig6_scaling.png", "circle scenario: success and SPL against the swarm size")
    (out / "paper.md").write_text("\n".join(lines))
    _write_json(out / "paper.json", {"cells": {name: {"summary": summaries[name], "status": status[name]}
                                               for name in summaries}})
    return {"summaries": summaries, "status": status}


def paper_main(argv: list[str] | None = None) -> int:
    args = parse_paper_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    table, fig6 = paper_cells(args.episodes, args.seed, args.dynamics, args.camera_noise, args.max_steps, args.batch,
                              args.policy_paths, args.table_n, args.densities, args.ns, args.radius,
                              args.table_episodes)
    for method, path in args.policy_paths.items():
        if not path.exists():
            print(f"{method}: {path} not found, reported as 'not trained'", file=sys.stderr)
    try:
        result = run_paper(args.out, table, fig6, args.progress, args.policy_paths)
    except (EvaluationError, OSError) as err:  # OSError: the output folder became unwritable
        print(f"error: {err}", file=sys.stderr)
        return 2
    counts = {k: list(result["status"].values()).count(k) for k in ("computed", "stored", "not trained")}
    print((args.out / "paper.md").read_text())
    print(f"\ncells: {counts['computed']} computed, {counts['stored']} reused, {counts['not trained']} not trained; "
          f"wrote {args.out / 'paper.md'}, {args.out / 'paper.json'}, {args.out / 'fig6_scaling.png'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["paper"]:
        return paper_main(argv[1:])
    args = parse_args(argv)
    args.argv = argv
    if args.mavlink:
        # Ctrl-C and SIGTERM must reach the cleanup that stops the children, even when this
        # process was started with SIGINT ignored (e.g. in the background of a script).
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        return run_single(args)
    except KeyboardInterrupt:  # every child process is already stopped (sitl.mavlink_swarm)
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
