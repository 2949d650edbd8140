"""Simulated vehicles that speak MAVLink like PX4 SITL (or ArduCopter) — the companion's SITL.

    python -m sitl.vehicle --n 2                       # PX4 flavour, ports 14540, 14541
    python -m sitl.vehicle --n 1 --autopilot ardupilot
    python -m sitl.vehicle --n 2 --autopilot ardupilot --transport tcp   # TCP 5762, 5772 (SITL SERIAL1)

Runs N vehicles in one simulated world (the simulator's dynamics backend, raycast depth
camera and collision checks) in real time. Vehicle ``i`` (system id ``i + 1``):

* speaks MAVLink 2 to its companion: it sends from an ephemeral local UDP port to
  ``HOST:base-port + i`` (PX4 SITL's onboard port 14540 + i), where ``companion --connect
  udp:14540`` listens, and takes the companion's messages on that local port;
* or, with ``--transport tcp``, listens like ArduPilot SITL's SERIAL1 port: TCP
  ``HOST:base-port + 10*i`` (default base 5762: 5762, 5772, ...), one client at a time, where
  ``companion --connect tcp:HOST:5762`` connects;
* optionally talks to a ground station the same way at ``HOST:gcs-port`` (QGroundControl's
  14550; all vehicles share it), and routes messages between the two links;
* sends its rendered depth frames to ``HOST:depth-port + i`` (format:
  :mod:`companion.depth_wire`), where ``companion --camera sitl:<port>`` listens.

What the autopilot does (modes, commands, failsafes, failure injection) is described in
:mod:`sitl.realtime.mavlink_autopilot`. Events (modes, arming, commands, crashes, failures) and a
status line per vehicle per second go to ``--log`` as JSON lines.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import numpy as np

from companion.flight_modes import AutopilotKind
from companion.spec import DEFAULT_TASK_SPEC
from sitl.cli_args import (
    ArgumentParser,
    MAX_VEHICLES,
    check_port_block,
    finite_float,
    finite_floats,
    host,
    int_range,
    output_file,
    positive_float,
    response_spec,
    udp_port,
    udp_port_nonzero,
)
from sitl.sim.collision import uav_uav_collisions
from sitl.sim.dynamics import DYNAMICS_NAMES, KinematicRandomization, describe_response, make_dynamics, nominal_ranges
from sitl.sim.metrics import Outcome
from sitl.realtime.camera_feed import CameraConfig, CameraFeed, add_camera_arguments, camera_config, check_camera_arguments
from sitl.realtime.event_log import EventLog
from sitl.realtime.loop import serve
from sitl.realtime.mavlink_autopilot import Body, SimAutopilot
from sitl.realtime.depth_transport import DEPTH_BASE_PORT
from sitl.realtime.tcp_endpoint import ARDUPILOT_INSTANCE_PORT_STEP, ARDUPILOT_SERIAL1_BASE_PORT, MavlinkTcpServer
from sitl.realtime.udp_endpoint import GCS_PORT, PX4_ONBOARD_BASE_PORT, MavlinkUdpEndpoint

MAV_COMP_ID_AUTOPILOT1 = 1
PHYSICS_DT_S = 0.02
MAX_PHYSICS_STEPS_PER_PASS = 5  # more than 0.1 s behind: drop the backlog, stay real time
HARD_LANDING_M_S = 2.0
TRACE_HZ = 10.0
CRASH_UAV = Outcome.COLLISION_UAV.code  # the crash event's outcome codes: the simulator's outcome names
CRASH_GROUND = Outcome.COLLISION_GROUND.code


@dataclass(frozen=True)
class VehiclesConfig:
    """What ``python -m sitl.vehicle`` simulates and where it talks (its options, checked).

    Vehicle ``i`` has system id ``i + 1``, talks MAVLink to ``host:base_port + i`` (and to a
    ground station at ``host:gcs_port``, 0 for none) and sends depth to ``host:depth_port + i``.
    """

    starts_ned: np.ndarray  # [n, 3] m, local NED
    yaws_rad: np.ndarray  # [n]
    autopilot: AutopilotKind = AutopilotKind.PX4
    host: str = "127.0.0.1"
    base_port: int = PX4_ONBOARD_BASE_PORT
    depth_port: int = DEPTH_BASE_PORT
    gcs_port: int = GCS_PORT
    airborne: bool = False
    dynamics: str = "kinematic"
    camera: CameraConfig = field(default_factory=CameraConfig)
    signing_key: bytes | None = None
    odometry_child_frame: str = "local_ned"
    collision_radius_m: float = DEFAULT_TASK_SPEC.collision_radius_m
    transport: str = "udp"  # "tcp": vehicle i listens on TCP host:base_port + 10*i (ArduPilot SITL SERIAL1)
    guided_timeout_s: float | None = None  # ArduPilot GUID_TIMEOUT; None: the autopilot model's default
    #: kinematic only: each vehicle's velocity response drawn once, at start, from these ranges (None: nominal)
    response: KinematicRandomization | None = None
    response_seed: int = 0  # seed of that draw

    @property
    def n(self) -> int:
        return len(self.starts_ned)

    def onboard_port(self, i: int) -> int:
        """Vehicle ``i``'s onboard (companion) port: UDP base + i, or TCP base + 10*i as ArduPilot SITL."""
        return self.base_port + (ARDUPILOT_INSTANCE_PORT_STEP * i if self.transport == "tcp" else i)


class SimulatedVehicles:
    """N simulated vehicles: dynamics, camera, collisions, and one autopilot each.

    ``trace`` (a text stream), when set, gets :meth:`trace_line` at 10 Hz.
    """

    def __init__(self, config: VehiclesConfig, log: EventLog, trace: TextIO | None = None) -> None:
        n = config.n
        self.n, self.config, self.log, self.trace = n, config, log, trace
        self.dynamics = make_dynamics(config.dynamics, n)
        self.dynamics.reset(np.arange(n), np.asarray(config.starts_ned, dtype=np.float64),
                            np.asarray(config.yaws_rad, dtype=np.float64))
        if config.response is not None:
            # A vehicle that responds like a fitted airframe (`sitl.real_autopilots fit` prints the spec), its
            # command delay included; the ``response`` event says what each vehicle got.
            self.dynamics.randomize(np.arange(n), config.response, np.random.default_rng(config.response_seed))
            log("response", spec=describe_response(config.response, nominal_ranges()),
                vehicles=[{name: round(float(values[i]), 4) for name, values in self.dynamics.response.items()}
                          for i in range(n)])
        self.feed = CameraFeed(config.camera, config.host, config.depth_port, n)
        self.autopilots: list[SimAutopilot] = []
        for i in range(n):
            if config.transport == "tcp":
                onboard = MavlinkTcpServer("onboard", (config.host, config.onboard_port(i)), i + 1,
                                           MAV_COMP_ID_AUTOPILOT1, config.signing_key, link_id=1)
            else:
                onboard = self._link("onboard", config.base_port + i, i + 1, link_id=1)
            gcs = self._link("gcs", config.gcs_port, i + 1, link_id=2) if config.gcs_port else None
            ap = SimAutopilot(i, config.autopilot, onboard, gcs, log, airborne=config.airborne,
                              odometry_child_frame=config.odometry_child_frame, camera=self.feed.sender)
            if config.guided_timeout_s is not None:
                ap.guided_timeout_s = config.guided_timeout_s
            self.autopilots.append(ap)
        self.collided = np.zeros(n, dtype=bool)
        self.skipped_frames = 0
        self._next_physics_s: float | None = None
        self._next_trace_s: float | None = None

    def _link(self, name: str, port: int, sysid: int, link_id: int) -> MavlinkUdpEndpoint:
        """An autopilot link as PX4 SITL's: from an ephemeral local port to ``host:port``."""
        return MavlinkUdpEndpoint.autopilot_link(name, (self.config.host, port), sysid, self.config.signing_key,
                                                 link_id=link_id)

    def body(self, i: int) -> Body:
        d = self.dynamics
        return Body(d.pos_ned[i], d.vel_ned[i], float(d.yaw_rad[i]), float(d.yaw_rate_rad_s[i]))

    # ------------------------------------------------------------------ the real-time loop's calls
    def fds(self) -> dict[int, tuple[SimAutopilot, MavlinkUdpEndpoint]]:
        """Every socket to wait on (a TCP link adds its client's while one is connected)."""
        out = {}
        for ap in self.autopilots:
            for link in ap.links:
                for fd in (link.fds() if hasattr(link, "fds") else [link.fileno()]):
                    out[fd] = (ap, link)
        return out

    def receive(self, link: tuple[SimAutopilot, MavlinkUdpEndpoint], now_s: float) -> None:
        ap, endpoint = link
        for msg in endpoint.receive():
            ap.handle(endpoint, msg, now_s)

    def wake_s(self) -> float:
        return self._next_physics_s if self._next_physics_s is not None else -math.inf

    def tick(self, now_s: float) -> None:
        """Physics at 50 Hz (catching up at most 0.1 s), telemetry, and the trace."""
        if self._next_physics_s is None:
            self._next_physics_s = now_s
        if now_s >= self._next_physics_s:
            steps = 0
            while now_s >= self._next_physics_s and steps < MAX_PHYSICS_STEPS_PER_PASS:
                self.physics_step(now_s, PHYSICS_DT_S)
                self._next_physics_s += PHYSICS_DT_S
                steps += 1
            if now_s >= self._next_physics_s:
                self.log("overrun", behind_s=round(now_s - self._next_physics_s, 3))
                self._next_physics_s = now_s + PHYSICS_DT_S
        for i, ap in enumerate(self.autopilots):
            ap.send_telemetry(now_s, self.body(i))
        if self.trace is not None:
            if self._next_trace_s is None:
                self._next_trace_s = now_s
            if now_s >= self._next_trace_s:
                self.trace_line(self.trace)
                self._next_trace_s = max(self._next_trace_s + 1.0 / TRACE_HZ, now_s)

    def render_and_send(self, now_s: float | None = None) -> None:
        d = self.dynamics
        self.feed.render_and_send(list(range(self.n)), d.pos_ned, d.yaw_rad)

    def warm_up(self) -> None:
        self.render_and_send()  # compile/load the camera kernel before announcing readiness

    def physics_step(self, now_s: float, dt_s: float) -> None:
        """Advance every vehicle by ``dt_s`` under its autopilot's command."""
        d = self.dynamics
        cmds = np.zeros((self.n, 3))
        active = np.zeros(self.n, dtype=bool)
        for i, ap in enumerate(self.autopilots):
            cmds[i], active[i] = ap.velocity_command(now_s, self.body(i))
        prev = d.pos_ned.copy()
        d.step(cmds, dt_s, active)
        for i, ap in enumerate(self.autopilots):
            if active[i] and not ap.airborne and d.pos_ned[i, 2] < -0.01:
                ap.lifted_off()
            if ap.airborne and d.pos_ned[i, 2] >= 0.0:
                sink = d.vel_ned[i, 2]
                d.pos_ned[i, 2] = 0.0
                d.vel_ned[i] = 0.0
                d.yaw_rate_rad_s[i] = 0.0
                ap.touched_down(now_s)
                if sink > HARD_LANDING_M_S:
                    ap.crash(f"hit the ground at {sink:.1f} m/s", CRASH_GROUND)
            if not active[i] and not ap.airborne:
                d.vel_ned[i] = 0.0
                d.yaw_rate_rad_s[i] = 0.0
        flying = np.array([ap.airborne for ap in self.autopilots])
        hits = uav_uav_collisions(prev, d.pos_ned, flying, self.n, self.config.collision_radius_m)
        for i in np.flatnonzero(hits & ~self.collided):
            self.autopilots[i].crash("collision with another vehicle", CRASH_UAV)
        self.collided |= hits
        for i, ap in enumerate(self.autopilots):
            ap.update(now_s, self.body(i))

    def status(self, now_s: float | None = None) -> None:
        for i, ap in enumerate(self.autopilots):
            self.log("status", vehicle=i, pos_ned=self.dynamics.pos_ned[i], vel_ned=self.dynamics.vel_ned[i],
                     yaw_deg=round(math.degrees(float(self.dynamics.yaw_rad[i])), 1), mode=ap.mode, armed=ap.armed,
                     airborne=ap.airborne, crashed=ap.crashed, setpoints=ap.setpoints_received,
                     last_setpoint_t=None if not math.isfinite(ap.last_setpoint_s) else
                     round(time.time() - (time.monotonic() - ap.last_setpoint_s), 4),
                     frames_sent=self.feed.frames_sent(i), refused_unsigned=sum(l.refused_unsigned for l in ap.links))

    def trace_line(self, stream: TextIO) -> None:
        """One JSON line of ground truth: every vehicle's position and state (for evaluations)."""
        record = {"t": round(time.time(), 4), "pos_ned": self.dynamics.pos_ned.round(4).tolist(),
                  "airborne": [ap.airborne for ap in self.autopilots],
                  "crashed": [ap.crashed for ap in self.autopilots]}
        stream.write(json.dumps(record) + "\n")

    def close(self) -> None:
        for ap in self.autopilots:
            for link in ap.links:
                link.close()
        self.feed.close()
        if self.trace is not None:
            self.trace.close()


# --------------------------------------------------------------------------- command line


def _read_starts(path: Path, n: int, airborne: bool) -> tuple[np.ndarray, np.ndarray]:
    """Per-vehicle starts from a JSON file -> (positions [n, 3] NED, yaws [n] rad)."""
    try:
        items = json.loads(path.read_text())
        ned = np.array([item["ned"] for item in items], dtype=np.float64)
        yaw = np.radians(np.array([item.get("yaw_deg", 0.0) for item in items], dtype=np.float64))
    except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
        raise ValueError(f"not a JSON list of {{\"ned\": [N, E, D], \"yaw_deg\": Y}} objects ({err})") from None
    if ned.shape != (n, 3) or not np.all(np.isfinite(ned)) or not np.all(np.isfinite(yaw)):
        raise ValueError(f"needs {n} finite starts (one per vehicle, --n), got shape {ned.shape}")
    if airborne and np.any(ned[:, 2] > -0.5):
        raise ValueError("--airborne needs every start in the air (D < -0.5)")
    if not airborne and np.any(ned[:, 2] != 0.0):
        raise ValueError("vehicles on the ground start at D = 0; use --airborne to start in the air")
    return ned, yaw


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = ArgumentParser(prog="python -m sitl.vehicle", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int_range(1, MAX_VEHICLES), default=1,
                        help=f"number of vehicles, 1..{MAX_VEHICLES} (system ids 1..N; default 1)")
    parser.add_argument("--autopilot", choices=[k.value for k in AutopilotKind], default="px4",
                        help="behave like PX4 (default) or ArduCopter")
    parser.add_argument("--host", type=host, default="127.0.0.1", help="address of the companions and ground station (default 127.0.0.1)")
    parser.add_argument("--transport", choices=("udp", "tcp"), default="udp",
                        help="udp (default): send to the companion's UDP port as PX4 SITL; tcp: listen on TCP "
                             "as ArduPilot SITL's SERIAL1 (companion: --connect tcp:HOST:PORT)")
    parser.add_argument("--base-port", type=udp_port_nonzero, default=None,
                        help=f"udp: companion i listens on base-port + i (default {PX4_ONBOARD_BASE_PORT}); tcp: "
                             f"vehicle i listens on base-port + 10*i (default {ARDUPILOT_SERIAL1_BASE_PORT})")
    parser.add_argument("--guid-timeout", type=positive_float, default=None, metavar="S",
                        help="ArduPilot flavour: GUID_TIMEOUT, stop in GUIDED after S seconds without a setpoint "
                             "(default 3, ArduPilot's)")
    parser.add_argument("--depth-port", type=udp_port_nonzero, default=DEPTH_BASE_PORT,
                        help=f"depth frames of vehicle i go to depth-port + i (default {DEPTH_BASE_PORT})")
    parser.add_argument("--gcs-port", type=udp_port, default=GCS_PORT,
                        help=f"ground-station port, 0 for none (default {GCS_PORT})")
    parser.add_argument("--start", type=finite_floats((3,), "--start"), default=[0.0, 0.0, 0.0], metavar="N,E,D",
                        help="start of vehicle 0 in local NED metres (default 0,0,0: on the ground at home)")
    parser.add_argument("--spacing", type=finite_float, default=3.0, help="vehicle i starts i * spacing metres east of vehicle 0")
    parser.add_argument("--yaw-deg", type=finite_float, default=0.0, help="initial heading in degrees from north (default 0)")
    parser.add_argument("--starts", metavar="FILE",
                        help="JSON list of {\"ned\": [N, E, D], \"yaw_deg\": Y}, one per vehicle: overrides "
                             "--start, --spacing and --yaw-deg")
    parser.add_argument("--airborne", action="store_true", help="start armed and hovering at --start (needs D < -0.5)")
    parser.add_argument("--dynamics", choices=DYNAMICS_NAMES, default="kinematic")
    parser.add_argument("--response", type=response_spec, default=None, metavar="SPEC",
                        help="kinematic only: each vehicle's velocity response, drawn once at start: a preset "
                             "(px4-sih) or FIELD=LOW:HIGH / FIELD=VALUE items over the nominal response, e.g. "
                             "command_delay_s=0.15 (an airframe that acts 0.15 s late) or the spec `python -m "
                             "sitl.real_autopilots fit RUN` prints (docs/simulator.md); the vehicle's own takeoff, "
                             "hold and landing fly it too; default nominal")
    parser.add_argument("--response-seed", type=int_range(0), default=None, metavar="N",
                        help="seed of the --response draw (default 0)")
    add_camera_arguments(parser)
    parser.add_argument("--signing-key", metavar="FILE", help="MAVLink 2 signing key: sign all, refuse unsigned")
    parser.add_argument("--odometry-child-frame", choices=("local_ned", "body_frd"), default="local_ned",
                        help="ODOMETRY velocity frame: local_ned as PX4 1.14+, body_frd as PX4 up to 1.13")
    parser.add_argument("--log", type=output_file, default="-", metavar="PATH",
                        help="JSON-lines event log (default '-': stdout)")
    parser.add_argument("--duration", type=positive_float, metavar="S", help="stop after S seconds")
    parser.add_argument("--trace", type=output_file, metavar="PATH",
                        help="write every vehicle's true position, airborne and crashed flags as JSON lines at 10 Hz")
    args = parser.parse_args(argv)
    if args.base_port is None:
        args.base_port = ARDUPILOT_SERIAL1_BASE_PORT if args.transport == "tcp" else PX4_ONBOARD_BASE_PORT
    if args.transport == "tcp":
        last = args.base_port + ARDUPILOT_INSTANCE_PORT_STEP * (args.n - 1)
        if last > 65535:
            parser.error(f"--base-port {args.base_port}: the TCP ports of {args.n} vehicles (every 10th) would pass 65535")
    else:
        check_port_block(parser, "--base-port", args.base_port, args.n)
    if args.response is not None and args.dynamics != "kinematic":
        parser.error(f"--response draws the kinematic backend's response; --dynamics {args.dynamics} has its own")
    if args.response_seed is not None and args.response is None:
        parser.error("--response-seed seeds the --response draw: give --response too")
    if args.guid_timeout is not None and args.autopilot != "ardupilot":
        parser.error("--guid-timeout is an ArduPilot parameter (use it with --autopilot ardupilot)")
    check_port_block(parser, "--depth-port", args.depth_port, args.n)
    if args.starts is not None:
        try:
            args.starts = _read_starts(Path(args.starts), args.n, args.airborne)
        except ValueError as err:
            parser.error(f"--starts {args.starts}: {err}")
    if args.airborne and args.starts is None and args.start[2] > -0.5:
        parser.error("--airborne needs a start altitude: --start N,E,D with D < -0.5 (altitude is -D)")
    if not args.airborne and args.starts is None and args.start[2] != 0.0:
        parser.error("a vehicle on the ground starts at D = 0; use --airborne to start in the air")
    if args.signing_key:
        from companion.mavlink_link import load_signing_key

        try:
            load_signing_key(args.signing_key)
        except ValueError as err:
            parser.error(f"--signing-key: {err}")
    check_camera_arguments(parser, args)
    return args


def vehicles_config(args: argparse.Namespace) -> VehiclesConfig:
    """The :class:`VehiclesConfig` of parsed options (:func:`parse_args`)."""
    if args.starts is not None:
        starts, yaws = args.starts
    else:
        starts = np.repeat(np.asarray(args.start, dtype=np.float64)[None], args.n, axis=0)
        starts[:, 1] += np.arange(args.n) * args.spacing
        yaws = np.full(args.n, math.radians(args.yaw_deg))
    key = None
    if args.signing_key:
        from companion.mavlink_link import load_signing_key

        key = load_signing_key(args.signing_key)
    return VehiclesConfig(
        starts_ned=starts, yaws_rad=yaws, autopilot=AutopilotKind(args.autopilot), host=args.host,
        base_port=args.base_port, depth_port=args.depth_port, gcs_port=args.gcs_port, airborne=args.airborne,
        dynamics=args.dynamics, camera=camera_config(args), signing_key=key,
        odometry_child_frame=args.odometry_child_frame, transport=args.transport, guided_timeout_s=args.guid_timeout,
        response=args.response, response_seed=args.response_seed or 0)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    config = vehicles_config(args)
    log = EventLog.open(args.log)
    trace = open(args.trace, "w", buffering=1) if args.trace else None  # noqa: SIM115
    vehicles = SimulatedVehicles(config, log, trace)
    ready = dict(n=config.n, autopilot=args.autopilot, dynamics=config.dynamics,
                 onboard_ports=[config.onboard_port(i) for i in range(config.n)], transport=config.transport,
                 depth_ports=[config.depth_port + i for i in range(config.n)], gcs_port=config.gcs_port or None,
                 camera=config.camera.describe(), signing=config.signing_key is not None,
                 response=describe_response(config.response, nominal_ranges()) if config.response else "nominal")
    connect = (f"tcp:{config.host}:{config.base_port}+10i" if config.transport == "tcp"
               else f"udp:{config.base_port}+i")
    banner = (f"sitl.vehicle: {config.n} {args.autopilot} vehicle(s) up; companion i: --connect "
              f"{connect} --camera sitl:{config.depth_port}+i")
    return serve(vehicles, args.duration, config.camera.hz, ready, banner)
