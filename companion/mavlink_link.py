"""The companion's one MAVLink connection to its autopilot (pymavlink, MAVLink 2).

pymavlink is not thread-safe, so exactly one object — :class:`AutopilotLink`, driven by the
control loop's thread — owns the connection: it reads every message, keeps the latest
heartbeat and odometry, tracks commands until their COMMAND_ACK and sends setpoints.

What goes over the link:

* out: HEARTBEAT at 1 Hz as an onboard controller (component 191, the autopilot's system
  id); COMMAND_LONG (SET_MESSAGE_INTERVAL, arm, mode, takeoff, land) one at a time, each
  retried until acknowledged; SET_POSITION_TARGET_LOCAL_NED in ``MAV_FRAME_BODY_NED`` (8)
  with type_mask 1479 (velocity + yaw rate), the frame both PX4 and ArduPilot accept, and,
  to hold a point (at the goal, on the way out), in ``MAV_FRAME_LOCAL_NED`` (1) with type_mask
  2552 (position + yaw);
  STATUSTEXT for what the pilot should know.
* in: HEARTBEAT (PX4 or ArduPilot, mode, arming), ODOMETRY (PX4) or LOCAL_POSITION_NED +
  ATTITUDE (ArduPilot), COMMAND_ACK, and the run-time goal: SET_POSITION_TARGET_LOCAL_NED
  addressed to component 191 in ``MAV_FRAME_LOCAL_NED`` with the position fields valid.

With a signing key every outgoing message is signed and every unsigned incoming one is
refused (and reported), so neither setpoints nor goals can be injected without the key.

The link locks onto the first autopilot it hears: its (system, component), on UDP its source
address, and with signing its link id. Afterwards datagrams from other addresses are dropped
unparsed, and messages claiming the autopilot's ids on another signing link id (a replay of what
it sent to the ground station) are dropped; both are counted and reported once, never acted upon.
Run-time goals therefore reach the companion through the autopilot, which routes the ground
station's messages onto this link (PX4 ``MAV_x_FORWARD``, ArduPilot's routing), not from a ground
station sending to the companion's port directly. See :mod:`companion.mavlink_endpoint` for the
transport (per-datagram parsing, exclusive bind, verify-before-store signing).
"""

from __future__ import annotations

import errno
import math
import os
import re
import select
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

os.environ["MAVLINK20"] = "1"  # before pymavlink picks its wire protocol: always MAVLink 2

from pymavlink import mavutil  # noqa: E402

from companion.flight_modes import (  # noqa: E402
    MAV_AUTOPILOT_INVALID,
    AutopilotKind,
    is_companion_mode,
    is_landing_mode,
    mode_name,
)
from companion.frames import body_to_ned_matrix, euler_yaw_rate, quaternion_to_euler  # noqa: E402
from companion.mavlink_endpoint import UdpEndpoint, VerifyFirstMAVLink, new_parser, setup_signing  # noqa: E402

mavutil.set_dialect("common")
mavlink = mavutil.mavlink

MAV_COMP_ID_ONBOARD_COMPUTER = 191
MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_BODY_NED = 8
#: ignore position (bits 0-2), acceleration (6-8) and yaw (10): velocity + yaw rate.
TYPE_MASK_VELOCITY_YAW_RATE = 1479
#: ignore velocity (bits 3-5), acceleration (6-8) and yaw rate (11): position + yaw (a point to hold).
TYPE_MASK_POSITION_YAW = 2552
#: open() errors worth retrying until the heartbeat timeout: the autopilot's port is not there *yet*
#: (ArduPilot SITL's TCP SERIAL ports listen only after boot; a USB serial adapter appears late).
_RETRYABLE_OPEN_ERRNOS = {errno.ECONNREFUSED, errno.ENOENT, errno.ECONNRESET, errno.ECONNABORTED,
                          errno.EHOSTUNREACH, errno.ENETUNREACH, errno.ETIMEDOUT, errno.EAGAIN}
#: How long close() waits for the autopilot to take the last bytes of a TCP link (see close()).
TCP_CLOSE_DRAIN_S = 0.5
_TYPE_MASK_POSITION_IGNORED = 0b111
_WORLD_VELOCITY_FRAMES = {1, 14, 16, 18}  # LOCAL_NED, MOCAP_NED, VISION_NED, ESTIM_NED
_BODY_VELOCITY_FRAMES = {8, 9, 12}  # BODY_NED, BODY_OFFSET_NED, BODY_FRD
_NORTH_ALIGNED_POSE_FRAMES = {1, 14, 16, 18}
#: Telemetry beyond these is garbage, not a vehicle state: refused like NaN (issue 16, item 13).
MAX_ODOMETRY_DISTANCE_M = 1.0e6  # local NED position: 1000 km from the origin
MAX_ODOMETRY_SPEED_M_S = 150.0  # per axis: well above any multirotor
MAX_BODY_RATE_RAD_S = 35.0  # per axis: 2000 deg/s, the full scale of common IMU gyros
#: A body-to-NED attitude quaternion must be a unit one within this tolerance (float32 on the wire).
QUATERNION_NORM_TOLERANCE = 0.1
#: ODOMETRY counts as flowing (and is preferred to LOCAL_POSITION_NED + ATTITUDE) while its last
#: sample, good or refused, is younger than this; an ODOMETRY fault is dropped once it is older.
ODOMETRY_SOURCE_SWITCH_S = 0.5
MAV_RESULT_NAMES = {0: "ACCEPTED", 1: "TEMPORARILY_REJECTED", 2: "DENIED", 3: "UNSUPPORTED", 4: "FAILED",
                    5: "IN_PROGRESS", 6: "CANCELLED"}
COMMAND_NAMES = {400: "ARM/DISARM", 176: "DO_SET_MODE", 22: "NAV_TAKEOFF", 21: "NAV_LAND", 511: "SET_MESSAGE_INTERVAL"}

CONNECTION_FORMS = ("udp:PORT (listen on 0.0.0.0:PORT; PX4 SITL's onboard port is 14540), udpin:HOST:PORT, "
                    "udpout:HOST:PORT, tcp:HOST:PORT, tcpin:HOST:PORT, or a serial device such as /dev/ttyTHS1,921600")


class LinkError(RuntimeError):
    """The link cannot be opened, or no autopilot answers on it."""


def normalize_connection(text: str) -> str:
    """Turn a ``--connect`` value into a pymavlink connection string; raise ValueError if invalid.

    ``udp:14540`` is PX4's shorthand for listening on all interfaces at that port.
    """
    value = text.strip()
    if re.fullmatch(r"udp:\d+", value):
        port = int(value[4:])
        if not 1 <= port <= 65535:
            raise ValueError(f"invalid connection {text!r}: port must be in 1..65535")
        return f"udpin:0.0.0.0:{port}"
    match = re.fullmatch(r"(udp|udpin|udpout|tcp|tcpin):([^:]*):(\d+)", value)
    if match:
        scheme, host, port = match.groups()
        if not host or not 1 <= int(port) <= 65535:
            raise ValueError(f"invalid connection {text!r}: use {scheme}:HOST:PORT with a port in 1..65535")
        return f"{'udpin' if scheme == 'udp' else scheme}:{host}:{port}"
    match = re.fullmatch(r"(/dev/[^,\s]+|COM\d+)(?:,(\d+))?", value)
    if match:
        return value
    raise ValueError(f"invalid connection {text!r}: use {CONNECTION_FORMS}")


def load_signing_key(path: str | Path) -> bytes:
    """Read a MAVLink 2 signing key: 32 raw bytes, or 64 hex characters (one line)."""
    try:
        data = Path(path).read_bytes()
    except OSError as err:
        raise ValueError(f"cannot read signing key {path}: {err.strerror}") from err
    text = data.strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    if len(data) == 32:
        return data
    raise ValueError(f"signing key {path} must hold 32 raw bytes or 64 hex characters, "
                     f"got {len(data)} bytes (make one with: python -c 'import secrets; print(secrets.token_hex(32))')")


# --------------------------------------------------------------------------- telemetry


@dataclass
class Heartbeat:
    """The autopilot's latest HEARTBEAT."""

    sysid: int
    compid: int
    kind: AutopilotKind
    custom_mode: int
    base_mode: int
    system_status: int
    received_s: float

    @property
    def armed(self) -> bool:
        return bool(self.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    @property
    def mode(self) -> str:
        return mode_name(self.kind, self.custom_mode)

    @property
    def in_companion_mode(self) -> bool:
        """OFFBOARD (PX4) or GUIDED (ArduPilot): the autopilot follows our setpoints."""
        return is_companion_mode(self.kind, self.custom_mode)

    @property
    def landing(self) -> bool:
        return is_landing_mode(self.kind, self.custom_mode)


@dataclass
class Odometry:
    """The vehicle's pose and velocity in local NED, whichever messages they came from."""

    pos_ned: np.ndarray  # [3] m
    vel_ned: np.ndarray  # [3] m/s
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    yaw_rate_rad_s: float  # Euler yaw rate (heading change), not the body z rate
    received_s: float  # monotonic time of the (oldest) message it was built from
    source: str


class OdometryInvalid(ValueError):
    """Telemetry whose values cannot be a vehicle state (non-finite or out of range)."""


def _check_finite_in_range(source: str, what: str, values, limit: float) -> None:
    """Raise :class:`OdometryInvalid` naming ``source`` and ``what`` if a value is NaN/inf or beyond ``limit``."""
    array = np.asarray(values, dtype=np.float64)
    if not np.all(np.isfinite(array)):
        raise OdometryInvalid(f"{source} holds non-finite {what}")
    if np.any(np.abs(array) > limit):
        raise OdometryInvalid(f"{source} holds out-of-range {what} (max |value| {float(np.max(np.abs(array))):.3g} > {limit:g})")


def odometry_from_msg(msg, received_s: float) -> Odometry:
    """Odometry from an ODOMETRY message; raise ValueError for frames it cannot use.

    Raises :class:`OdometryInvalid` (a ValueError) for values no vehicle can have: NaN/inf or
    out-of-range position, velocity, attitude quaternion or angular rates.

    ``child_frame_id`` says in which frame the velocity is: PX4 up to 1.13 sends
    ``MAV_FRAME_BODY_FRD`` with the velocity in the body frame, PX4 1.14+ usually
    ``MAV_FRAME_LOCAL_NED`` with the velocity in NED. Both are handled.
    """
    if msg.frame_id not in _NORTH_ALIGNED_POSE_FRAMES:
        raise ValueError(f"ODOMETRY frame_id {msg.frame_id} is not a north-aligned local frame")
    if msg.child_frame_id not in _BODY_VELOCITY_FRAMES | _WORLD_VELOCITY_FRAMES:
        raise ValueError(f"ODOMETRY child_frame_id {msg.child_frame_id} is not a frame this companion knows")
    _check_finite_in_range("ODOMETRY", "position", [msg.x, msg.y, msg.z], MAX_ODOMETRY_DISTANCE_M)
    _check_finite_in_range("ODOMETRY", "velocity", [msg.vx, msg.vy, msg.vz], MAX_ODOMETRY_SPEED_M_S)
    _check_finite_in_range("ODOMETRY", "attitude", msg.q, 1.0 + QUATERNION_NORM_TOLERANCE)
    norm = math.sqrt(sum(float(v) ** 2 for v in msg.q))
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise OdometryInvalid(f"ODOMETRY attitude is not a unit quaternion (|q| = {norm:.3f})")
    _check_finite_in_range("ODOMETRY", "angular rates", [msg.rollspeed, msg.pitchspeed, msg.yawspeed],
                           MAX_BODY_RATE_RAD_S)
    roll, pitch, yaw = quaternion_to_euler(msg.q)
    vel = np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64)
    if msg.child_frame_id in _BODY_VELOCITY_FRAMES:
        vel = body_to_ned_matrix(roll, pitch, yaw) @ vel
    pos = np.array([msg.x, msg.y, msg.z], dtype=np.float64)
    return Odometry(pos, vel, roll, pitch, yaw, euler_yaw_rate(roll, pitch, msg.pitchspeed, msg.yawspeed),
                    received_s, "ODOMETRY")


def odometry_from_local_position(lpn, lpn_s: float, att, att_s: float) -> Odometry:
    """Odometry from LOCAL_POSITION_NED (NED position and velocity) + ATTITUDE (ArduPilot).

    Raises :class:`OdometryInvalid` for non-finite or out-of-range values.
    """
    _check_finite_in_range("LOCAL_POSITION_NED", "position", [lpn.x, lpn.y, lpn.z], MAX_ODOMETRY_DISTANCE_M)
    _check_finite_in_range("LOCAL_POSITION_NED", "velocity", [lpn.vx, lpn.vy, lpn.vz], MAX_ODOMETRY_SPEED_M_S)
    _check_finite_in_range("ATTITUDE", "attitude", [att.roll, att.pitch, att.yaw], 2 * math.pi)
    _check_finite_in_range("ATTITUDE", "angular rates", [att.rollspeed, att.pitchspeed, att.yawspeed],
                           MAX_BODY_RATE_RAD_S)
    pos = np.array([lpn.x, lpn.y, lpn.z], dtype=np.float64)
    vel = np.array([lpn.vx, lpn.vy, lpn.vz], dtype=np.float64)
    return Odometry(pos, vel, att.roll, att.pitch, att.yaw,
                    euler_yaw_rate(att.roll, att.pitch, att.pitchspeed, att.yawspeed),
                    min(lpn_s, att_s), "LOCAL_POSITION_NED+ATTITUDE")


# --------------------------------------------------------------------------- commands and events


@dataclass
class PendingCommand:
    """A COMMAND_LONG waiting for its COMMAND_ACK (retried with a rising confirmation)."""

    command: int
    params: tuple[float, ...]
    label: str
    attempts: int = 0
    last_sent_s: float = -1.0
    result: int | None = None
    failure: str | None = None

    @property
    def done(self) -> bool:
        return self.result is not None or self.failure is not None

    @property
    def accepted(self) -> bool:
        return self.result == mavlink.MAV_RESULT_ACCEPTED

    def describe_failure(self) -> str:
        if self.failure:
            return self.failure
        return f"{self.label} refused by the autopilot: MAV_RESULT_{MAV_RESULT_NAMES.get(self.result, self.result)}"


@dataclass
class LinkEvent:
    """Something the control loop must know about: a goal, a refused message, an autopilot text."""

    kind: str  # "goal", "refused_unsigned", "statustext", "odometry_frame", "io_error", "ignored_traffic", "relocked"
    detail: dict = field(default_factory=dict)


class AutopilotLink:
    """Owner of the pymavlink connection to one autopilot.

    Args:
        connection: a ``--connect`` value (see :func:`normalize_connection`).
        signing_key: 32-byte MAVLink 2 signing key, or None for no signing.
        command_timeout_s: wait this long for a COMMAND_ACK before resending.
        command_attempts: give a command up after this many unanswered sends.
    """

    def __init__(self, connection: str, *, signing_key: bytes | None = None,
                 command_timeout_s: float = 1.0, command_attempts: int = 3,
                 relock_after_s: float | None = None) -> None:
        self.connection = normalize_connection(connection)
        self.relock_after_s = relock_after_s  # UDP: follow the autopilot to a new port after this much silence
        self.relocks: list[tuple[tuple[str, int], tuple[str, int]]] = []  # (old, new) addresses, for events
        self.signing_key = signing_key
        self.command_timeout_s = command_timeout_s
        self.command_attempts = command_attempts
        self.conn = None
        self.heartbeat: Heartbeat | None = None
        self.odometry: Odometry | None = None
        #: Why the latest odometry sample was refused (e.g. "odometry invalid: ODOMETRY holds
        #: non-finite angular rates"), or None; cleared by the next good sample of that source.
        self.odometry_fault: str | None = None
        self._odometry_fault_source: str | None = None
        self._odometry_fault_s = -math.inf
        self._autopilot_link_id: int | None = None  # signing link id of the autopilot's stream
        self.dropped_foreign_link = 0  # autopilot ids on another signing link id (replays)
        self._reported_foreign_address = self._reported_foreign_link = False
        self._lpn = self._att = None
        self._lpn_s = self._att_s = -1.0
        self._odometry_refused_logged = False
        self._commands: list[PendingCommand] = []
        self._boot_s = time.monotonic()
        self.refused_unsigned = 0
        self._refused_ids: list[int] = []
        self.setpoints_sent = 0

    # ------------------------------------------------------------------ connection
    def open(self, retry_for_s: float = 0.0, on_wait=None) -> None:
        """Open the port or socket (does not wait for the autopilot).

        UDP goes through our own :class:`UdpEndpoint` (exclusive bind, one datagram at a time,
        one peer); TCP and serial through pymavlink's stream connection. A TCP connection that
        is refused or a serial device that does not exist yet is retried every 0.5 s for
        ``retry_for_s`` seconds (the autopilot may boot after us); ``on_wait(reason)`` is
        called once, on the first failure. Raises :class:`LinkError` when it gives up.
        """
        deadline = time.monotonic() + retry_for_s
        waited = False
        while True:
            try:
                self._open_once()
                return
            except LinkError as err:
                cause = err.__cause__
                code = getattr(cause, "errno", None)
                if code is None and cause is not None and cause.args and isinstance(cause.args[0], int):
                    code = cause.args[0]  # pyserial's SerialException(errno, text)
                if code not in _RETRYABLE_OPEN_ERRNOS or time.monotonic() + 0.5 > deadline:
                    if waited:
                        raise LinkError(f"{err} (retried for {retry_for_s:g} s, --heartbeat-timeout)") from cause
                    raise
                if not waited and on_wait is not None:
                    on_wait(str(err))
                waited = True
                time.sleep(0.5)

    def _open_once(self) -> None:
        scheme, _, rest = self.connection.partition(":")
        try:
            if scheme in ("udpin", "udpout"):
                host, _, port = rest.rpartition(":")
                self.conn = UdpEndpoint(scheme, host, int(port), 1, MAV_COMP_ID_ONBOARD_COMPUTER)
                self.conn.relock_after_s = self.relock_after_s
            else:
                # retries=0: one attempt; open() retries, bounded by the heartbeat timeout.
                self.conn = mavutil.mavlink_connection(self.connection, source_system=1,
                                                       source_component=MAV_COMP_ID_ONBOARD_COMPUTER,
                                                       dialect="common", autoreconnect=True, retries=0)
                # A byte stream keeps pymavlink's parser, with the verify-before-store signature check.
                self.conn.mav = new_parser(self.conn, 1, MAV_COMP_ID_ONBOARD_COMPUTER)
        except ModuleNotFoundError as err:
            raise LinkError(f"cannot open {self.connection}: {err.name} is missing (pip install pyserial for serial links)") from err
        except OSError as err:
            if err.errno == errno.EADDRINUSE:
                raise LinkError(f"cannot open {self.connection}: address already in use (another companion or "
                                "MAVLink router holds this port; stop it or pick another port)") from err
            raise LinkError(f"cannot open {self.connection}: {err}") from err
        except Exception as err:  # serial.SerialException, socket errors
            raise LinkError(f"cannot open {self.connection}: {err}") from err
        assert isinstance(self.conn.mav, VerifyFirstMAVLink)
        if self.signing_key is not None:
            setup_signing(self.conn.mav, self.signing_key, self._refuse_unsigned)

    def _refuse_unsigned(self, _mav, msg_id: int) -> bool:
        self.refused_unsigned += 1
        self._refused_ids.append(msg_id)
        return False

    def fileno(self) -> int | None:
        fd = getattr(self.conn, "fd", None)
        return fd if isinstance(fd, int) and fd >= 0 else None

    def close(self) -> None:
        """Close the link; on TCP, only after the autopilot has had the last setpoints.

        Closing a TCP socket that still holds unread telemetry makes the kernel send RST, and
        the peer may then drop the bytes we sent last that it has not read yet: the final hold
        setpoints were lost that way on ArduPilot (issue 18). So: shut down our sending side
        (FIN after the data), read and discard until the autopilot closes its side or
        ``TCP_CLOSE_DRAIN_S`` passes, then close.
        """
        if self.conn is None:
            return
        sock = getattr(self.conn, "port", None)
        if self.connection.startswith("tcp:") and isinstance(sock, socket.socket):
            try:
                sock.shutdown(socket.SHUT_WR)
                deadline = time.monotonic() + TCP_CLOSE_DRAIN_S
                sock.setblocking(False)
                while (remaining := deadline - time.monotonic()) > 0:
                    ready, _, _ = select.select([sock], [], [], remaining)
                    if ready and not sock.recv(65536):
                        break  # the autopilot closed too: it has read everything we sent
            except OSError:
                pass
        try:
            self.conn.close()
        except OSError:
            pass

    def wait_for_autopilot(self, timeout_s: float) -> Heartbeat:
        """Block until an autopilot's HEARTBEAT arrives; raise :class:`LinkError` after ``timeout_s``."""
        import select

        deadline = time.monotonic() + timeout_s
        while self.heartbeat is None:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                signing = " (or its messages are unsigned/signed with another key)" if self.signing_key else ""
                raise LinkError(f"no heartbeat from an autopilot on {self.connection} within {timeout_s:g} s: "
                                f"is the autopilot running and sending MAVLink to this port{signing}?")
            fd = self.fileno()
            if fd is not None:
                select.select([fd], [], [], min(remaining, 0.2))
            else:
                time.sleep(min(remaining, 0.01))
            self.receive(time.monotonic())
        return self.heartbeat

    # ------------------------------------------------------------------ receiving
    def receive(self, now_s: float, max_messages: int = 500) -> list[LinkEvent]:
        """Read every waiting message (at most ``max_messages``) and return the events among them."""
        events: list[LinkEvent] = []
        for _ in range(max_messages):
            try:
                msg = self.conn.recv_msg()
            except (OSError, EOFError) as err:
                events.append(LinkEvent("io_error", {"error": str(err)}))
                break
            if msg is None:
                break
            self._handle(msg, now_s, events)
        if self._refused_ids:
            names = sorted({self._msg_name(i) for i in self._refused_ids})
            events.append(LinkEvent("refused_unsigned", {"messages": names, "count": len(self._refused_ids)}))
            self._refused_ids.clear()
        self._report_ignored_traffic(events)
        return events

    @property
    def dropped_foreign_address(self) -> int:
        """Datagrams dropped because they came from another address than the autopilot's (UDP)."""
        return getattr(self.conn, "dropped_foreign", 0)

    def _report_ignored_traffic(self, events: list[LinkEvent]) -> None:
        """One event the first time traffic is dropped for each reason (the counters keep counting)."""
        hb = self.heartbeat
        if not self._reported_foreign_address and self.dropped_foreign_address:
            self._reported_foreign_address = True
            events.append(LinkEvent("ignored_traffic", {
                "reason": f"ignoring MAVLink from addresses other than the autopilot's "
                          f"{self.conn.locked_address[0]}:{self.conn.locked_address[1]}",
                "count": self.dropped_foreign_address}))
        if not self._reported_foreign_link and self.dropped_foreign_link:
            self._reported_foreign_link = True
            events.append(LinkEvent("ignored_traffic", {
                "reason": f"ignoring signed messages claiming the autopilot (system {hb.sysid}, component "
                          f"{hb.compid}) on link id other than {self._autopilot_link_id} (replayed?)",
                "count": self.dropped_foreign_link}))

    @staticmethod
    def _msg_name(msg_id: int) -> str:
        cls = mavlink.mavlink_map.get(msg_id)
        return cls.msgname if cls is not None else f"MSG{msg_id}"

    def _from_autopilot(self, msg) -> bool:
        hb = self.heartbeat
        return hb is not None and msg.get_srcSystem() == hb.sysid and msg.get_srcComponent() == hb.compid

    def _from_another_link(self, msg) -> bool:
        """A signed message with the autopilot's ids on another link id than the autopilot's own.

        The autopilot signs all it sends to us with one link id; the same ids on another link id
        are its traffic to someone else (the ground station), captured and replayed.
        """
        return (self._autopilot_link_id is not None and msg.get_signed() and self._from_autopilot(msg)
                and msg.get_link_id() != self._autopilot_link_id)

    def _handle(self, msg, now_s: float, events: list[LinkEvent]) -> None:
        if getattr(msg, "_relock_candidate", False):
            self._consider_relock(msg, now_s, events)
            return
        kind = msg.get_type()
        if kind == "BAD_DATA":
            return
        if self._from_another_link(msg):
            self.dropped_foreign_link += 1
            return
        if kind == "HEARTBEAT":
            self._on_heartbeat(msg, now_s)
        elif kind == "ODOMETRY" and self._from_autopilot(msg):
            try:
                odometry = odometry_from_msg(msg, now_s)
            except OdometryInvalid as err:
                self._set_odometry_fault("ODOMETRY", str(err), now_s)
            except ValueError as err:
                if not self._odometry_refused_logged:
                    self._odometry_refused_logged = True
                    events.append(LinkEvent("odometry_frame", {"error": str(err)}))
            else:
                self.odometry = odometry
                self._clear_odometry_fault("ODOMETRY")
        elif kind == "LOCAL_POSITION_NED" and self._from_autopilot(msg):
            self._lpn, self._lpn_s = msg, now_s
            self._merge_local_position()
        elif kind == "ATTITUDE" and self._from_autopilot(msg):
            self._att, self._att_s = msg, now_s
            self._merge_local_position()
        elif kind == "COMMAND_ACK" and self._from_autopilot(msg):
            self._on_command_ack(msg)
        elif kind == "SET_POSITION_TARGET_LOCAL_NED":
            goal = self._goal_from(msg)
            if goal is not None:
                events.append(LinkEvent("goal", {"goal_ned": goal, "from": [msg.get_srcSystem(), msg.get_srcComponent()],
                                                 "signed": bool(getattr(msg, "_signed", False))}))
        elif kind == "STATUSTEXT" and self._from_autopilot(msg):
            events.append(LinkEvent("statustext", {"severity": msg.severity, "text": msg.text}))

    def _on_heartbeat(self, msg, now_s: float) -> None:
        if msg.autopilot == MAV_AUTOPILOT_INVALID or msg.type in (mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER):
            return  # ground stations and other companions
        kind = AutopilotKind.from_heartbeat(msg.autopilot)
        if kind is None:
            return
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if self.heartbeat is not None and src != (self.heartbeat.sysid, self.heartbeat.compid):
            return  # another vehicle on a shared link: we fly the first one we saw
        if self.heartbeat is None:
            self.conn.mav.srcSystem = src[0]  # components of one vehicle share its system id
            self._lock_onto(msg)
        self.heartbeat = Heartbeat(src[0], src[1], kind, msg.custom_mode, msg.base_mode, msg.system_status, now_s)

    def _consider_relock(self, msg, now_s: float, events: list[LinkEvent]) -> None:
        """Follow the autopilot to a new address after it fell silent (an autopilot, router or MAVProxy
        restarted on a new source port): only on a HEARTBEAT from the same system, component and
        autopilot kind and, with signing, signed on the autopilot's own link id (so a replay captured
        on another link cannot take the lock). Anything else from a new address is ignored."""
        hb = self.heartbeat
        if (msg.get_type() != "HEARTBEAT" or hb is None
                or (msg.get_srcSystem(), msg.get_srcComponent()) != (hb.sysid, hb.compid)
                or AutopilotKind.from_heartbeat(msg.autopilot) is not hb.kind
                or msg.type in (mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER)):
            return
        if self.signing_key is not None and not (msg.get_signed() and msg.get_link_id() == self._autopilot_link_id):
            return
        old = self.conn.locked_address
        self.conn.lock(msg._source_addr)
        self.relocks.append((old, msg._source_addr))
        events.append(LinkEvent("relocked", {
            "reason": f"the autopilot (system {hb.sysid}) fell silent at {old[0]}:{old[1]} and now talks from "
                      f"{msg._source_addr[0]}:{msg._source_addr[1]}: following it there"}))
        self._on_heartbeat(msg, now_s)

    def _lock_onto(self, msg) -> None:
        """Remember the autopilot's address (UDP) and signing link id: the only ones accepted from now on."""
        address = getattr(msg, "_source_addr", None)
        if address is not None and hasattr(self.conn, "lock"):
            self.conn.lock(address)
        if self.signing_key is not None and msg.get_signed():
            self._autopilot_link_id = msg.get_link_id()

    def _set_odometry_fault(self, source: str, error: str, now_s: float) -> None:
        self.odometry_fault = f"odometry invalid: {error}"
        self._odometry_fault_source = source
        self._odometry_fault_s = now_s

    def _clear_odometry_fault(self, source: str) -> None:
        if self._odometry_fault_source == source:
            self.odometry_fault = self._odometry_fault_source = None

    def _merge_local_position(self) -> None:
        if self._lpn is None or self._att is None:
            return
        source = "LOCAL_POSITION_NED+ATTITUDE"
        try:
            odometry = odometry_from_local_position(self._lpn, self._lpn_s, self._att, self._att_s)
        except OdometryInvalid as err:
            self._set_odometry_fault(source, str(err), max(self._lpn_s, self._att_s))
            return
        self._clear_odometry_fault(source)
        if self._odometry_fault_source == "ODOMETRY" and self._lpn_s - self._odometry_fault_s >= ODOMETRY_SOURCE_SWITCH_S:
            self._clear_odometry_fault("ODOMETRY")  # ODOMETRY went silent: this pair is the source now
        if self.odometry is not None and self.odometry.source == "ODOMETRY" and self._lpn_s - self.odometry.received_s < ODOMETRY_SOURCE_SWITCH_S:
            return  # ODOMETRY is flowing: it is the better source (one consistent sample)
        if self._odometry_fault_source == "ODOMETRY":
            return  # the estimator just sent garbage on ODOMETRY: do not fly on its other output meanwhile
        self.odometry = odometry

    def _goal_from(self, msg) -> list[float] | None:
        """A run-time goal: addressed to us, in LOCAL_NED, with the position fields valid."""
        if msg.target_component != MAV_COMP_ID_ONBOARD_COMPUTER:
            return None
        if self.heartbeat is not None and msg.target_system not in (0, self.heartbeat.sysid):
            return None
        if msg.coordinate_frame != MAV_FRAME_LOCAL_NED or msg.type_mask & _TYPE_MASK_POSITION_IGNORED:
            return None
        goal = [float(msg.x), float(msg.y), float(msg.z)]
        return goal if all(math.isfinite(v) for v in goal) else None

    # ------------------------------------------------------------------ commands
    def queue_command(self, command: int, *params: float, label: str | None = None) -> PendingCommand:
        """Queue a COMMAND_LONG to the autopilot; sent after the ones before it are answered."""
        padded = tuple(float(p) for p in params) + (0.0,) * (7 - len(params))
        pending = PendingCommand(command, padded, label or COMMAND_NAMES.get(command, f"command {command}"))
        self._commands.append(pending)
        return pending

    def cancel_commands(self) -> None:
        """Forget every queued command: after a pilot's takeover nothing we asked for may be re-sent."""
        for pending in self._commands:
            pending.failure = pending.failure or f"{pending.label}: cancelled"
        self._commands.clear()

    def service_commands(self, now_s: float) -> None:
        """(Re)send the command at the head of the queue; give it up after the last attempt."""
        while self._commands and self._commands[0].done:
            self._commands.pop(0)
        if not self._commands or self.heartbeat is None:
            return
        head = self._commands[0]
        if head.attempts and now_s - head.last_sent_s < self.command_timeout_s:
            return
        if head.attempts >= self.command_attempts:
            hint = ("is the same signing key set on the autopilot?" if self.signing_key is not None
                    else "does the autopilot require MAVLink signing (--signing-key)?")
            head.failure = f"{head.label}: no COMMAND_ACK after {head.attempts} attempts ({hint})"
            self._commands.pop(0)
            return
        hb = self.heartbeat
        self.conn.mav.command_long_send(hb.sysid, hb.compid, head.command, head.attempts, *head.params)
        head.attempts += 1
        head.last_sent_s = now_s

    def _on_command_ack(self, msg) -> None:
        if not self._commands:
            return
        head = self._commands[0]
        if msg.command != head.command or head.attempts == 0:
            return
        if msg.result == mavlink.MAV_RESULT_IN_PROGRESS:
            head.last_sent_s = time.monotonic()  # still working on it: wait, do not resend
            return
        head.result = msg.result

    # ------------------------------------------------------------------ sending
    def time_boot_ms(self) -> int:
        return int((time.monotonic() - self._boot_s) * 1000) & 0xFFFFFFFF

    def send_heartbeat(self) -> None:
        """Our HEARTBEAT: an onboard controller that is active."""
        self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0,
                                     mavlink.MAV_STATE_ACTIVE)

    def send_velocity_setpoint(self, vel_fwd_m_s: float, vel_down_m_s: float, yaw_rate_rad_s: float) -> None:
        """A body-frame velocity + yaw-rate setpoint (MAV_FRAME_BODY_NED, type_mask 1479)."""
        hb = self.heartbeat
        self.conn.mav.set_position_target_local_ned_send(
            self.time_boot_ms(), hb.sysid, hb.compid, MAV_FRAME_BODY_NED, TYPE_MASK_VELOCITY_YAW_RATE,
            0.0, 0.0, 0.0, float(vel_fwd_m_s), 0.0, float(vel_down_m_s), 0.0, 0.0, 0.0, 0.0, float(yaw_rate_rad_s))
        self.setpoints_sent += 1

    def send_position_target(self, pos_ned, yaw_rad: float) -> None:
        """Hold a point: a LOCAL_NED position + yaw target (type_mask 2552), which PX4 (OFFBOARD)
        and ArduPilot (GUIDED, no GUID_TIMEOUT for positions) fly to and hold."""
        hb = self.heartbeat
        x, y, z = (float(v) for v in pos_ned)
        self.conn.mav.set_position_target_local_ned_send(
            self.time_boot_ms(), hb.sysid, hb.compid, MAV_FRAME_LOCAL_NED, TYPE_MASK_POSITION_YAW,
            x, y, z, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, float(yaw_rad), 0.0)
        self.setpoints_sent += 1

    def send_statustext(self, severity: int, text: str) -> None:
        """A STATUSTEXT for the pilot's ground station (cut to MAVLink's 50 characters)."""
        self.conn.mav.statustext_send(severity, text.encode("ascii", "replace")[:50])

    def request_message_interval(self, msg_id: int, rate_hz: float) -> PendingCommand:
        """Ask the autopilot to stream ``msg_id`` at ``rate_hz`` (MAV_CMD_SET_MESSAGE_INTERVAL)."""
        return self.queue_command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / rate_hz,
                                  label=f"SET_MESSAGE_INTERVAL({self._msg_name(msg_id)}, {rate_hz:g} Hz)")

    def heartbeat_age_s(self, now_s: float) -> float:
        return math.inf if self.heartbeat is None else now_s - self.heartbeat.received_s

    def odometry_age_s(self, now_s: float) -> float:
        return math.inf if self.odometry is None else now_s - self.odometry.received_s
