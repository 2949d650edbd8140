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
what a scenario gives for free), ``orca`` (ORCA in 3D with perfect knowledge of every
UAV: the privileged classical reference, :mod:`sitl.eval.orca`), ``orca-fov`` (the same
ORCA knowing only the UAVs inside its own camera's view: what the field of view allows),
``orca-fov-right`` (orca-fov keeping right of the UAVs it sees closing in: a right-of-way convention; 40 deg),
``orca-fov-right80`` (the same turning 80 deg: a wider roundabout that also holds when circles start scattered),
``orca-fov-memory`` (orca-fov never forgetting a UAV it saw, tracked perfectly: what memory adds) or
``orca-fov-look-around`` (orca-fov-memory that also knows every UAV around it at the start: a look around).

``--mavlink`` flies the same episodes with the whole product instead: the SITL vehicles
(``sitl.vehicle``) and one real ``companion`` process per UAV, in real time over MAVLink
(:mod:`sitl.realtime.mavlink_swarm`), and reports it beside the in-process evaluation of the same
episodes.

``python -m sitl.swarm_test paper`` reproduces the paper's Table II and Fig. 6 (resumable;
``paper --help``); ``python -m sitl.swarm_test flown`` runs the protocol of the task as flown:
altitudes 1.5-15 m, circles of 8-20 m at 2-15 m, start jitter, obstacles, camera noise and a
JSBSim cell, success split by goal altitude (resumable; ``flown --help``). Evaluation seeds are ``EVAL_SEED_OFFSET + --seed``, disjoint from
training seeds; episodes run as parallel worlds and the policy is evaluated in one batch
over every acting UAV of every world.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import signal
import sys
from pathlib import Path

from companion.face_goal import DEFAULT_FACE_GOAL_S, FaceGoalSpec, add_face_goal_argument
from companion.governor import GOVERNOR_PRESETS
from companion.spec import CAMERA_PRESETS, DEFAULT_TASK_SPEC
from sitl.cli_args import (
    add_governor_flag,
    ArgumentParser,
    camera_preset,
    MAX_THREADS,
    MAX_VEHICLES,
    float_range,
    int_list,
    int_range,
    output_dir,
    output_file_in_new_dir,
    port_in,
    response_spec,
)
from sitl.eval.over_mavlink import evaluate_beside_in_process
from sitl.eval.evaluate import EvalResult, EvalSettings, density_label, evaluate_method
from sitl.eval.methods import BASELINES, DEFAULT_POLICY, EvaluationError, resolve_method
from sitl.eval.paper import DEFAULT_FIG6_NS, PAPER_METHODS, paper_cells, parse_policies, run_paper
from sitl.eval.report import write_json, markdown_table
from sitl.sim.config import CIRCLE_HEADINGS, CIRCLE_RADIUS_M, DENSITIES, SCENARIOS, ScenarioConfig, density_from_name
from sitl.sim.dynamics import DYNAMICS_NAMES, RESPONSE_PRESETS
from sitl.sim.scenarios import EVAL_SEED_OFFSET

#: Bounds of the evaluation's sizes: beyond them a run would only exhaust memory or never end.
MAX_EPISODES = 1_000_000


MAX_EPISODE_STEPS = 100_000


MAX_BATCH = 10_000


MAX_RADIUS_M = 10_000.0


def _add_governor(parser: argparse.ArgumentParser) -> None:
    add_governor_flag(parser, ", the straight reference stays plain")
    add_face_goal_argument(
        parser, help="the controller turns in place to face its goal for SECONDS from the episode's start before it "
                     f"flies (companion --face-goal; {DEFAULT_FACE_GOAL_S:g} s alone): every UAV of an episode "
                     "starts flying together, facing its goal; the label gains +face-goal, the straight reference "
                     "stays plain (default off)")


def _face_goal(args: argparse.Namespace) -> FaceGoalSpec | None:
    return None if args.face_goal is None else FaceGoalSpec(hold_s=args.face_goal)


def _add_common(parser: argparse.ArgumentParser) -> None:
    """Options shared by the single evaluation and ``paper``."""
    parser.add_argument("--episodes", type=int_range(1, MAX_EPISODES), default=None,
                        help="episodes per evaluation (default 100; 10 with --mavlink, which flies in real time)")
    parser.add_argument("--seed", type=int_range(0), default=0,
                        help=f"evaluation seed; the simulator uses {EVAL_SEED_OFFSET} + SEED, disjoint from training")
    parser.add_argument("--dynamics", choices=DYNAMICS_NAMES, default=DYNAMICS_NAMES[0],
                        help="UAV dynamics (default kinematic)")
    parser.add_argument("--camera", type=camera_preset, default=None,
                        help=f"camera preset the UAVs carry: {', '.join(CAMERA_PRESETS)} (default: the policy's own camera, "
                             "paper for the references); a policy must fit in it (its FOV cut from the camera's)")
    parser.add_argument("--camera-noise", action=argparse.BooleanOptionalAction, default=None,
                        help="stereo depth noise with holes (default: on with a real sensor's --camera, off with paper)")
    parser.add_argument("--max-steps", type=int_range(1, MAX_EPISODE_STEPS), default=DEFAULT_TASK_SPEC.max_episode_steps,
                        help=f"episode time limit in control steps (default {DEFAULT_TASK_SPEC.max_episode_steps} = "
                             f"{DEFAULT_TASK_SPEC.max_episode_steps / 10:g} s at 10 Hz)")
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
    parser.add_argument("--radius", type=float_range(0.0, MAX_RADIUS_M, low_open=True), default=CIRCLE_RADIUS_M,
                        help=f"circle radius in m (default {CIRCLE_RADIUS_M:g})")
    parser.add_argument("--circle-heading", choices=[h for h in CIRCLE_HEADINGS if h != "mixed"], default="goal",
                        help="where circle UAVs face at the start: goal (each its own, the paper), common (the swarm "
                             "one heading drawn per episode, as SITL spawns it) or any (each its own random one) "
                             "(default goal; docs/results.md \"The circle's start heading\")")
    parser.add_argument("--altitude", type=float_range(0.0, MAX_RADIUS_M, low_open=True), default=None, metavar="M",
                        help=f"circle altitude in m (default {ScenarioConfig().circle_alt_m:g}, the paper's)")
    parser.add_argument("--scatter", type=float_range(0.0, MAX_RADIUS_M), default=0.0, metavar="M",
                        help="circle starts moved horizontally to a uniform point within M metres of the ring, goals "
                             "at the nominal antipodes (default 0; PX4 SIH's starts: ~1 m)")
    parser.add_argument("--response", type=response_spec, default=None, metavar="SPEC",
                        help="each UAV's velocity response drawn per UAV and episode (kinematic dynamics): a preset "
                             f"({', '.join(RESPONSE_PRESETS)}: fitted to that autopilot's vehicles) or "
                             "FIELD=LOW:HIGH items, comma-separated, over the nominal response (e.g. "
                             "tau_horizontal_s=0.5:1,drag_horizontal_per_s=0.4; the fields: "
                             "sitl.sim.dynamics.KinematicRandomization; `python -m sitl.real_autopilots fit RUN` prints "
                             "the spec of a flight); default: every UAV nominal")
    _add_common(parser)
    parser.add_argument("--out", type=output_dir, default=None,
                        help="output folder (default runs/swarm_test/<method>-<scenario>-n<N>)")
    parser.add_argument("--json", type=output_file_in_new_dir, default=None, help="also write the metrics JSON to this file")
    parser.add_argument("--no-reference", dest="reference", action="store_false",
                        help="do not fly the straight-to-goal reference beside the controller")
    parser.add_argument("--plot-episodes", type=int_range(0), default=1,
                        help="episodes to draw as trajectory figures (default 1; 0: none)")
    _add_governor(parser)
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
    if args.scenario != "circle" and (args.altitude is not None or args.scatter):
        parser.error("--altitude and --scatter shape the circle scenario; the random scenes draw their own altitudes")
    if args.response is not None and args.dynamics != "kinematic":
        parser.error(f"--response draws the kinematic backend's response; --dynamics {args.dynamics} has its own")
    if args.response is not None and args.mavlink:
        parser.error("--response is in-process only: sitl.vehicle flies the nominal response")
    if args.camera_noise is None:  # a real sensor's preset brings its noise
        args.camera_noise = args.camera not in (None, "paper") and not args.mavlink
    if args.episodes is None:
        args.episodes = 10 if args.mavlink else 100
    if args.mavlink:
        if args.policy in BASELINES:
            parser.error(f"--mavlink flies a policy file in the companion; {args.policy!r} is an in-process reference")
        if args.camera_noise:
            parser.error("--mavlink: sitl.vehicle renders perfect depth; --camera-noise is in-process only")
        if args.scenario == "obstacles":
            parser.error("--mavlink: sitl.vehicle has no per-episode obstacles; the obstacles scene is in-process only")
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
        circle = {"circle_scatter_m": args.scatter}
        if args.altitude is not None:
            circle["circle_alt_m"] = args.altitude
        args.scenario_config = ScenarioConfig(name=args.scenario, density=density, circle_radius_m=args.radius,
                                              circle_heading=args.circle_heading, **circle)
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


_port = port_in(1024, 65535)  # unprivileged ports for the --mavlink processes


def _scenario_tag(scenario: ScenarioConfig) -> str:
    if scenario.name == "circle":
        heading = "" if scenario.circle_heading == "goal" else f"-{scenario.circle_heading}"
        alt = "" if scenario.circle_alt_m == ScenarioConfig().circle_alt_m else f"-a{scenario.circle_alt_m:g}"
        scatter = f"-scatter{scenario.circle_scatter_m:g}" if scenario.circle_scatter_m else ""
        return f"circle-r{scenario.circle_radius_m:g}{alt}{scatter}{heading}"
    return f"{scenario.name}-{density_label(scenario.density).replace('/', '')}"


def run_single(args: argparse.Namespace) -> int:
    """The default command: one controller (+ the straight reference) in one scenario."""
    try:
        method = resolve_method(args.policy)
    except EvaluationError as err:
        args.parser.error(str(err))
    if args.face_goal is not None:
        method = method.with_face_goal(_face_goal(args))
    if args.governor:
        method = method.with_governor(GOVERNOR_PRESETS[args.governor])
    if method.kind == "policy":
        import torch

        torch.set_num_threads(args.threads)
    settings = EvalSettings(scenario=args.scenario_config, num_uavs=args.n, episodes=args.episodes, seed=args.seed,
                            dynamics=args.dynamics, camera_noise=args.camera_noise, max_episode_steps=args.max_steps,
                            batch_worlds=args.batch, camera=args.camera, response=args.response)
    methods = [method]
    if args.reference and method.label != "straight":
        methods.append(resolve_method("straight"))
    results: list[EvalResult] = []
    try:
        for m in methods:
            results.append(evaluate_method(m, settings, progress=args.progress))
    except EvaluationError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2

    default_name = f"{method.label}-{_scenario_tag(settings.scenario)}-n{settings.num_uavs}" + (
        "-response" if settings.response is not None else "")
    out = args.out or Path("runs/swarm_test") / (default_name + ("-mavlink" if args.mavlink else ""))
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        print(f"error: cannot create the output folder {out}: {err.strerror}", file=sys.stderr)
        return 2
    mavlink_info = None
    if args.mavlink:
        try:
            mav_result, mavlink_info = evaluate_beside_in_process(
                method, settings, results[0], out, args.start, args.base_port, args.depth_port, args.gcs_port,
                args.progress)
        except Exception as err:  # noqa: BLE001 - reported with its reason; every process is already stopped
            from sitl.realtime.mavlink_swarm import MavlinkSwarmError

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
        write_json(metrics_path, data)
        if args.json:
            write_json(args.json, data)
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
    parser.add_argument("--ns", type=int_list(1, MAX_VEHICLES), default=list(DEFAULT_FIG6_NS),
                        help="Fig. 6 swarm sizes (default " + ",".join(map(str, DEFAULT_FIG6_NS)) + ")")
    parser.add_argument("--radius", type=float_range(0.0, MAX_RADIUS_M, low_open=True), default=CIRCLE_RADIUS_M,
                        help=f"Fig. 6 circle radius in m (default {CIRCLE_RADIUS_M:g})")
    parser.add_argument("--table-episodes", type=int_range(1, MAX_EPISODES), default=None,
                        help="episodes per Table II cell (default 500: random-scene success differs between "
                             "methods by a few points, which 100 episodes cannot resolve; cells are cheap)")
    parser.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS",
                        help="evaluate the cells as Ray tasks (1 CPU each): on a Ray started on this machine, or on "
                             "the cluster at ADDRESS (auto, ray://head:10001); needs the [ray] extra")
    _add_common(parser)
    args = parser.parse_args(argv)
    if args.episodes is None:
        args.episodes = 100
    if args.table_episodes is None:
        args.table_episodes = max(500, args.episodes)
    args.camera_noise = bool(args.camera_noise)  # the paper protocol: perfect depth unless asked for
    try:
        args.policy_paths = parse_policies(args.policies)
    except ValueError as err:
        parser.error(str(err))
    return args


def paper_main(argv: list[str] | None = None) -> int:
    args = parse_paper_args(argv)
    from sitl.distributed import RayUnavailable, import_ray

    if args.ray is not None:
        try:
            import_ray()
        except RayUnavailable as err:
            print(f"error: --ray: {err}", file=sys.stderr)
            return 2
    import torch

    torch.set_num_threads(args.threads)
    table, fig6 = paper_cells(args.episodes, args.seed, args.dynamics, args.camera_noise, args.max_steps, args.batch,
                              args.policy_paths, args.table_n, args.densities, args.ns, args.radius,
                              args.table_episodes)
    for method, path in args.policy_paths.items():
        if not path.exists():
            print(f"{method}: {path} not found, reported as 'not trained'", file=sys.stderr)
    try:
        result = run_paper(args.out, table, fig6, args.progress, args.policy_paths, ray_address=args.ray)
    except (EvaluationError, OSError, RayUnavailable) as err:  # OSError: the output folder became unwritable
        print(f"error: {err}", file=sys.stderr)
        return 2
    counts = {k: list(result["status"].values()).count(k) for k in ("computed", "stored", "not trained")}
    print((args.out / "paper.md").read_text())
    print(f"\ncells: {counts['computed']} computed, {counts['stored']} reused, {counts['not trained']} not trained; "
          f"wrote {args.out / 'paper.md'}, {args.out / 'paper.json'}, {args.out / 'fig6_scaling.png'}")
    return 0


def _cell_names(text: str) -> tuple[str, ...]:
    """``--cells``: names of the flown protocol's cells, comma-separated."""
    from sitl.eval.flown import FLOWN_CELL_NAMES

    names = tuple(name.strip() for name in text.split(",") if name.strip())
    unknown = [name for name in names if name not in FLOWN_CELL_NAMES]
    if not names or unknown:
        raise argparse.ArgumentTypeError(f"unknown cell {', '.join(unknown) or repr(text)}; "
                                         f"choose from {', '.join(FLOWN_CELL_NAMES)}")
    return names


def parse_flown_args(argv: list[str] | None = None) -> argparse.Namespace:
    from sitl.eval.flown import DEFAULT_EPISODES, FLOWN_CELL_NAMES, FLOWN_COMMAND_DELAY_S

    delay = "-".join(f"{d:g}" for d in FLOWN_COMMAND_DELAY_S)
    parser = ArgumentParser(
        prog="python -m sitl.swarm_test flown",
        description="The task as flown (issue 15): random small/medium/large scenes with starts and goals "
                    "1.5-15 m above the ground, circles of 8 at 2-15 m (radius 8-20 m), an obstacle scene, "
                    f"random medium with a {delay} s command delay per UAV and random medium on JSBSim; "
                    "start jitter 0.5 m and camera noise everywhere; the straight "
                    "reference beside every cell; success split by goal altitude. One JSON per cell and "
                    "controller under OUT/cells (an identical one is reused, so an interrupted run resumes); "
                    "OUT/flown.md, flown.json, flown_success.png.")
    parser.add_argument("--policy", default=str(DEFAULT_POLICY),
                        help=f"policy file, or a reference: {', '.join(BASELINES)} (default {DEFAULT_POLICY})")
    parser.add_argument("--out", type=output_dir, default=Path("runs/flown"), help="output folder (default runs/flown)")
    parser.add_argument("--episodes", type=int_range(1, MAX_EPISODES), default=DEFAULT_EPISODES,
                        help=f"episodes per cell (default {DEFAULT_EPISODES})")
    parser.add_argument("--jsbsim-episodes", type=int_range(1, MAX_EPISODES), default=None,
                        help="episodes of the JSBSim cell (default --episodes; it runs ~10x slower)")
    parser.add_argument("--no-jsbsim", dest="jsbsim", action="store_false", help="leave the JSBSim cell out")
    parser.add_argument("--cells", type=_cell_names, default=None,
                        help=f"only these cells, comma-separated (default all: {', '.join(FLOWN_CELL_NAMES)}); e.g. "
                             "random-medium --episodes 5000 to resolve its goal-altitude bins")
    parser.add_argument("--seed", type=int_range(0), default=0,
                        help=f"evaluation seed; the simulator uses {EVAL_SEED_OFFSET} + SEED, disjoint from training")
    parser.add_argument("--camera", type=camera_preset, default=None,
                        help=f"camera preset the UAVs carry: {', '.join(CAMERA_PRESETS)} (default: the policy's own, "
                             "paper for the references; orca-fov avoids what this camera covers)")
    parser.add_argument("--camera-noise", action=argparse.BooleanOptionalAction, default=True,
                        help="stereo depth noise and dropouts (default on: a real camera)")
    parser.add_argument("--max-steps", type=int_range(1, MAX_EPISODE_STEPS), default=DEFAULT_TASK_SPEC.max_episode_steps,
                        help=f"episode time limit in control steps (default {DEFAULT_TASK_SPEC.max_episode_steps})")
    parser.add_argument("--no-reference", dest="reference", action="store_false",
                        help="do not fly the straight-to-goal reference beside the controller")
    _add_governor(parser)
    parser.add_argument("--response", type=response_spec, default=None, metavar="SPEC",
                        help="every kinematic cell also flies this velocity response, drawn per UAV and episode over "
                             "the cell's own (the JSBSim cell is left as it is): a preset or FIELD=LOW:HIGH items, as "
                             "for a single evaluation, e.g. command_delay_s=0:0.2 or the spec `python -m "
                             "sitl.real_autopilots fit RUN` prints; default: each cell's own")
    parser.add_argument("--batch", type=int_range(1, MAX_BATCH), default=100,
                        help="episodes flown at once as parallel worlds (default 100)")
    parser.add_argument("--threads", type=int_range(1, MAX_THREADS), default=2, help="torch threads for the policy (default 2)")
    parser.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars")
    args = parser.parse_args(argv)
    args.parser = parser
    return args


def flown_main(argv: list[str] | None = None) -> int:
    from sitl.eval.flown import flown_cells, protocol_methods, run_flown

    args = parse_flown_args(argv)
    try:
        methods = protocol_methods(args.policy, args.reference, GOVERNOR_PRESETS[args.governor] if args.governor else None,
                                   _face_goal(args))
    except EvaluationError as err:
        args.parser.error(str(err))
    if methods[0].kind == "policy":
        import torch

        torch.set_num_threads(args.threads)
    cells = flown_cells(args.episodes, args.seed, args.camera_noise, max_steps=args.max_steps, batch=args.batch,
                        jsbsim=args.jsbsim, jsbsim_episodes=args.jsbsim_episodes, camera=args.camera,
                        response=args.response)
    if args.cells:
        cells = [cell for cell in cells if cell.name in args.cells]
        if not cells:
            args.parser.error("--cells names only the JSBSim cell, which --no-jsbsim leaves out")
    try:
        result = run_flown(args.out, cells, methods, args.progress, args.response)
    except (EvaluationError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    counts = {k: list(result["status"].values()).count(k) for k in ("computed", "stored")}
    print((args.out / "flown.md").read_text())
    print(f"\ncells: {counts['computed']} computed, {counts['stored']} reused; wrote {args.out / 'flown.md'}, "
          f"{args.out / 'flown.json'}, {args.out / 'flown_success.png'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["paper"]:
        return paper_main(argv[1:])
    if argv[:1] == ["flown"]:
        return flown_main(argv[1:])
    args = parse_args(argv)
    args.argv = argv
    if args.mavlink:
        # Ctrl-C and SIGTERM must reach the cleanup that stops the children, even when this
        # process was started with SIGINT ignored (e.g. in the background of a script).
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        return run_single(args)
    except KeyboardInterrupt:  # every child process is already stopped (sitl.realtime.mavlink_swarm)
        print("interrupted", file=sys.stderr)
        return 130
