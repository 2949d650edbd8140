"""``companion``: the onboard process that flies a swarmnav policy through PX4 or ArduPilot.

    companion --connect udp:14540 --model policy.pt --camera realsense --goal 20,0,-6

Start-up is fail-fast and in this order, each with a clear error and exit status: load and
validate the policy file (3), start the depth camera (4), open the MAVLink link and wait for
the autopilot's heartbeat (5). Then (READY for systemd) it streams hold setpoints and waits
for the pilot to select OFFBOARD (PX4) or GUIDED (ArduPilot); ``--arm --takeoff ALT``
automates arming, takeoff and the mode switch (SITL and tests). The goal can be changed in
flight with SET_POSITION_TARGET_LOCAL_NED sent to component 191 (see docs/companion.md).

``companion --describe`` prints the observation/action contract as JSON.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import socket
import sys
import time
from dataclasses import asdict
from pathlib import Path

from companion.flightlog import DEFAULT_LOG_KEEP, DEFAULT_LOG_MAX_MB
from companion.face_goal import DEFAULT_FACE_GOAL_S, FaceGoalSpec, add_face_goal_argument
from companion.governor import (DEFAULT_GOVERNOR, GOVERNOR_PRESETS, add_governor_argument, describe_presets,
                                governor_name)
from companion.recording import DEFAULT_RECORD_KEEP, DEFAULT_RECORD_MAX_MB
from companion.spec import (
    DEFAULT_ACTION_SPEC,
    DEFAULT_CAMERA_SPEC,
    HEARTBEAT_TIMEOUT_MAX_S,
    LINK_TIMEOUT_MAX_S,
    LINK_TIMEOUT_MIN_S,
    MAX_INVALID_DEPTH_FRACTION,
    STATE_NAMES,
    goal_problem,
)


def describe() -> dict:
    """The observation/action contract as a JSON-ready dict."""
    return {
        "frames": "world: local NED; body: heading frame FRD (x forward, y right, z down), yaw positive right",
        "depth": {**DEFAULT_CAMERA_SPEC.to_dict(), "units": "metres, planar", "order": "oldest frame first"},
        "state": list(STATE_NAMES),
        "action": asdict(DEFAULT_ACTION_SPEC),
        "setpoint": {"message": "SET_POSITION_TARGET_LOCAL_NED", "coordinate_frame": 8, "type_mask": 1479},
        "goal_update": {"message": "SET_POSITION_TARGET_LOCAL_NED", "target_component": 191,
                        "coordinate_frame": 1, "fields": "x, y, z (local NED, m)"},
    }


# --------------------------------------------------------------------------- argument types


def _goal(text: str):
    import numpy as np

    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"goal must be N,E,D in metres (local NED), got {text!r}") from None
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"goal must be three finite numbers N,E,D in metres, got {text!r}")
    problem = goal_problem(values)  # the same check as goals sent in flight
    if problem is not None:
        raise argparse.ArgumentTypeError(problem)
    return np.asarray(values)


#: A value that starts with '-' but is a number or a comma-separated list of numbers
#: (``-24,0,-8``, ``-5``, ``-1.5e2,0,-3``): argparse would take it for an option.
_NEGATIVE_VALUE = re.compile(r"-\.?\d[\d.eE+\-]*(,[+\-]?[\d.eE+\-]*)*")


def join_negative_values(parser: argparse.ArgumentParser, argv: list[str]) -> list[str]:
    """``--goal -24,0,-8`` -> ``--goal=-24,0,-8`` for every option of ``parser`` taking one value.

    argparse treats an argument that starts with '-' as an option unless it is a plain negative
    number, so ``--goal -24,0,-8`` fails with "expected one argument" (issue 18), and every
    circle layout has negative coordinates. Joining the pair is exactly what ``--goal=...``
    means; anything after ``--`` is left alone. Shared with the simulator's command lines.
    """
    one_value = {option for action in parser._actions if action.option_strings and action.nargs is None
                 for option in action.option_strings}
    out: list[str] = []
    i = 0
    while i < len(argv):
        arg = argv[i]
        if arg == "--":
            out.extend(argv[i:])
            break
        if arg in one_value and i + 1 < len(argv) and _NEGATIVE_VALUE.fullmatch(argv[i + 1]):
            out.append(f"{arg}={argv[i + 1]}")
            i += 2
            continue
        out.append(arg)
        i += 1
    return out


class _Parser(argparse.ArgumentParser):
    """argparse's parser, but a bad value prints one line, ``companion: error: ...``, and exits 2,
    and negative N,E,D values are taken as written (:func:`join_negative_values`).

    argparse prints the usage block first; in the systemd journal the reason then hides
    below it. ``--help`` still shows the usage.
    """

    def error(self, message: str):  # noqa: D102 - argparse's API
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())} (see --help)\n")

    def parse_known_args(self, args=None, namespace=None):  # noqa: D102 - argparse's API
        argv = sys.argv[1:] if args is None else list(args)
        return super().parse_known_args(join_negative_values(self, argv), namespace)


def _positive(name: str, upper: float = math.inf, lower: float = 0.0):
    """A parser of finite numbers in (0, upper] (or [lower, upper] when ``lower`` > 0): NaN and inf never pass."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a number, got {text!r}") from None
        in_range = lower <= value <= upper if lower > 0 else 0 < value <= upper
        if not (math.isfinite(value) and in_range):
            low_text = f">= {lower:g}" if lower > 0 else "> 0"
            raise argparse.ArgumentTypeError(f"{name} must be {low_text}{'' if upper == math.inf else f' and <= {upper:g}'}"
                                             f" (a finite number), got {text!r}")
        return value
    return parse


def _count(name: str):
    def parse(text: str) -> int:
        if not text.isdigit() or int(text) > 1000:
            raise argparse.ArgumentTypeError(f"{name} must be a whole number in 0..1000, got {text!r}")
        return int(text)
    return parse


def _connection(text: str) -> str:
    from companion.mavlink_link import normalize_connection

    try:
        normalized = normalize_connection(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    scheme, _, rest = normalized.partition(":")
    if scheme in ("udpin", "udpout", "tcp", "tcpin"):  # a host typo fails here, not at the first send
        host = rest.rpartition(":")[0]
        try:
            socket.getaddrinfo(host, None, socket.AF_INET)
        except (socket.gaierror, UnicodeError) as err:
            raise argparse.ArgumentTypeError(f"invalid connection {text!r}: cannot resolve host {host!r} "
                                             f"({getattr(err, 'strerror', None) or err})") from None
    return text


def _output_file(text: str) -> str:
    """``-`` (stdout) or a file path in an existing directory.

    A missing directory is refused (not created), for ``--log`` and ``--record`` alike: on a
    vehicle a typo must not scatter files, and the error must come before take-off.
    """
    if text == "-":
        return text
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a directory, expected a file")
    if not path.parent.is_dir():
        raise argparse.ArgumentTypeError(f"cannot write {text}: no such directory {str(path.parent)!r}")
    return text


def _camera(text: str) -> str:
    from companion.depth_sources import parse_camera_spec

    try:
        parse_camera_spec(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return text


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="companion", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--describe", action="store_true", help="print the observation/action contract as JSON and exit")
    link = parser.add_argument_group("link")
    link.add_argument("--connect", type=_connection, metavar="CONN",
                      help="MAVLink connection: udp:14540 (listen, PX4 SITL's onboard port), udpin:HOST:PORT, "
                           "udpout:HOST:PORT, tcp:HOST:PORT, /dev/ttyTHS1,921600")
    link.add_argument("--heartbeat-timeout", type=_positive("--heartbeat-timeout", HEARTBEAT_TIMEOUT_MAX_S), default=10.0, metavar="S",
                      help="give up if no autopilot heartbeat arrives within S seconds (default 10); a TCP "
                           "connection refused or a serial device not there yet is retried meanwhile")
    link.add_argument("--link-timeout", type=_positive("--link-timeout", LINK_TIMEOUT_MAX_S, LINK_TIMEOUT_MIN_S),
                      default=2.0, metavar="S",
                      help=f"declare the link lost after S seconds without a heartbeat, {LINK_TIMEOUT_MIN_S:g}.."
                           f"{LINK_TIMEOUT_MAX_S:g} (default 2)")
    link.add_argument("--signing-key", metavar="FILE",
                      help="MAVLink 2 signing key (32 bytes or 64 hex characters): sign everything, refuse unsigned input")
    link.add_argument("--stream-rate", type=_positive("--stream-rate", 200), default=50.0, metavar="HZ",
                      help="odometry rate requested from the autopilot (default 50 Hz)")
    flight = parser.add_argument_group("flight")
    flight.add_argument("--model", metavar="PATH",
                        help="policy file: TorchScript (.pt) or ONNX (.onnx, run by onnxruntime), with policy.json metadata")
    flight.add_argument("--onnx-provider", choices=("auto", "cpu", "cuda", "tensorrt"), default="auto",
                        help="onnxruntime execution provider for an .onnx model: auto (default: TensorRT, then CUDA, "
                             "then CPU, whichever this onnxruntime build has), or one of them (refused if absent)")
    flight.add_argument("--camera", type=_camera, default="realsense", metavar="SOURCE",
                        help="depth source: realsense[:WxH@FPS] (default), sitl:PORT[:VEHICLE], replay:PATH[,loop]")
    flight.add_argument("--goal", type=_goal, metavar="N,E,D",
                        help="goal in local NED metres (altitude is -D); negative values as written: --goal -24,0,-8")
    flight.add_argument("--arm", action="store_true",
                        help="arm, take off and switch to OFFBOARD/GUIDED automatically (SITL and tests; needs --takeoff)")
    flight.add_argument("--takeoff", type=_positive("--takeoff", 100), metavar="ALT",
                        help="take-off altitude in metres above home for --arm")
    flight.add_argument("--land-on-arrival", action="store_true", help="land once arrived (within the policy's arrival radius, policy.json task; 0.5 m by default)")
    flight.add_argument("--exit-on-arrival", action="store_true",
                        help="exit 0 once arrived (and landed with --land-on-arrival), non-zero on any failure")
    flight.add_argument("--timeout", type=_positive("--timeout"), metavar="S", help="exit 7 if not arrived within S seconds")
    flight.add_argument("--max-invalid-depth", type=_positive("--max-invalid-depth", 1.0),
                        default=None, metavar="FRACTION",
                        help="hold when more than this fraction of a depth frame's pixels are invalid (0, negative, "
                             f"NaN): a covered, dazzled or dead camera (default {MAX_INVALID_DEPTH_FRACTION:g} for an "
                             "ideal simulated camera; 1, off, for a real sensor's policy (min range > 0), whose open-sky "
                             "frames are 100 %% invalid: docs/companion.md; 1 turns the check off)")
    flight.add_argument("--no-camera-sync", action="store_true",
                        help="do not phase-lock the control ticks to depth frame arrivals")
    flight.add_argument("--obstacle-distance", action=argparse.BooleanOptionalAction, default=True,
                        help="publish MAVLink OBSTACLE_DISTANCE (72 bins, body FRD) from every depth frame, for the "
                             "autopilot's own collision prevention (default on; docs/companion.md)")
    add_governor_argument(
        flight, help="speed governor after the policy: cap the forward speed so the vehicle stops short of the "
                      "nearest depth point in a corridor ahead (--governor alone: "
                      f"{DEFAULT_GOVERNOR}; {describe_presets()}; swarm is for policies that turn by themselves in "
                      "dense traffic; PX4's collision prevention does nothing in Offboard; default off: "
                      "docs/companion.md). A policy trained with the governor "
                      "(policy.json 'governor') always flies with it, with the file's settings")
    add_face_goal_argument(
        flight, help="before flying to a new goal, turn in place to face it and start the policy SECONDS after the goal "
                     f"arrived (or after engaging; --face-goal alone: {DEFAULT_FACE_GOAL_S:g} s, half a turn at the "
                     "policy's yaw limit and settling). The same hold for every vehicle: a swarm given its goals "
                     "together starts together, each facing its goal, as the policy was trained (docs/companion.md "
                     "'Face the goal first'). Default off")
    output = parser.add_argument_group("output")
    output.add_argument("--log", type=_output_file, default="-", metavar="PATH",
                        help="JSON-lines log of every control step and event (default '-': stdout)")
    output.add_argument("--record", type=_output_file, metavar="PATH", help="write a flight recording (depth + state + action)")
    output.add_argument("--log-max-mb", type=_positive("--log-max-mb", 1e6), default=DEFAULT_LOG_MAX_MB, metavar="MB",
                        help=f"rotate the log file once it holds MB megabytes (default {DEFAULT_LOG_MAX_MB:g}: ~4 h)")
    output.add_argument("--log-keep", type=_count("--log-keep"), default=DEFAULT_LOG_KEEP, metavar="N",
                        help=f"rotated log files kept as PATH.1 .. PATH.N (default {DEFAULT_LOG_KEEP})")
    output.add_argument("--record-max-mb", type=_positive("--record-max-mb", 1e6), default=DEFAULT_RECORD_MAX_MB,
                        metavar="MB", help="start a new recording part once one holds MB megabytes "
                        f"(default {DEFAULT_RECORD_MAX_MB:g}: ~1.8 h)")
    output.add_argument("--record-keep", type=_count("--record-keep"), default=DEFAULT_RECORD_KEEP, metavar="N",
                        help=f"older recording parts kept as PATH.1 .. PATH.N (default {DEFAULT_RECORD_KEEP})")
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.describe:
        return args
    if not args.connect:
        parser.error("--connect is required (e.g. --connect udp:14540)")
    if not args.model:
        parser.error("--model is required (a policy file, e.g. models/policy.pt)")
    if args.arm and args.takeoff is None:
        parser.error("--arm needs --takeoff ALT (the altitude to climb to if the vehicle is on the ground)")
    if args.takeoff is not None and not args.arm:
        parser.error("--takeoff only applies with --arm")
    if args.signing_key:
        from companion.mavlink_link import load_signing_key

        try:
            load_signing_key(args.signing_key)
        except ValueError as err:
            parser.error(f"--signing-key: {err}")
    return args


# --------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.describe:
        print(json.dumps(describe(), indent=2))
        return 0
    from companion.flightlog import FlightLog, RotatingTextFile

    try:
        stream = sys.stdout if args.log == "-" else RotatingTextFile(args.log, int(args.log_max_mb * 1e6), args.log_keep)
    except OSError as err:
        print(f"companion: error: cannot open the log {args.log}: {err.strerror}", file=sys.stderr)
        return 1
    log = FlightLog(stream)
    try:
        return _fly(args, log)
    finally:
        log.close()


def _fly(args: argparse.Namespace, log) -> int:
    from companion.runtime import ExitCode

    def fail(code: ExitCode, message: str) -> int:
        log.event("exit", f"error: {message}", level="error", code=int(code), reason=message)
        return int(code)

    # 1. The model: the contract is checked before anything else is touched.
    import torch

    torch.set_num_threads(1)  # one inference thread: predictable latency on a small computer
    try:
        torch.set_num_interop_threads(1)
    except RuntimeError:
        pass
    from companion.policy import PolicyFileError, load_policy

    try:
        providers = None
        if Path(args.model).suffix.lower() == ".onnx":
            from companion.onnx_policy import OnnxUnavailableError, select_providers

            try:
                providers = select_providers(args.onnx_provider)
            except OnnxUnavailableError as err:
                raise PolicyFileError(f"{args.model}: {err}") from None
        policy = load_policy(args.model, providers=providers)
    except PolicyFileError as err:
        return fail(ExitCode.BAD_MODEL, f"cannot use the model: {err}")
    blank_depth, blank_state = policy.blank_observation()
    for _ in range(20):  # let TorchScript's profiling executor settle before the first real step
        policy.act(blank_depth, blank_state)
    cam = policy.camera
    spacing = cam.describe_stack()
    log.event("model", f"model {args.model}: {cam.width}x{cam.height}x{cam.frames} depth{spacing}, "
              f"{cam.hfov_deg:g} x {cam.vertical_fov_deg:.4g} deg pitched {cam.mount_pitch_deg:+g} deg, "
              f"range {cam.min_range_m:g}-{cam.max_range_m:g} m, control period {policy.control_period_s:g} s",
              model=args.model, metadata={k: v for k, v in policy.metadata.items() if k != "provenance"},
              runtime="onnxruntime" if providers else "torchscript",
              providers=getattr(policy.module, "providers", None))  # what onnxruntime really uses
    for note in policy.notes:  # how an older policy file was read
        log.event("model_note", note)
    if policy.memory is not None:  # the state then carries what the camera showed recently, moved with odometry
        m = policy.memory
        log.event("model_note", f"the policy remembers depth: {m.steps} control steps "
                                f"({m.steps * policy.control_period_s:g} s), nearest point per direction sector "
                                f"within {m.range_m:g} m, from the camera's frames and odometry")
    if policy.governor is not None:  # trained with it: it always flies with it (--governor or not)
        log.event("model_note", "the policy was trained with the speed governor after it: the companion applies it "
                                "with the file's settings")
    governor = policy.governor if policy.governor is not None else (
        GOVERNOR_PRESETS[args.governor] if args.governor else None)
    if governor is not None:  # what will fly, by name, and where it came from
        source = "policy file" if policy.governor is not None else "--governor"
        log.event("governor", f"speed governor '{governor_name(governor)}' after the policy ({source}): "
                              f"{governor.describe()}",
                  setting=governor_name(governor), source=source, governor=governor.to_dict())
    if args.face_goal is not None:
        log.event("face_goal", f"face the goal first (--face-goal): {FaceGoalSpec(hold_s=args.face_goal).describe()}",
                  hold_s=args.face_goal)

    # 2. The camera.
    from companion.depth_sources import DepthSourceError, open_depth_source

    try:
        from companion.observation import default_max_invalid_fraction

        max_invalid = (args.max_invalid_depth if args.max_invalid_depth is not None
                       else default_max_invalid_fraction(policy.camera))
        depth = open_depth_source(args.camera, policy.camera, max_invalid)
        depth.start()
    except DepthSourceError as err:
        return fail(ExitCode.CAMERA, f"cannot start the camera: {err}")

    # 3. The recording (if asked for), then the link.
    from companion.mavlink_link import AutopilotLink, LinkError, load_signing_key
    from companion.recording import FlightRecorder

    link = None
    recorder = None
    try:
        if args.record:
            try:
                recorder = FlightRecorder(args.record, policy.camera, policy.control_period_s, args.model,
                                          max_bytes=int(args.record_max_mb * 1e6), keep=args.record_keep,
                                          state_dim=policy.state_dim)
            except OSError as err:
                return fail(ExitCode.ERROR, f"cannot write the recording {args.record}: {err.strerror}")
        key = load_signing_key(args.signing_key) if args.signing_key else None  # checked by parse_args
        link = AutopilotLink(args.connect, signing_key=key, relock_after_s=args.link_timeout)
        started_s = time.monotonic()

        def waiting(reason: str) -> None:  # the autopilot may boot after us (ArduPilot SITL's TCP ports)
            log.event("link", f"waiting for the autopilot: {reason}; retrying for up to {args.heartbeat_timeout:g} s "
                      "(--heartbeat-timeout)", level="warning", waiting=True)

        try:
            link.open(retry_for_s=args.heartbeat_timeout, on_wait=waiting)
            hb = link.wait_for_autopilot(max(args.heartbeat_timeout - (time.monotonic() - started_s), 1.0))
        except LinkError as err:
            return fail(ExitCode.LINK, str(err))
        log.event("link", f"connected to {hb.kind.value.upper()} (system {hb.sysid}) on {link.connection}: "
                  f"mode {hb.mode}, {'armed' if hb.armed else 'disarmed'}"
                  f"{', MAVLink 2 signing on' if key else ''}",
                  autopilot=hb.kind.value, sysid=hb.sysid, mode=hb.mode, armed=hb.armed, signing=key is not None)

        from companion.runtime import Companion, CompanionConfig
        from companion.sdnotify import SystemdNotifier

        config = CompanionConfig(goal_ned=args.goal, arm=args.arm, takeoff_alt_m=args.takeoff,
                                 land_on_arrival=args.land_on_arrival, exit_on_arrival=args.exit_on_arrival,
                                 timeout_s=args.timeout, link_timeout_s=args.link_timeout,
                                 stream_rate_hz=args.stream_rate, camera_sync=not args.no_camera_sync,
                                 obstacle_distance=args.obstacle_distance,
                                 governor=GOVERNOR_PRESETS[args.governor] if args.governor else None,
                                 face_goal=None if args.face_goal is None else FaceGoalSpec(hold_s=args.face_goal))
        notifier = SystemdNotifier()
        companion = Companion(policy, depth, link, config, log, recorder, notifier)
        notifier.ready(f"model, camera and link up ({hb.kind.value}, system {hb.sysid})")
        return int(companion.run())
    finally:
        if recorder is not None:
            recorder.close()
        if link is not None:
            link.close()
        depth.close()


if __name__ == "__main__":
    raise SystemExit(main())
