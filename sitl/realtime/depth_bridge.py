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
* renders each vehicle's camera with :class:`sitl.camera.DepthCamera` (the other vehicles as
  the simulator's UAV bodies, the ground and ``--box``/``--cylinder`` obstacles in the world
  frame) at ``--camera-hz`` and sends the frames to ``HOST:depth-port + i``
  (:mod:`sitl.realtime.depth_transport`), where ``companion --camera sitl:PORT`` listens: a companion
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
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from companion.flight_modes import MAV_AUTOPILOT_INVALID, AutopilotKind, mode_name
from companion.frames import geodetic_to_ned, ned_to_geodetic
from companion.mavlink_link import normalize_connection
from sitl.cli_args import (
    ArgumentParser,
    check_port_block,
    finite_float,
    finite_floats,
    float_range,
    host,
    int_range,
    output_file,
    positive_float,
    positive_int,
    udp_port_nonzero,
)
from sitl.realtime.camera_feed import CameraConfig, CameraFeed, add_camera_arguments, camera_config, check_camera_arguments
from sitl.realtime.event_log import EventLog
from sitl.realtime.loop import serve
from sitl.realtime.depth_transport import DEPTH_BASE_PORT
from sitl.realtime.udp_endpoint import GCS_PORT, MavlinkUdpEndpoint, mavlink

from pymavlink import mavutil  # noqa: E402  (after companion.mavlink_endpoint: MAVLink 2)

POSE_TIMEOUT_S = 0.5  # older telemetry: no frames for that vehicle, and it is not drawn
HEARTBEAT_PERIOD_S = 1.0
STREAM_CHECK_PERIOD_S = 5.0  # ask for the streams again while they come at under half the rate
ORIGIN_REQUEST_PERIOD_S = 2.0
ORIGIN_REQUESTS_AFTER_HOME = 5  # GPS_GLOBAL_ORIGIN is still asked for this often once HOME_POSITION gave an origin
REOPEN_PERIOD_S = 2.0  # retry a --connect link that cannot be opened or dropped
RECONNECTED_AFTER_S = 3.0  # a heartbeat after this much silence is logged as a new connection
MAV_COMP_ID_MISSIONPLANNER = 190  # a ground station's component id
MAV_DATA_STREAM_POSITION = 6  # ArduPilot stream groups: LOCAL_POSITION_NED is in POSITION,
MAV_DATA_STREAM_EXTRA1 = 10  # ATTITUDE in EXTRA1
_NOT_AUTOPILOT_TYPES = {mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER}
_REFUSED = {mavlink.MAV_RESULT_DENIED, mavlink.MAV_RESULT_UNSUPPORTED, mavlink.MAV_RESULT_FAILED,
            mavlink.MAV_RESULT_TEMPORARILY_REJECTED}

GlobalPoint = tuple[float, float, float]  # latitude deg, longitude deg, altitude m AMSL


# --------------------------------------------------------------------------- the world frame


def ned_offset_m(ref: GlobalPoint, point: GlobalPoint) -> np.ndarray:
    """North/east offset in metres of ``point`` from ``ref`` (:func:`companion.frames.geodetic_to_ned`); down is 0.

    Down is 0 on purpose: every autopilot's local origin is where it started, on the ground,
    and the world has one flat ground at D = 0.
    """
    north, east, _ = geodetic_to_ned(np.array([point[0], point[1], 0.0]), ref[0], ref[1])
    return np.array([north, east, 0.0])


def shift_global(point: GlobalPoint, north_m: float, east_m: float) -> GlobalPoint:
    """``point`` moved by north/east metres (:func:`companion.frames.ned_to_geodetic`)."""
    lat, lon, _ = ned_to_geodetic(np.array([north_m, east_m, 0.0]), point[0], point[1])
    return float(lat), float(lon), point[2]


class Layout:
    """Where each vehicle's local NED origin lies in the world frame.

    Args:
        fixed_offsets_ned: [N, 3] metres (``--spawn-offsets``, ``--offset-line``, ``--spacing``),
            or None: from the autopilots' global origins, relative to vehicle 0's.
    """

    def __init__(self, fixed_offsets_ned: np.ndarray | None, fixed_source: str = "--spawn-offsets") -> None:
        self.fixed = fixed_offsets_ned
        self.fixed_source = fixed_source  # the option that gave the fixed offsets, for the logs

    def source(self, vehicle: Vehicle) -> str | None:
        """Where vehicle ``vehicle``'s offset comes from: the layout option, or its origin message."""
        return vehicle.origin_source if self.fixed is None else self.fixed_source

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
    vel_ned: np.ndarray | None = None  # LOCAL_POSITION_NED's velocity, m/s
    armed: bool | None = None  # from the autopilot's HEARTBEAT
    mode: str | None = None  # its flight mode's name (companion.flight_modes)
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
    origin_requests: int = 0  # GPS_GLOBAL_ORIGIN requests since HOME_POSITION gave an origin
    refusals_logged: set = field(default_factory=set)

    def pose_age_s(self, now_s: float) -> float:
        return now_s - min(self.pos_s, self.att_s)


class Px4GcsPort:
    """The UDP port where every PX4 SITL instance sends its ground-station link (14550).

    PX4 instance ``i`` (system id ``i + 1``) sends from its own local port (18570 + i); the
    messages are told apart by the system id in each one, and each instance is answered at
    the address its messages come from.
    """

    def __init__(self, host: str, port: int, index_by_sysid: dict[int, int], own_sysid: int) -> None:
        self.endpoint = MavlinkUdpEndpoint("gcs", (host, port), own_sysid, MAV_COMP_ID_MISSIONPLANNER)
        self.index_by_sysid = index_by_sysid
        self.sysid_by_index = {index: sysid for sysid, index in index_by_sysid.items()}

    def fileno(self) -> int:
        return self.endpoint.fileno()

    def receive(self) -> list[tuple[int | None, object]]:
        """Every waiting message, with the index of the vehicle it came from (None: unknown system)."""
        return [(self.index_by_sysid.get(msg.get_srcSystem()), msg) for msg in self.endpoint.receive()]

    def sender(self, index: int) -> mavlink.MAVLink | None:
        """The encoder that talks to vehicle ``index`` (None until it has been heard)."""
        return self.endpoint.encoder_for(self.sysid_by_index[index])

    def service(self, now_s: float, log: EventLog) -> None:
        pass  # a bound socket needs no upkeep

    def close(self) -> None:
        self.endpoint.close()


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


@dataclass(frozen=True)
class DepthBridgeConfig:
    """Which autopilots ``python -m sitl.world`` serves and how (its options, checked).

    Either ``px4_instances`` PX4 SITL instances (from ``px4_first_instance``; ground-station links
    on ``gcs_host:gcs_port``) or one pymavlink ``connections`` string per vehicle.
    ``offsets_ned`` [n, 3] m places each vehicle's local origin in the world frame (None: from the
    autopilots' global origins). Vehicle ``i``'s frames go to ``host:depth_port + i`` (with PX4,
    ``i`` is the instance).
    """

    px4_instances: int = 0
    connections: tuple[str, ...] = ()
    px4_first_instance: int = 0
    gcs_host: str = "0.0.0.0"
    gcs_port: int = GCS_PORT
    offsets_ned: np.ndarray | None = None
    offsets_source: str = "--spawn-offsets"  # the option that gave offsets_ned (logged as each vehicle's origin source)
    host: str = "127.0.0.1"
    depth_port: int = DEPTH_BASE_PORT
    camera: CameraConfig = field(default_factory=CameraConfig)
    stream_rate_hz: float = 50.0
    sysid: int = 250
    trace_path: str | None = None  # every vehicle's world position, velocity, mode and armed state as JSON lines
    trace_hz: float = 10.0

    def __post_init__(self) -> None:
        if bool(self.px4_instances) == bool(self.connections):
            raise ValueError("give either px4_instances or connections")


class DepthBridge:
    """Depth cameras for external autopilots: the vehicles, their links, the layout, the camera feed."""

    def __init__(self, config: DepthBridgeConfig, log: EventLog) -> None:
        self.config, self.log = config, log
        if config.px4_instances:
            first = config.px4_first_instance
            self.vehicles = [Vehicle(j, f"PX4 instance {first + j} (system id {first + j + 1}) on udp "
                                        f"{config.gcs_host}:{config.gcs_port}", config.depth_port + first + j,
                                     expected_sysid=first + j + 1) for j in range(config.px4_instances)]
            index_by_sysid = {v.expected_sysid: v.index for v in self.vehicles}
            self.links: list[Px4GcsPort | VehicleConnection] = [
                Px4GcsPort(config.gcs_host, config.gcs_port, index_by_sysid, config.sysid)]
            self.link_of = [self.links[0]] * len(self.vehicles)
        else:
            self.vehicles = [Vehicle(j, normalize_connection(c), config.depth_port + j)
                             for j, c in enumerate(config.connections)]
            self.links = [VehicleConnection(j, c, config.sysid) for j, c in enumerate(config.connections)]
            self.link_of = list(self.links)
        self.n = len(self.vehicles)
        self.layout = Layout(config.offsets_ned, config.offsets_source)
        self.feed = CameraFeed(config.camera, config.host, self.vehicles[0].depth_port, self.n)
        self.next_heartbeat_s = 0.0
        self.unknown_sysids: set[int] = set()
        self.unknown_messages: set[tuple[int | None, str]] = set()
        self.render_ms: list[float] = []
        self.skipped_frames = 0
        self._cpu_at_status = (time.monotonic(), time.process_time())
        self.trace = EventLog.open(config.trace_path) if config.trace_path else None
        self.next_trace_s = 0.0

    # ------------------------------------------------------------------ receiving
    def fds(self) -> dict[int, Px4GcsPort | VehicleConnection]:
        out = {}
        for link in self.links:
            fd = link.fileno()
            if fd is not None:
                out[fd] = link
        return out

    def wake_s(self) -> float:
        return math.inf  # nothing between messages, frames and status lines but link upkeep (at 10 Hz)

    def tick(self, now_s: float) -> None:
        self.service(now_s)
        if self.trace is not None and now_s >= self.next_trace_s:
            self.next_trace_s = max(self.next_trace_s + 1.0 / self.config.trace_hz, now_s)
            self._write_trace(now_s)

    def _write_trace(self, now_s: float) -> None:
        """One ``--trace`` line: per vehicle its world position (None unless placed), velocity, heading (rad from
        north), mode, armed.

        The positions are the autopilots' estimates placed by the layout, as they are drawn: what
        scripts measure arrival, separation and stopping distances with (``sitl.real_autopilots``).
        """
        placed = [self._placed(v, now_s)[0] for v in self.vehicles]
        self.trace("pose", pos_ned=[None if p is None else p.round(3).tolist() for p in placed],
                   vel_ned=[None if v.vel_ned is None else v.vel_ned.round(3).tolist() for v in self.vehicles],
                   yaw_rad=[round(v.yaw_rad, 4) for v in self.vehicles],
                   mode=[v.mode for v in self.vehicles], armed=[v.armed for v in self.vehicles])

    def receive(self, link: Px4GcsPort | VehicleConnection, now_s: float) -> None:
        for index, msg in link.receive():
            if msg.get_type().startswith("UNKNOWN_"):
                self._skip_unknown(msg)
                continue
            if index is None:
                sysid = msg.get_srcSystem()
                if sysid not in self.unknown_sysids:
                    self.unknown_sysids.add(sysid)
                    self.log("ignored_system", sysid=sysid, why=f"not one of the --px4 instances' system ids "
                                                               f"{sorted(v.expected_sysid for v in self.vehicles)}")
                continue
            self._on_message(self.vehicles[index], msg, now_s)

    def _skip_unknown(self, msg) -> None:
        """Log once per system and message id a message pymavlink's dialect does not define.

        pymavlink hands such a message over as ``UNKNOWN_<id>`` without its header, so its
        system id reads 0; the header is still in the raw bytes. PX4 sends several messages
        that are in PX4's common.xml but newer than pymavlink's: at start CURRENT_EVENT_SEQUENCE
        (411) and EVENT (410) of its events interface, then LINK_NODE_STATUS (8) and
        TIME_ESTIMATE_TO_TARGET (380). That was the ``ignored_system sysid 0`` of issue 18.
        """
        raw = bytes(getattr(msg, "_msgbuf", b""))
        sysid = compid = None
        if len(raw) >= 10 and raw[0] == 0xFD:  # MAVLink 2: magic, len, incompat, compat, seq, sysid, compid, id x3
            sysid, compid = raw[5], raw[6]
        elif len(raw) >= 6 and raw[0] == 0xFE:  # MAVLink 1: magic, len, seq, sysid, compid, id
            sysid, compid = raw[3], raw[4]
        msg_id = msg.get_type()[len("UNKNOWN_"):]
        key = (sysid, msg_id)
        if key not in self.unknown_messages:
            self.unknown_messages.add(key)
            self.log("unknown_message", msg_id=int(msg_id) if msg_id.isdigit() else msg_id, sysid=sysid, compid=compid,
                     why="not in pymavlink's common dialect (newer than the installed pymavlink); skipped")

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
            v.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            kind_ = AutopilotKind.from_heartbeat(msg.autopilot)
            v.mode = mode_name(kind_, msg.custom_mode) if kind_ is not None else str(msg.custom_mode)
            return
        if v.sysid is None or src != (v.sysid, v.compid):
            return
        if kind == "LOCAL_POSITION_NED":
            pos = np.array([msg.x, msg.y, msg.z], dtype=np.float64)
            if np.all(np.isfinite(pos)):
                v.pos_ned_local, v.pos_s = pos, now_s
                v.vel_ned = np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64)
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
                     alt_m=round(origin[2], 2), used=self.layout.from_origins)
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
                if first or v.pose_rate_hz < 0.5 * self.config.stream_rate_hz:
                    self._request_streams(v, mav)
                    self.log("streams_requested", vehicle=v.index, rate_hz=self.config.stream_rate_hz,
                             measured_hz=None if first else round(v.pose_rate_hz, 1))
                v.streams_requested_s, v.pose_msgs_at_check = now_s, v.pose_msgs
            # GPS_GLOBAL_ORIGIN is the local frame's origin itself; HOME_POSITION (less its local
            # position) only stands in until it comes, so it is asked for a while longer (PX4
            # answers HOME_POSITION first; the two differ by up to ~0.5 m in SIH).
            wants_origin = v.origin is None or (v.origin_source != "GPS_GLOBAL_ORIGIN"
                                                and v.origin_requests < ORIGIN_REQUESTS_AFTER_HOME)
            if self.layout.from_origins and wants_origin and now_s - v.origin_requested_s >= ORIGIN_REQUEST_PERIOD_S:
                v.origin_requested_s = now_s
                if v.origin is not None:
                    v.origin_requests += 1
                msg_ids = [mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN]
                if v.origin is None:
                    msg_ids.append(mavlink.MAVLINK_MSG_ID_HOME_POSITION)
                for msg_id in msg_ids:
                    mav.command_long_send(v.sysid, v.compid, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, msg_id, 0, 0, 0, 0, 0, 0)

    def _request_streams(self, v: Vehicle, mav: mavlink.MAVLink) -> None:
        """LOCAL_POSITION_NED and ATTITUDE at the stream rate (per link, on both autopilots)."""
        if v.kind == AutopilotKind.ARDUPILOT.value:  # older ArduPilot knows only stream groups
            for stream in (MAV_DATA_STREAM_POSITION, MAV_DATA_STREAM_EXTRA1):
                mav.request_data_stream_send(v.sysid, v.compid, stream, int(round(self.config.stream_rate_hz)), 1)
        for msg_id in (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_ATTITUDE):
            mav.command_long_send(v.sysid, v.compid, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id,
                                  1e6 / self.config.stream_rate_hz, 0, 0, 0, 0, 0)

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
        self.feed.render_and_send([v.index for v in rows], np.array(positions), np.array([v.yaw_rad for v in rows]))
        self.render_ms.append((time.perf_counter() - started) * 1e3)

    def _update_state(self, v: Vehicle, pos: np.ndarray | None, why: str) -> None:
        v.why = why
        if pos is not None and v.state != "tracking":
            v.state = "tracking"
            # The source of the offset actually used: with a fixed layout the autopilot's own
            # GPS_GLOBAL_ORIGIN (ArduPilot sends it unasked) is logged but not used (issue 18, item 5).
            self.log("tracking", vehicle=v.index, sysid=v.sysid, depth_port=v.depth_port,
                     origin_offset_ned=self.layout.offset_ned(v.index, self.vehicles),
                     origin_source=self.layout.source(v), autopilot_origin_source=v.origin_source)
        elif pos is None and v.state == "tracking":
            v.state = "lost"
            self.log("lost", vehicle=v.index, sysid=v.sysid, why=why, frames_sent=self.feed.frames_sent(v.index))

    def warm_up(self) -> None:
        """Load (or compile) the camera kernel before announcing readiness."""
        self.feed.render(np.array([[0.0, 0.0, -2.0], [5.0, 0.0, -2.0]]), np.zeros(2))

    # ------------------------------------------------------------------ logs
    def status(self, now_s: float) -> None:
        for v in self.vehicles:
            pos, _ = self._placed(v, now_s)
            frames = self.feed.frames_sent(v.index)
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
        self.feed.close()
        if self.trace is not None:
            self.trace.close()


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
        args.offsets_source = "--offset-line" if args.offset_line is not None else "--spacing"
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
    parser.add_argument("--gcs-port", type=udp_port_nonzero, default=GCS_PORT,
                        help=f"with --px4: the UDP port the instances send their ground-station link to (default {GCS_PORT})")
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
    parser.add_argument("--depth-port", type=udp_port_nonzero, default=DEPTH_BASE_PORT,
                        help=f"vehicle i's frames go to depth-port + i; with --px4, i is the instance (default {DEPTH_BASE_PORT})")
    add_camera_arguments(parser, frame="world")
    parser.add_argument("--stream-rate", type=float_range(0.0, 1000.0, low_open=True), default=50.0,
                        help="LOCAL_POSITION_NED and ATTITUDE rate asked of each autopilot (default 50 Hz)")
    parser.add_argument("--sysid", type=int_range(1, 255), default=250,
                        help="this ground station's MAVLink system id (default 250; QGroundControl uses 255)")
    parser.add_argument("--log", type=output_file, default="-", metavar="PATH", help="JSON-lines event log (default '-': stdout)")
    parser.add_argument("--trace", type=output_file, metavar="PATH",
                        help="JSON lines at 10 Hz: every vehicle's world position and velocity (the autopilots' "
                             "estimates, as drawn), flight mode and armed state")
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
    args.offsets_source = "--spawn-offsets"
    args.offsets = _offsets(args, n, parser)
    check_camera_arguments(parser, args)
    return args


def depth_bridge_config(args: argparse.Namespace) -> DepthBridgeConfig:
    """The :class:`DepthBridgeConfig` of parsed options (:func:`parse_args`)."""
    return DepthBridgeConfig(
        px4_instances=args.px4 or 0, connections=tuple(args.connect or ()), px4_first_instance=args.px4_first_instance,
        gcs_host=args.gcs_host, gcs_port=args.gcs_port, offsets_ned=args.offsets, offsets_source=args.offsets_source, host=args.host,
        depth_port=args.depth_port, camera=camera_config(args), stream_rate_hz=args.stream_rate, sysid=args.sysid,
        trace_path=args.trace)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    config = depth_bridge_config(args)
    log = EventLog.open(args.log)
    try:
        bridge = DepthBridge(config, log)
    except OSError as err:
        print(f"sitl.world: error: cannot listen on udp {config.gcs_host}:{config.gcs_port}: {err.strerror} "
              "(is QGroundControl or another ground station using it?)", file=sys.stderr)
        log.close()
        return 1
    ready = dict(vehicles=[{"vehicle": v.index, "source": v.source, "depth_port": v.depth_port} for v in bridge.vehicles],
                 layout=bridge.layout.describe(),
                 camera={**config.camera.describe(), "max_range_m": config.camera.spec.max_range_m},
                 stream_rate_hz=config.stream_rate_hz, pose_timeout_s=POSE_TIMEOUT_S)
    banner = (f"sitl.world: depth for {bridge.n} vehicle(s) on {config.host}:{bridge.vehicles[0].depth_port}"
              f"..{bridge.vehicles[-1].depth_port}")
    return serve(bridge, args.duration, config.camera.hz, ready, banner)


if __name__ == "__main__":
    raise SystemExit(main())
