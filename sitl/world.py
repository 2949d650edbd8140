"""Depth cameras for autopilots this process does not simulate: ``python -m sitl.world``.

    python -m sitl.world --px4 3                                   # PX4 SITL instances 0..2
    python -m sitl.world --connect tcp:127.0.0.1:5760 --connect tcp:127.0.0.1:5770   # ArduPilot SITL -I 0, -I 1

What AirSim does for PX4: N autopilot SITL instances fly, each with its own physics, and
this process gives each of them a forward depth camera. It

* reads every vehicle's pose (LOCAL_POSITION_NED + ATTITUDE, asked for at ``--stream-rate``
  50 Hz) from that vehicle's own MAVLink telemetry, and heartbeats to each as a ground
  station at 1 Hz. Either ``--px4 N``: all PX4 SITL instances send their ground-station link
  to one UDP port (14550), instance ``i`` has system id ``i + 1``, and the messages are told
  apart by system id; or ``--connect CONN`` once per vehicle (any pymavlink connection, e.g.
  ArduPilot SITL ``-I i``'s SERIAL0 ``tcp:127.0.0.1:5760+10i``);
* places every vehicle in one world frame. Each autopilot's local NED frame starts at its own
  origin (where its estimator got its first position fix: its spawn point), so vehicle ``i``
  is drawn at its local position + the offset of its origin. By default the offsets come from
  the origins' latitudes and longitudes (GPS_GLOBAL_ORIGIN, else HOME_POSITION less its local
  position), relative to the first vehicle's origin, whose local frame is the world frame;
  ``--spawn-offsets``, ``--offset-line`` or ``--spacing`` give them instead;
* renders each vehicle's camera with :class:`sitl.sim.camera.DepthCamera` (the other vehicles as
  the simulator's UAV bodies, the ground and ``--box``/``--cylinder`` obstacles in the world
  frame) at ``--camera-hz`` and sends the frames to ``HOST:depth-port + i``
  (:mod:`sitl.depth_transport`), where ``companion --camera sitl:PORT`` listens: a companion
  cannot tell them from ``python -m sitl.vehicle``'s. With ``--px4``, ``i`` is the PX4 instance.

A vehicle whose pose is missing or older than 0.5 s gets no frames (its companion's
stale-camera failsafe then holds it) and is not drawn in the others' images. Events
(connected, tracking, lost, origins, refused commands) and a status line per vehicle per
second go to ``--log`` as JSON lines. docs/real_autopilots.md has the full PX4 and ArduPilot
setups.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import select
import signal
import socket
import sys
import time
from dataclasses import dataclass, field

import numpy as np

os.environ["MAVLINK20"] = "1"  # before pymavlink loads: MAVLink 2, like the companion

from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from companion.flight_modes import MAV_AUTOPILOT_INVALID, AutopilotKind  # noqa: E402
from companion.mavlink_link import normalize_connection  # noqa: E402
from companion.spec import CameraSpec  # noqa: E402
from sitl.sim.camera import LANDED_CAMERA_HEIGHT_M, DepthCamera  # noqa: E402
from sitl.cli_args import (
    ArgumentParser,  # noqa: E402
    MAX_CAMERA_HZ,
    MAX_SUPERSAMPLE,
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
    positive_int,
    udp_port_nonzero,
)
from sitl.depth_transport import DepthFrameSender  # noqa: E402
from sitl.event_log import EventLog  # noqa: E402

POSE_TIMEOUT_S = 0.5  # older telemetry: no frames for that vehicle, and it is not drawn
HEARTBEAT_PERIOD_S = 1.0
STREAM_CHECK_PERIOD_S = 5.0  # ask for the streams again while they come at under half the rate
ORIGIN_REQUEST_PERIOD_S = 2.0
REOPEN_PERIOD_S = 2.0  # retry a --connect link that cannot be opened or dropped
RECONNECTED_AFTER_S = 3.0  # a heartbeat after this much silence is logged as a new connection
EARTH_RADIUS_M = 6_371_000.0  # PX4's CONSTANTS_RADIUS_OF_EARTH, what it projects its local frame with
MAV_COMP_ID_MISSIONPLANNER = 190  # a ground station's component id
MAV_DATA_STREAM_POSITION = 6  # ArduPilot stream groups: LOCAL_POSITION_NED is in POSITION,
MAV_DATA_STREAM_EXTRA1 = 10  # ATTITUDE in EXTRA1
_NOT_AUTOPILOT_TYPES = {mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER}
_REFUSED = {mavlink.MAV_RESULT_DENIED, mavlink.MAV_RESULT_UNSUPPORTED, mavlink.MAV_RESULT_FAILED,
            mavlink.MAV_RESULT_TEMPORARILY_REJECTED}

GlobalPoint = tuple[float, float, float]  # latitude deg, longitude deg, altitude m AMSL


# --------------------------------------------------------------------------- the world frame


def ned_offset_m(ref: GlobalPoint, point: GlobalPoint) -> np.ndarray:
    """North/east offset in metres of ``point`` from ``ref`` (flat earth); down is 0.

    Down is 0 on purpose: every autopilot's local origin is where it started, on the ground,
    and the world has one flat ground at D = 0.
    """
    north = math.radians(point[0] - ref[0]) * EARTH_RADIUS_M
    east = math.radians(point[1] - ref[1]) * EARTH_RADIUS_M * math.cos(math.radians(ref[0]))
    return np.array([north, east, 0.0])


def shift_global(point: GlobalPoint, north_m: float, east_m: float) -> GlobalPoint:
    """``point`` moved by north/east metres (flat earth)."""
    lat = point[0] + math.degrees(north_m / EARTH_RADIUS_M)
    lon = point[1] + math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(point[0]))))
    return lat, lon, point[2]


class Layout:
    """Where each vehicle's local NED origin lies in the world frame.

    Args:
        fixed_offsets_ned: [N, 3] metres (``--spawn-offsets``, ``--offset-line``, ``--spacing``),
            or None: from the autopilots' global origins, relative to vehicle 0's.
    """

    def __init__(self, fixed_offsets_ned: np.ndarray | None) -> None:
        self.fixed = fixed_offsets_ned

    @property
    def from_origins(self) -> bool:
        return self.fixed is None

    def offset_ned(self, index: int, vehicles: list[Vehicle]) -> np.ndarray | None:
        """Vehicle ``index``'s origin in the world frame, or None while it is not known."""
        if self.fixed is not None:
            return self.fixed[index]
        ref, own = vehicles[0].origin, vehicles[index].origin
        if ref is None or own is None:
            return None
        return ned_offset_m(ref, own)

    def describe(self) -> str | list:
        return "from global origins (vehicle 0's local frame)" if self.fixed is None else self.fixed.round(3).tolist()


# --------------------------------------------------------------------------- vehicles


@dataclass
class Vehicle:
    """What the world knows about one vehicle, all from its own telemetry."""

    index: int
    source: str  # where its telemetry comes from, for the logs
    depth_port: int
    expected_sysid: int | None = None  # --px4: the instance's system id
    sysid: int | None = None  # the autopilot we listen to, from its first heartbeat
    compid: int | None = None
    kind: str | None = None  # "px4", "ardupilot" or "other"
    heartbeat_s: float = -math.inf
    pos_ned_local: np.ndarray | None = None  # LOCAL_POSITION_NED, in the autopilot's own frame
    pos_s: float = -math.inf
    yaw_rad: float = 0.0
    att_s: float = -math.inf
    origin: GlobalPoint | None = None  # of its local frame
    origin_source: str | None = None
    state: str = "waiting"  # waiting -> tracking (frames sent) <-> lost
    why: str = "no heartbeat yet"
    pose_msgs: int = 0
    pose_msgs_at_check: int = 0
    pose_rate_hz: float = 0.0
    frames_at_status: int = 0
    streams_requested_s: float = -math.inf
    origin_requested_s: float = -math.inf
    refusals_logged: set = field(default_factory=set)

    def pose_age_s(self, now_s: float) -> float:
        return now_s - min(self.pos_s, self.att_s)


class _UdpPeer:
    """pymavlink's output ``file`` for one peer: each packed message goes to one address."""

    def __init__(self, sock: socket.socket, addr: tuple[str, int]) -> None:
        self.sock, self.addr = sock, addr

    def write(self, buf: bytes) -> None:
        try:
            self.sock.sendto(buf, self.addr)
        except OSError:
            pass  # the instance is gone (ICMP port unreachable): its telemetry will go stale


class Px4GcsPort:
    """The UDP port where every PX4 SITL instance sends its ground-station link (14550).

    PX4 instance ``i`` (system id ``i + 1``) sends from its own local port (18570 + i); the
    messages are told apart by the system id in each one, and each instance is answered at
    the address its messages come from.
    """

    def __init__(self, host: str, port: int, index_by_sysid: dict[int, int], own_sysid: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.bind((host, port))
        except OSError:
            self.sock.close()
            raise
        self.sock.setblocking(False)
        self.index_by_sysid, self.own_sysid = index_by_sysid, own_sysid
        self._parsers: dict[tuple[str, int], mavlink.MAVLink] = {}  # one per sender: no mixed partial packets
        self._addr: dict[int, tuple[str, int]] = {}
        self._senders: dict[int, mavlink.MAVLink] = {}

    def fileno(self) -> int:
        return self.sock.fileno()

    def receive(self) -> list[tuple[int | None, object]]:
        """Every waiting message, with the index of the vehicle it came from (None: unknown system)."""
        out: list[tuple[int | None, object]] = []
        for _ in range(5000):
            try:
                data, addr = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                continue  # an ICMP error for something we sent to a vanished instance
            parser = self._parsers.get(addr)
            if parser is None:
                parser = self._parsers[addr] = mavlink.MAVLink(None)
                parser.robust_parsing = True
            try:
                msgs = parser.parse_buffer(data) or []
            except mavlink.MAVError:
                continue
            for msg in msgs:
                if msg.get_type() == "BAD_DATA":
                    continue
                index = self.index_by_sysid.get(msg.get_srcSystem())
                if index is not None and self._addr.get(index) != addr:  # new, or the instance restarted
                    self._addr[index] = addr
                    self._senders[index] = mavlink.MAVLink(_UdpPeer(self.sock, addr), srcSystem=self.own_sysid,
                                                           srcComponent=MAV_COMP_ID_MISSIONPLANNER)
                out.append((index, msg))
        return out

    def sender(self, index: int) -> mavlink.MAVLink | None:
        """The encoder that talks to vehicle ``index`` (None until it has been heard)."""
        return self._senders.get(index)

    def service(self, now_s: float, log: EventLog) -> None:
        pass  # a bound socket needs no upkeep

    def close(self) -> None:
        self.sock.close()


class VehicleConnection:
    """One vehicle's own MAVLink connection (a pymavlink connection string), reopened when it drops.

    ``tcp:HOST:PORT`` is a client: ArduPilot SITL ``-I i`` serves SERIAL0 on TCP 5760 + 10 i
    and waits for a client there before it starts.
    """

    def __init__(self, index: int, connection: str, own_sysid: int) -> None:
        self.index, self.connection, self.own_sysid = index, normalize_connection(connection), own_sysid
        self.conn = None
        self.next_open_s = 0.0
        self.last_error: str | None = None

    def fileno(self) -> int | None:
        if self.conn is None:
            return None
        port = getattr(self.conn, "port", None)  # tcp/udp: the socket (replaced on reconnect); serial: the device
        try:
            return port.fileno() if port is not None else self.conn.fd
        except (OSError, ValueError, AttributeError):
            return None

    def service(self, now_s: float, log: EventLog) -> None:
        """Open the connection if it is closed and a retry is due."""
        if self.conn is not None or now_s < self.next_open_s:
            return
        self.next_open_s = now_s + REOPEN_PERIOD_S
        try:
            with contextlib.redirect_stdout(sys.stderr):  # pymavlink prints; stdout may be the JSON log
                conn = mavutil.mavlink_connection(self.connection, source_system=self.own_sysid,
                                                  source_component=MAV_COMP_ID_MISSIONPLANNER, dialect="common",
                                                  autoreconnect=True, retries=0)
        except Exception as err:  # refused TCP, a busy UDP port, a missing serial device: retry later
            if str(err) != self.last_error:
                self.last_error = str(err)
                log("link_error", vehicle=self.index, connection=self.connection, error=str(err),
                    retry_every_s=REOPEN_PERIOD_S)
            return
        conn.mav.robust_parsing = True
        self.conn, self.last_error = conn, None
        log("link_open", vehicle=self.index, connection=self.connection)

    def receive(self) -> list[tuple[int | None, object]]:
        if self.conn is None:
            return []
        out: list[tuple[int | None, object]] = []
        try:
            with contextlib.redirect_stdout(sys.stderr):
                for _ in range(5000):
                    msg = self.conn.recv_msg()
                    if msg is None:
                        break
                    if msg.get_type() != "BAD_DATA":
                        out.append((self.index, msg))
        except (OSError, EOFError) as err:  # TCP peer gone and not back yet
            self.last_error = str(err)
            self.close()
        return out

    def sender(self, index: int) -> mavlink.MAVLink | None:
        return self.conn.mav if self.conn is not None else None

    def close(self) -> None:
        if self.conn is not None:
            with contextlib.suppress(OSError, AttributeError):
                self.conn.close()
            self.conn = None


# --------------------------------------------------------------------------- the world


class DepthWorld:
    """The vehicles, their links, the layout, the camera and the frame sender."""

    def __init__(self, args: argparse.Namespace, log: EventLog) -> None:
        self.args, self.log = args, log
        if args.px4:
            first = args.px4_first_instance
            self.vehicles = [Vehicle(j, f"PX4 instance {first + j} (system id {first + j + 1}) on udp "
                                        f"{args.gcs_host}:{args.gcs_port}", args.depth_port + first + j,
                                     expected_sysid=first + j + 1) for j in range(args.px4)]
            index_by_sysid = {v.expected_sysid: v.index for v in self.vehicles}
            self.links: list[Px4GcsPort | VehicleConnection] = [
                Px4GcsPort(args.gcs_host, args.gcs_port, index_by_sysid, args.sysid)]
            self.link_of = [self.links[0]] * len(self.vehicles)
        else:
            self.vehicles = [Vehicle(j, normalize_connection(c), args.depth_port + j) for j, c in enumerate(args.connect)]
            self.links = [VehicleConnection(j, c, args.sysid) for j, c in enumerate(args.connect)]
            self.link_of = list(self.links)
        self.n = len(self.vehicles)
        self.layout = Layout(args.offsets)
        self.camera = DepthCamera(CameraSpec(width=args.camera_size[0], height=args.camera_size[1], hfov_deg=args.hfov,
                                             max_range_m=args.max_range), supersample=args.supersample)
        self.boxes = np.asarray(args.box, dtype=np.float64).reshape(1, -1, 6) if args.box else None
        self.cylinders = np.asarray(args.cylinder, dtype=np.float64).reshape(1, -1, 5) if args.cylinder else None
        self.sender = DepthFrameSender(args.host, self.vehicles[0].depth_port, self.n, args.hfov, args.max_range)
        self.next_heartbeat_s = 0.0
        self.unknown_sysids: set[int] = set()
        self.render_ms: list[float] = []
        self.skipped_frames = 0
        self._cpu_at_status = (time.monotonic(), time.process_time())

    # ------------------------------------------------------------------ receiving
    def fds(self) -> dict[int, Px4GcsPort | VehicleConnection]:
        out = {}
        for link in self.links:
            fd = link.fileno()
            if fd is not None:
                out[fd] = link
        return out

    def receive(self, link: Px4GcsPort | VehicleConnection, now_s: float) -> None:
        for index, msg in link.receive():
            if index is None:
                sysid = msg.get_srcSystem()
                if sysid not in self.unknown_sysids:
                    self.unknown_sysids.add(sysid)
                    self.log("ignored_system", sysid=sysid, why=f"not one of the --px4 instances' system ids "
                                                               f"{sorted(v.expected_sysid for v in self.vehicles)}")
                continue
            self._on_message(self.vehicles[index], msg, now_s)

    def _on_message(self, v: Vehicle, msg, now_s: float) -> None:
        kind = msg.get_type()
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if kind == "HEARTBEAT":
            if msg.autopilot == MAV_AUTOPILOT_INVALID or msg.type in _NOT_AUTOPILOT_TYPES:
                return  # a companion or ground station on the same link
            if v.sysid is not None and src != (v.sysid, v.compid):
                return  # another autopilot routed through this link: we follow the first one
            if now_s - v.heartbeat_s > RECONNECTED_AFTER_S:
                autopilot = AutopilotKind.from_heartbeat(msg.autopilot)
                v.sysid, v.compid = src
                v.kind = autopilot.value if autopilot is not None else "other"
                v.streams_requested_s = -math.inf  # a restarted autopilot forgets our stream requests
                self.log("connected", vehicle=v.index, sysid=src[0], compid=src[1], autopilot=v.kind, source=v.source)
            v.heartbeat_s = now_s
            return
        if v.sysid is None or src != (v.sysid, v.compid):
            return
        if kind == "LOCAL_POSITION_NED":
            pos = np.array([msg.x, msg.y, msg.z], dtype=np.float64)
            if np.all(np.isfinite(pos)):
                v.pos_ned_local, v.pos_s = pos, now_s
                v.pose_msgs += 1
        elif kind == "ATTITUDE":
            if math.isfinite(msg.yaw):
                v.yaw_rad, v.att_s = float(msg.yaw), now_s
        elif kind == "GPS_GLOBAL_ORIGIN":
            self._set_origin(v, (msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3), "GPS_GLOBAL_ORIGIN")
        elif kind == "HOME_POSITION" and v.origin_source != "GPS_GLOBAL_ORIGIN":
            # Home is at local (x, y, z): the local frame's origin is home less that.
            x, y = (float(c) if math.isfinite(c) else 0.0 for c in (msg.x, msg.y))
            home = (msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
            self._set_origin(v, shift_global(home, -x, -y), "HOME_POSITION")
        elif kind == "COMMAND_ACK" and msg.result in _REFUSED:
            key = msg.command
            if key not in v.refusals_logged:
                v.refusals_logged.add(key)
                self.log("command_refused", vehicle=v.index, command=msg.command, result=msg.result)

    def _set_origin(self, v: Vehicle, origin: GlobalPoint, source: str) -> None:
        if not all(math.isfinite(c) for c in origin) or (origin[0] == 0.0 and origin[1] == 0.0):
            return  # no fix yet
        moved_m = math.inf if v.origin is None else float(np.linalg.norm(ned_offset_m(v.origin, origin)[:2]))
        if moved_m > 0.05 or source != v.origin_source:
            self.log("origin", vehicle=v.index, source=source, lat_deg=round(origin[0], 8), lon_deg=round(origin[1], 8),
                     alt_m=round(origin[2], 2))
        v.origin, v.origin_source = origin, source

    # ------------------------------------------------------------------ upkeep
    def service(self, now_s: float) -> None:
        """Open links, heartbeat at 1 Hz, ask for streams and origins when needed."""
        for link in self.links:
            link.service(now_s, self.log)
        heartbeat = now_s >= self.next_heartbeat_s
        if heartbeat:
            self.next_heartbeat_s = now_s + HEARTBEAT_PERIOD_S
        for v in self.vehicles:
            mav = self.link_of[v.index].sender(v.index)
            if mav is None:
                continue
            if heartbeat:  # a ground station's heartbeat: PX4 and ArduPilot keep streaming to it
                mav.heartbeat_send(mavlink.MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE)
            if v.sysid is None or now_s - v.heartbeat_s > RECONNECTED_AFTER_S:
                continue  # nobody to ask (gone autopilots are asked again when they are back)
            if now_s - v.streams_requested_s >= STREAM_CHECK_PERIOD_S:
                first = not math.isfinite(v.streams_requested_s)
                if not first:
                    v.pose_rate_hz = (v.pose_msgs - v.pose_msgs_at_check) / (now_s - v.streams_requested_s)
                if first or v.pose_rate_hz < 0.5 * self.args.stream_rate:
                    self._request_streams(v, mav)
                    self.log("streams_requested", vehicle=v.index, rate_hz=self.args.stream_rate,
                             measured_hz=None if first else round(v.pose_rate_hz, 1))
                v.streams_requested_s, v.pose_msgs_at_check = now_s, v.pose_msgs
            if self.layout.from_origins and v.origin is None and now_s - v.origin_requested_s >= ORIGIN_REQUEST_PERIOD_S:
                v.origin_requested_s = now_s
                for msg_id in (mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, mavlink.MAVLINK_MSG_ID_HOME_POSITION):
                    mav.command_long_send(v.sysid, v.compid, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, msg_id, 0, 0, 0, 0, 0, 0)

    def _request_streams(self, v: Vehicle, mav: mavlink.MAVLink) -> None:
        """LOCAL_POSITION_NED and ATTITUDE at the stream rate (per link, on both autopilots)."""
        if v.kind == AutopilotKind.ARDUPILOT.value:  # older ArduPilot knows only stream groups
            for stream in (MAV_DATA_STREAM_POSITION, MAV_DATA_STREAM_EXTRA1):
                mav.request_data_stream_send(v.sysid, v.compid, stream, int(round(self.args.stream_rate)), 1)
        for msg_id in (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_ATTITUDE):
            mav.command_long_send(v.sysid, v.compid, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id,
                                  1e6 / self.args.stream_rate, 0, 0, 0, 0, 0)

    # ------------------------------------------------------------------ rendering
    def _placed(self, v: Vehicle, now_s: float) -> tuple[np.ndarray | None, str]:
        """Vehicle ``v``'s position in the world frame now, or None and why not."""
        if v.sysid is None:
            return None, "no heartbeat yet"
        if v.pos_ned_local is None or not math.isfinite(v.att_s):
            return None, "no LOCAL_POSITION_NED/ATTITUDE yet"
        age = v.pose_age_s(now_s)
        if age > POSE_TIMEOUT_S:
            return None, f"telemetry {age:.2f} s old"
        offset = self.layout.offset_ned(v.index, self.vehicles)
        if offset is None:
            whose = "its" if v.origin is None else "vehicle 0's"
            return None, f"{whose} origin is unknown (no GPS_GLOBAL_ORIGIN or HOME_POSITION yet)"
        return v.pos_ned_local + offset, ""

    def render_and_send(self, now_s: float) -> None:
        """Render every vehicle with fresh telemetry, seeing only the others with fresh telemetry."""
        started = time.perf_counter()
        rows, positions = [], []
        for v in self.vehicles:
            pos, why = self._placed(v, now_s)
            self._update_state(v, pos, why)
            if pos is not None:
                rows.append(v)
                positions.append(pos)
        if not rows:
            return
        camera_ned = np.array(positions)
        camera_ned[:, 2] = np.minimum(camera_ned[:, 2], -LANDED_CAMERA_HEIGHT_M)  # above the gear, as sitl.vehicle
        yaw = np.array([v.yaw_rad for v in rows])
        depth = self.camera.render(camera_ned, yaw, len(rows), boxes=self.boxes, cylinders=self.cylinders)
        for k, v in enumerate(rows):
            self.sender.send(v.index, depth[k])
        self.render_ms.append((time.perf_counter() - started) * 1e3)

    def _update_state(self, v: Vehicle, pos: np.ndarray | None, why: str) -> None:
        v.why = why
        if pos is not None and v.state != "tracking":
            v.state = "tracking"
            self.log("tracking", vehicle=v.index, sysid=v.sysid, depth_port=v.depth_port,
                     origin_offset_ned=self.layout.offset_ned(v.index, self.vehicles), origin_source=v.origin_source)
        elif pos is None and v.state == "tracking":
            v.state = "lost"
            self.log("lost", vehicle=v.index, sysid=v.sysid, why=why, frames_sent=int(self.sender.sent[v.index]))

    def warm_up(self) -> None:
        """Load (or compile) the camera kernel before announcing readiness."""
        self.camera.render(np.array([[0.0, 0.0, -2.0], [5.0, 0.0, -2.0]]), np.zeros(2), 2,
                           boxes=self.boxes, cylinders=self.cylinders)

    # ------------------------------------------------------------------ logs
    def status(self, now_s: float) -> None:
        for v in self.vehicles:
            pos, _ = self._placed(v, now_s)
            frames = int(self.sender.sent[v.index])
            self.log("status", vehicle=v.index, sysid=v.sysid, state=v.state, why=v.why or None,
                     pose_age_ms=round(v.pose_age_s(now_s) * 1e3, 1) if math.isfinite(v.pose_age_s(now_s)) else None,
                     pos_ned=pos, yaw_deg=round(math.degrees(v.yaw_rad), 1), pose_rate_hz=round(v.pose_rate_hz, 1),
                     frames_sent=frames, frames_last_s=frames - v.frames_at_status, depth_port=v.depth_port)
            v.frames_at_status = frames
        wall, cpu = time.monotonic(), time.process_time()
        wall0, cpu0 = self._cpu_at_status
        self._cpu_at_status = (wall, cpu)
        ms = np.array(self.render_ms) if self.render_ms else np.zeros(1)
        self.log("world_status", tracking=sum(v.state == "tracking" for v in self.vehicles), vehicles=self.n,
                 cpu_percent=round(100.0 * (cpu - cpu0) / max(wall - wall0, 1e-6), 1),
                 render_ms_mean=round(float(ms.mean()), 2), render_ms_max=round(float(ms.max()), 2),
                 renders=len(self.render_ms), skipped_frames=self.skipped_frames)
        self.render_ms.clear()

    def close(self) -> None:
        for link in self.links:
            link.close()
        self.sender.close()


def run(world: DepthWorld, duration_s: float | None, camera_hz: float) -> None:
    """Real-time loop: read telemetry as it comes, render at ``camera_hz`` on a fixed time grid."""
    stop: list[str] = []
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda signum, _frame: stop.append(signal.Signals(signum).name))
    started = now = time.monotonic()
    next_camera, next_status = now, now + 1.0
    camera_period = 1.0 / camera_hz
    while not stop:
        if duration_s is not None and now - started >= duration_s:
            stop.append("duration")
            break
        fds = world.fds()
        timeout = min(max(0.0, min(next_camera, next_status) - time.monotonic()), 0.1)  # 0.1: links, heartbeats
        if fds:
            readable, _, _ = select.select(list(fds), [], [], timeout)
        else:
            time.sleep(timeout)
            readable = []
        now = time.monotonic()
        for fd in readable:
            world.receive(fds[fd], now)
        world.service(now)
        if now >= next_camera:
            world.render_and_send(now)
            next_camera += camera_period
            if next_camera <= now:  # fell behind: skip frames but keep the camera's time grid
                skipped = math.ceil((now - next_camera) / camera_period + 1e-9)
                next_camera += skipped * camera_period
                world.skipped_frames += skipped
        if now >= next_status:
            world.status(now)
            next_status += 1.0
    world.status(time.monotonic())
    world.log("stopped", reason=stop[0] if stop else "?")


# --------------------------------------------------------------------------- command line


def _offsets(args: argparse.Namespace, n: int, parser: argparse.ArgumentParser) -> np.ndarray | None:
    """The fixed origin offsets [n, 3] the layout options ask for, or None (from global origins)."""
    if args.spawn_offsets is not None:
        parse = finite_floats((3,), "--spawn-offsets")
        try:
            rows = [parse(item) for item in args.spawn_offsets.split(";") if item.strip()]
        except argparse.ArgumentTypeError as err:
            parser.error(f"--spawn-offsets: {err} (use N,E,D;N,E,D;... in metres, one per vehicle)")
        if len(rows) != n:
            parser.error(f"--spawn-offsets gives {len(rows)} offset(s) but there are {n} vehicles (one N,E,D each)")
        return np.array(rows, dtype=np.float64)
    if args.offset_line is not None or args.spacing is not None:
        bearing_deg, dist_m = args.offset_line if args.offset_line is not None else (90.0, args.spacing)
        step = np.array([math.cos(math.radians(bearing_deg)), math.sin(math.radians(bearing_deg)), 0.0]) * dist_m
        return np.arange(n)[:, None] * step[None, :]
    return None


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = ArgumentParser(prog="python -m sitl.world", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--px4", type=positive_int, metavar="N",
                        help="N PX4 SITL instances whose ground-station links all reach --gcs-port (instance i: "
                             "system id i + 1)")
    source.add_argument("--connect", action="append", metavar="CONN",
                        help="one vehicle's MAVLink connection, repeatable (vehicle i is the i-th): tcp:HOST:PORT "
                             "(ArduPilot SITL -I i: tcp:127.0.0.1:5760+10i), udpin:HOST:PORT, udpout:HOST:PORT, "
                             "udp:PORT or a serial device")
    parser.add_argument("--px4-first-instance", type=int_range(0, 254), default=0, metavar="K",
                        help="with --px4: the instances are K .. K+N-1 (default 0; PX4's gazebo-classic "
                             "sitl_multiple_run.sh starts at 1)")
    parser.add_argument("--gcs-port", type=udp_port_nonzero, default=14550,
                        help="with --px4: the UDP port the instances send their ground-station link to (default 14550)")
    parser.add_argument("--gcs-host", type=host, default="0.0.0.0", help="with --px4: the address to listen on (default 0.0.0.0)")
    layout = parser.add_mutually_exclusive_group()
    layout.add_argument("--spawn-offsets", metavar="N,E,D;N,E,D;...",
                        help="each vehicle's local origin (spawn point) in the world frame, metres, one per vehicle "
                             "(default: from the autopilots' global origins)")
    layout.add_argument("--offset-line", type=finite_floats((2,), "--offset-line"), metavar="BEARING,DIST",
                        help="vehicle i's origin i*DIST m from vehicle 0's towards BEARING degrees (ArduPilot's "
                             "sim_vehicle.py --auto-offset-line; PX4's gazebo-classic sitl_multiple_run.sh: 0,3)")
    layout.add_argument("--spacing", type=finite_float, metavar="M",
                        help="vehicle i's origin i*M m east of vehicle 0's (the same as --offset-line 90,M)")
    parser.add_argument("--host", type=host, default="127.0.0.1", help="where the companions listen for depth (default 127.0.0.1)")
    parser.add_argument("--depth-port", type=udp_port_nonzero, default=14640,
                        help="vehicle i's frames go to depth-port + i; with --px4, i is the instance (default 14640)")
    parser.add_argument("--camera-hz", type=float_range(0.0, MAX_CAMERA_HZ, low_open=True), default=30.0,
                        help=f"depth frame rate, up to {MAX_CAMERA_HZ:g} (default 30; use a multiple of the policy's "
                             "control rate)")
    parser.add_argument("--camera-size", type=image_size, default=(32, 32), metavar="WxH",
                        help="rendered resolution (default 32x32)")
    parser.add_argument("--hfov", type=finite_float, default=90.0, help="horizontal field of view in degrees (default 90)")
    parser.add_argument("--max-range", type=positive_float, default=20.0, help="camera range in metres (default 20)")
    parser.add_argument("--supersample", type=int_range(1, MAX_SUPERSAMPLE), default=4,
                        help=f"sub-rays per pixel side, 1..{MAX_SUPERSAMPLE} (default 4)")
    parser.add_argument("--cylinder", type=cylinder, action="append", metavar="N,E,R[,H]",
                        help="a vertical pole at N,E (world frame) of radius R (and height H, default 30 m); repeatable")
    parser.add_argument("--box", type=box, action="append", metavar="N,E,D,HN,HE,HD",
                        help="an axis-aligned box: centre and half sizes in world NED metres; repeatable")
    parser.add_argument("--stream-rate", type=float_range(0.0, 1000.0, low_open=True), default=50.0,
                        help="LOCAL_POSITION_NED and ATTITUDE rate asked of each autopilot (default 50 Hz)")
    parser.add_argument("--sysid", type=int_range(1, 255), default=250,
                        help="this ground station's MAVLink system id (default 250; QGroundControl uses 255)")
    parser.add_argument("--log", type=output_file, default="-", metavar="PATH", help="JSON-lines event log (default '-': stdout)")
    parser.add_argument("--duration", type=positive_float, metavar="S", help="stop after S seconds")
    args = parser.parse_args(argv)

    if args.connect:
        for conn in args.connect:
            try:
                normalize_connection(conn)
            except ValueError as err:
                parser.error(f"--connect: {err}")
        if args.px4_first_instance != 0:
            parser.error("--px4-first-instance only applies to --px4")
    n = args.px4 or len(args.connect)
    first = args.px4_first_instance if args.px4 else 0
    if args.px4 and not (0 <= first and first + n <= 255):
        parser.error(f"--px4 {n} from instance {first} needs system ids {first + 1}..{first + n}, beyond MAVLink's 1..255")
    check_port_block(parser, "--depth-port", args.depth_port + first, n)
    if not 1 <= args.sysid <= 255:
        parser.error(f"--sysid must be in 1..255, got {args.sysid}")
    if args.spacing is not None and not math.isfinite(args.spacing):
        parser.error("--spacing must be a finite number of metres")
    args.offsets = _offsets(args, n, parser)
    args.cylinder = cylinder_rows(args.cylinder)
    check_camera(parser, args)
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    log = EventLog.open(args.log)
    try:
        world = DepthWorld(args, log)
    except OSError as err:
        print(f"sitl.world: error: cannot listen on udp {args.gcs_host}:{args.gcs_port}: {err.strerror} "
              "(is QGroundControl or another ground station using it?)", file=sys.stderr)
        return 1
    try:
        world.warm_up()
        log("ready", vehicles=[{"vehicle": v.index, "source": v.source, "depth_port": v.depth_port}
                               for v in world.vehicles],
            layout=world.layout.describe(), camera={"size": list(args.camera_size), "hfov_deg": args.hfov,
                                                    "hz": args.camera_hz, "max_range_m": args.max_range},
            stream_rate_hz=args.stream_rate, pose_timeout_s=POSE_TIMEOUT_S)
        print(f"sitl.world: depth for {world.n} vehicle(s) on {args.host}:{world.vehicles[0].depth_port}"
              f"..{world.vehicles[-1].depth_port}", file=sys.stderr, flush=True)
        run(world, args.duration, args.camera_hz)
    finally:
        world.close()
        log.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
