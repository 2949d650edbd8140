"""Simulated vehicles that speak MAVLink like PX4 SITL (or ArduCopter) — the companion's SITL.

    python -m sitl.vehicle --n 2                       # PX4 flavour, ports 14540, 14541
    python -m sitl.vehicle --n 1 --autopilot ardupilot

Runs N vehicles in one simulated world (the simulator's dynamics backend, raycast depth
camera and collision checks) in real time. Vehicle ``i`` (system id ``i + 1``):

* speaks MAVLink 2 to its companion: it sends from an ephemeral local UDP port to
  ``HOST:base-port + i`` (PX4 SITL's onboard port 14540 + i), where ``companion --connect
  udp:14540`` listens, and takes the companion's messages on that local port;
* optionally talks to a ground station the same way at ``HOST:gcs-port`` (QGroundControl's
  14550; all vehicles share it), and routes messages between the two links;
* sends its rendered depth frames to ``HOST:depth-port + i`` (format:
  :mod:`companion.depth_wire`), where ``companion --camera sitl:<port>`` listens.

What the autopilot does (modes, commands, failsafes, failure injection) is described in
:mod:`sitl.mavlink_autopilot`. Events (modes, arming, commands, crashes, failures) and a
status line per vehicle per second go to ``--log`` as JSON lines.
"""

from __future__ import annotations

import argparse
import json
import math
import select
import signal
import sys
import time
from pathlib import Path

import numpy as np

from companion.flight_modes import AutopilotKind
from companion.spec import CameraSpec
from sitl.cli_args import (
    ArgumentParser,
    MAX_CAMERA_HZ,
    MAX_SUPERSAMPLE,
    MAX_VEHICLES,
    box,
    check_camera,
    check_port_block,
    cylinder,
    cylinder_rows,
    finite_float,
    finite_floats,
    float_range,
    host,
    image_size,
    int_range,
    output_file,
    positive_float,
    udp_port,
    udp_port_nonzero,
)
from sitl.sim.camera import LANDED_CAMERA_HEIGHT_M, DepthCamera
from sitl.sim.collision import uav_uav_collisions
from sitl.depth_transport import DepthFrameSender
from sitl.sim.dynamics import DYNAMICS_NAMES, make_dynamics
from sitl.event_log import EventLog
from sitl.mavlink_autopilot import Body, MavlinkUdpLink, SimAutopilot

PHYSICS_DT_S = 0.02
COLLISION_RADIUS_M = 0.3
HARD_LANDING_M_S = 2.0


class SimWorld:
    """N simulated vehicles: dynamics, camera, collisions, and one autopilot each."""

    def __init__(self, args: argparse.Namespace, log: EventLog) -> None:
        n = args.n
        self.n, self.args, self.log = n, args, log
        self.dynamics = make_dynamics(args.dynamics, n)
        if args.starts is not None:
            starts, yaws = args.starts
        else:
            starts = np.repeat(np.asarray(args.start, dtype=np.float64)[None], n, axis=0)
            starts[:, 1] += np.arange(n) * args.spacing
            yaws = np.full(n, math.radians(args.yaw_deg))
        self.dynamics.reset(np.arange(n), starts, yaws)
        self.camera_spec = CameraSpec(width=args.camera_size[0], height=args.camera_size[1], hfov_deg=args.hfov,
                                      max_range_m=args.max_range)
        self.camera = DepthCamera(self.camera_spec, supersample=args.supersample)
        self.cylinders = np.asarray(args.cylinder, dtype=np.float64).reshape(1, -1, 5) if args.cylinder else None
        self.boxes = np.asarray(args.box, dtype=np.float64).reshape(1, -1, 6) if args.box else None
        self.sender = DepthFrameSender(args.host, args.depth_port, n, args.hfov, args.max_range)
        key = None
        if args.signing_key:
            from companion.mavlink_link import load_signing_key

            key = load_signing_key(args.signing_key)
        kind = AutopilotKind(args.autopilot)
        self.autopilots: list[SimAutopilot] = []
        for i in range(n):
            onboard = MavlinkUdpLink("onboard", (args.host, args.base_port + i), i + 1, key, link_id=1)
            gcs = MavlinkUdpLink("gcs", (args.host, args.gcs_port), i + 1, key, link_id=2) if args.gcs_port else None
            self.autopilots.append(SimAutopilot(i, kind, onboard, gcs, log, airborne=args.airborne,
                                                odometry_child_frame=args.odometry_child_frame, camera=self.sender))
        self.collided = np.zeros(n, dtype=bool)

    def body(self, i: int) -> Body:
        d = self.dynamics
        return Body(d.pos_ned[i], d.vel_ned[i], float(d.yaw_rad[i]), float(d.yaw_rate_rad_s[i]))

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
                    ap.crash(f"hit the ground at {sink:.1f} m/s")
            if not active[i] and not ap.airborne:
                d.vel_ned[i] = 0.0
                d.yaw_rate_rad_s[i] = 0.0
        flying = np.array([ap.airborne for ap in self.autopilots])
        hits = uav_uav_collisions(prev, d.pos_ned, flying, self.n, COLLISION_RADIUS_M)
        for i in np.flatnonzero(hits & ~self.collided):
            self.autopilots[i].crash("collision with another vehicle")
        self.collided |= hits
        for i, ap in enumerate(self.autopilots):
            ap.update(now_s, self.body(i))

    def render_and_send(self) -> None:
        d = self.dynamics
        camera_ned = d.pos_ned.copy()
        camera_ned[:, 2] = np.minimum(camera_ned[:, 2], -LANDED_CAMERA_HEIGHT_M)
        depth = self.camera.render(camera_ned, d.yaw_rad, self.n, boxes=self.boxes, cylinders=self.cylinders)
        for i in range(self.n):
            self.sender.send(i, depth[i])

    def status(self) -> None:
        for i, ap in enumerate(self.autopilots):
            self.log("status", vehicle=i, pos_ned=self.dynamics.pos_ned[i], vel_ned=self.dynamics.vel_ned[i],
                     yaw_deg=round(math.degrees(float(self.dynamics.yaw_rad[i])), 1), mode=ap.mode, armed=ap.armed,
                     airborne=ap.airborne, crashed=ap.crashed, setpoints=ap.setpoints_received,
                     last_setpoint_t=None if not math.isfinite(ap.last_setpoint_s) else
                     round(time.time() - (time.monotonic() - ap.last_setpoint_s), 4),
                     frames_sent=int(self.sender.sent[i]), refused_unsigned=sum(l.refused_unsigned for l in ap.links))

    def trace(self, stream) -> None:
        """One JSON line of ground truth: every vehicle's position and state (for evaluations)."""
        record = {"t": round(time.time(), 4), "pos_ned": self.dynamics.pos_ned.round(4).tolist(),
                  "airborne": [ap.airborne for ap in self.autopilots],
                  "crashed": [ap.crashed for ap in self.autopilots]}
        stream.write(json.dumps(record) + "\n")

    def close(self) -> None:
        for ap in self.autopilots:
            for link in ap.links:
                link.close()
        self.sender.close()


def run(world: SimWorld, duration_s: float | None, camera_hz: float, trace=None, trace_hz: float = 10.0) -> None:
    """Real-time loop: wait for messages, step physics at 50 Hz, render at ``camera_hz``.

    ``trace`` (a text stream) gets :meth:`SimWorld.trace` at ``trace_hz``.
    """
    stop: list[str] = []
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda signum, _frame: stop.append(signal.Signals(signum).name))
    by_fd = {link.fileno(): (ap, link) for ap in world.autopilots for link in ap.links}
    started = now = time.monotonic()
    next_physics, next_camera, next_status, next_trace = now, now, now + 1.0, now
    camera_period = 1.0 / camera_hz
    while not stop:
        if duration_s is not None and now - started >= duration_s:
            stop.append("duration")
            break
        timeout = max(0.0, min(next_physics, next_camera) - time.monotonic())
        try:
            readable, _, _ = select.select(list(by_fd), [], [], timeout)
        except InterruptedError:
            readable = []
        now = time.monotonic()
        for fd in readable:
            ap, link = by_fd[fd]
            for msg in link.receive():
                ap.handle(link, msg, now)
        if now >= next_physics:
            steps = 0
            while now >= next_physics and steps < 5:
                world.physics_step(now, PHYSICS_DT_S)
                next_physics += PHYSICS_DT_S
                steps += 1
            if now >= next_physics:  # more than 0.1 s behind: drop the backlog, stay real time
                world.log("overrun", behind_s=round(now - next_physics, 3))
                next_physics = now + PHYSICS_DT_S
        if now >= next_camera:
            world.render_and_send()
            next_camera += camera_period
            if next_camera <= now:  # fell behind: skip frames but keep the camera's time grid
                next_camera += math.ceil((now - next_camera) / camera_period + 1e-9) * camera_period
        for i, ap in enumerate(world.autopilots):
            ap.send_telemetry(now, world.body(i))
        if now >= next_status:
            world.status()
            next_status += 1.0
        if trace is not None and now >= next_trace:
            world.trace(trace)
            next_trace = max(next_trace + 1.0 / trace_hz, now)
    world.status()
    world.log("stopped", reason=stop[0] if stop else "?")


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
    parser.add_argument("--base-port", type=udp_port_nonzero, default=14540, help="companion i listens on base-port + i (default 14540)")
    parser.add_argument("--depth-port", type=udp_port_nonzero, default=14640, help="depth frames of vehicle i go to depth-port + i (default 14640)")
    parser.add_argument("--gcs-port", type=udp_port, default=14550, help="ground-station port, 0 for none (default 14550)")
    parser.add_argument("--start", type=finite_floats((3,), "--start"), default=[0.0, 0.0, 0.0], metavar="N,E,D",
                        help="start of vehicle 0 in local NED metres (default 0,0,0: on the ground at home)")
    parser.add_argument("--spacing", type=finite_float, default=3.0, help="vehicle i starts i * spacing metres east of vehicle 0")
    parser.add_argument("--yaw-deg", type=finite_float, default=0.0, help="initial heading in degrees from north (default 0)")
    parser.add_argument("--starts", metavar="FILE",
                        help="JSON list of {\"ned\": [N, E, D], \"yaw_deg\": Y}, one per vehicle: overrides "
                             "--start, --spacing and --yaw-deg")
    parser.add_argument("--airborne", action="store_true", help="start armed and hovering at --start (needs D < -0.5)")
    parser.add_argument("--dynamics", choices=DYNAMICS_NAMES, default="kinematic")
    parser.add_argument("--camera-hz", type=float_range(0.0, MAX_CAMERA_HZ, low_open=True), default=30.0,
                        help=f"depth frame rate, up to {MAX_CAMERA_HZ:g} (default 30; use a multiple of the policy's "
                             "control rate)")
    parser.add_argument("--camera-size", type=image_size, default=(32, 32), metavar="WxH", help="rendered resolution (default 32x32)")
    parser.add_argument("--hfov", type=finite_float, default=90.0, help="horizontal field of view in degrees (default 90)")
    parser.add_argument("--max-range", type=positive_float, default=20.0, help="camera range in metres (default 20)")
    parser.add_argument("--supersample", type=int_range(1, MAX_SUPERSAMPLE), default=4,
                        help=f"sub-rays per pixel side, 1..{MAX_SUPERSAMPLE} (default 4)")
    parser.add_argument("--cylinder", type=cylinder, action="append", metavar="N,E,R[,H]",
                        help="a vertical pole at N,E of radius R (and height H, default 30 m); repeatable")
    parser.add_argument("--box", type=box, action="append", metavar="N,E,D,HN,HE,HD",
                        help="an axis-aligned box: centre and half sizes in NED metres; repeatable")
    parser.add_argument("--signing-key", metavar="FILE", help="MAVLink 2 signing key: sign all, refuse unsigned")
    parser.add_argument("--odometry-child-frame", choices=("local_ned", "body_frd"), default="local_ned",
                        help="ODOMETRY velocity frame: local_ned as PX4 1.14+, body_frd as PX4 up to 1.13")
    parser.add_argument("--log", type=output_file, default="-", metavar="PATH",
                        help="JSON-lines event log (default '-': stdout)")
    parser.add_argument("--duration", type=positive_float, metavar="S", help="stop after S seconds")
    parser.add_argument("--trace", type=output_file, metavar="PATH",
                        help="write every vehicle's true position, airborne and crashed flags as JSON lines at 10 Hz")
    args = parser.parse_args(argv)
    check_port_block(parser, "--base-port", args.base_port, args.n)
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
    args.cylinder = cylinder_rows(args.cylinder)
    if args.signing_key:
        from companion.mavlink_link import load_signing_key

        try:
            load_signing_key(args.signing_key)
        except ValueError as err:
            parser.error(f"--signing-key: {err}")
    check_camera(parser, args)
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    log = EventLog.open(args.log)
    world = SimWorld(args, log)
    world.render_and_send()  # compile/load the camera kernel before announcing readiness
    log("ready", n=args.n, autopilot=args.autopilot, dynamics=args.dynamics,
        onboard_ports=[args.base_port + i for i in range(args.n)],
        depth_ports=[args.depth_port + i for i in range(args.n)], gcs_port=args.gcs_port or None,
        camera={"size": list(args.camera_size), "hfov_deg": args.hfov, "hz": args.camera_hz},
        signing=bool(args.signing_key))
    print(f"sitl.vehicle: {args.n} {args.autopilot} vehicle(s) up; companion i: --connect udp:{args.base_port}+i "
          f"--camera sitl:{args.depth_port}+i", file=sys.stderr, flush=True)
    trace = open(args.trace, "w", buffering=1) if args.trace else None  # noqa: SIM115
    try:
        run(world, args.duration, args.camera_hz, trace)
    finally:
        world.close()
        if trace is not None:
            trace.close()
        log.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
