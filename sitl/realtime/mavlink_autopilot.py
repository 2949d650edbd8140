"""A simulated autopilot that speaks MAVLink 2 like PX4 SITL or ArduCopter SITL.

One :class:`SimAutopilot` per simulated vehicle. It has two links: the *onboard* link to
its companion (PX4 SITL sends to UDP 14540 + i) and an optional *ground-station* link. It
decides what velocity the vehicle's dynamics track from its flight mode, answers commands
with COMMAND_ACK, streams telemetry and forwards messages between its links like a real
autopilot's MAVLink router (so a ground station can reach the companion, component 191).

What it implements, per flavour:

=============================  ==================================  =================================
                               PX4                                 ArduPilot (ArduCopter)
=============================  ==================================  =================================
HEARTBEAT.autopilot            MAV_AUTOPILOT_PX4 (12)              MAV_AUTOPILOT_ARDUPILOTMEGA (3)
custom_mode                    (main << 16) | (sub << 24)          mode number
start mode (ground/airborne)   POSCTL / AUTO.LOITER                STABILIZE / LOITER
companion mode                 OFFBOARD (6), accepted only after   GUIDED (4), any time
                               >= 1 s of setpoints at > 2 Hz
setpoint loss                  OFFBOARD -> AUTO.LOITER after 1 s   GUIDED stops (zero velocity) after
                               (COM_OF_LOSS_T)                     GUID_TIMEOUT (3 s), stays GUIDED;
                                                                   a position target never times out
hold modes (hand-back)         AUTO.LOITER (Hold)                  LOITER, BRAKE, POSHOLD: hold
                                                                   position (RC sticks centred)
setpoint frames accepted       LOCAL_NED (1), BODY_NED (8);        LOCAL_NED (1), LOCAL_OFFSET_NED
                               9 and 12 dropped                    (7), BODY_NED (8), BODY_OFFSET_NED
                                                                   (9); 12 dropped
position targets               LOCAL_NED (1), position bits        LOCAL_NED (1), position bits
                               only: flown to and held             only: flown to and held
odometry                       ODOMETRY (child_frame_id            LOCAL_POSITION_NED + ATTITUDE
                               LOCAL_NED, or BODY_FRD as before    (ODOMETRY refused)
                               PX4 1.14), LOCAL_POSITION_NED,
                               ATTITUDE
NAV_TAKEOFF param7             altitude AMSL (home 488 m), NaN:    altitude above home, GUIDED only
                               2.5 m above home
=============================  ==================================  =================================

Commands: ARM_DISARM (400), DO_SET_MODE (176) and SET_MODE, NAV_TAKEOFF (22), NAV_LAND (21),
SET_MESSAGE_INTERVAL (511), REQUEST_MESSAGE (512), REQUEST_AUTOPILOT_CAPABILITIES (520) and
INJECT_FAILURE (420, always enabled in this simulator): unit SENSOR_GPS (4) stops the position
outputs (ODOMETRY, LOCAL_POSITION_NED, GLOBAL_POSITION_INT), SENSOR_DISTANCE_SENSOR (7) is the
depth camera (OFF stops it, GARBAGE sends truncated frames, WRONG frames without valid
pixels), SYSTEM_MAVLINK_SIGNAL (105) silences the onboard link both ways; type OK (0)
restores. A mode or arming change is announced with an immediate HEARTBEAT.

The kinematic dynamics track forward speed, down speed and yaw rate; a lateral component of
a velocity setpoint is not flown (the swarmnav policy never commands one), and a position
target is flown to along the heading (a P law on the along-track and vertical errors, the
heading kept or turned to the target's yaw), so a lateral offset from it stays.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass

import numpy as np

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from companion.flight_modes import (  # noqa: E402
    ARDUCOPTER_MODE_BY_NAME,
    ARDUCOPTER_MODES,
    MAV_AUTOPILOT_ARDUPILOTMEGA,
    MAV_AUTOPILOT_PX4,
    PX4_MODE_BY_NAME,
    PX4_MODES,
    AutopilotKind,
    px4_custom_mode,
    px4_main_sub,
)
from companion.frames import ned_to_frd, ned_to_geodetic, wrap_angle_rad, yaw_to_quaternion  # noqa: E402
from sitl.realtime.udp_endpoint import MavlinkUdpEndpoint  # noqa: E402

HOME_LAT_DEG = 47.397742  # PX4 SITL's default home (Zurich)
HOME_LON_DEG = 8.545594
HOME_ALT_AMSL_M = 488.0

OFFBOARD_STREAM_MIN_S = 1.0  # PX4: setpoints for this long before OFFBOARD is accepted
SETPOINT_GAP_MAX_S = 0.5  # > 2 Hz: a longer gap restarts the stream
OFFBOARD_LOSS_S = 1.0  # PX4 COM_OF_LOSS_T
GUIDED_TIMEOUT_S = 3.0  # ArduCopter GUID_TIMEOUT default: velocity target timeout in GUIDED
POSITION_GAIN_1_S = 0.8  # position target: commanded speed per metre of error (a P law, both flavours)
POSITION_MAX_SPEED_M_S = 3.0  # position target: the fastest approach (horizontal)
POSITION_MAX_CLIMB_M_S = 1.5  # position target: the fastest climb or descent
TAKEOFF_SPEED_M_S = 1.5  # PX4 MPC_TKO_SPEED / ArduCopter WPNAV_SPEED_UP-like
LAND_SPEED_M_S = 0.7  # PX4 MPC_LAND_SPEED (ArduCopter LAND_SPEED is 0.5)
PX4_DEFAULT_TAKEOFF_ALT_M = 2.5  # MIS_TAKEOFF_ALT
MAX_SPEED_M_S = 12.0
MAX_YAW_RATE_RAD_S = 3.0

FAILURE_UNIT_SENSOR_GPS = 4
FAILURE_UNIT_SENSOR_DISTANCE_SENSOR = 7
FAILURE_UNIT_SYSTEM_MAVLINK_SIGNAL = 105
FAILURE_TYPES = {0: "ok", 1: "off", 3: "garbage", 4: "wrong"}

_PILOT_HOLD_MODES_PX4 = {"MANUAL", "ALTCTL", "POSCTL", "STABILIZED", "ACRO", "AUTO.LOITER", "AUTO.READY"}
_PILOT_HOLD_MODES_APM = {"STABILIZE", "ACRO", "ALT_HOLD", "LOITER", "POSHOLD", "BRAKE"}

_MSG = mavlink
_DEFAULT_STREAMS_HZ = {
    _MSG.MAVLINK_MSG_ID_HEARTBEAT: 1.0, _MSG.MAVLINK_MSG_ID_SYS_STATUS: 1.0, _MSG.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1.0,
    _MSG.MAVLINK_MSG_ID_ATTITUDE: 10.0, _MSG.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 10.0,
    _MSG.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 10.0, _MSG.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 5.0,
    _MSG.MAVLINK_MSG_ID_ODOMETRY: 10.0, _MSG.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
}
_POSITION_MESSAGES = {_MSG.MAVLINK_MSG_ID_ODOMETRY, _MSG.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
                      _MSG.MAVLINK_MSG_ID_GLOBAL_POSITION_INT}


@dataclass
class Body:
    """The physical state of one simulated vehicle, as the autopilot's estimator knows it."""

    pos_ned: np.ndarray
    vel_ned: np.ndarray
    yaw_rad: float
    yaw_rate_rad_s: float


class SimAutopilot:
    """The flight-mode logic and MAVLink interface of one simulated vehicle.

    Args:
        index: vehicle index in the world (system id ``index + 1``).
        kind: PX4 or ArduPilot behaviour.
        onboard: the link to the companion.
        gcs: the link to a ground station, or None.
        events: callable(event: str, **fields) that logs what happens.
        airborne: start armed and hovering instead of disarmed on the ground.
        odometry_child_frame: ODOMETRY velocity frame, ``local_ned`` (PX4 1.14+) or
            ``body_frd`` (PX4 up to 1.13).
        camera: the vehicle's depth sender (for camera failure injection), or None.
    """

    def __init__(self, index: int, kind: AutopilotKind, onboard: MavlinkUdpEndpoint, gcs: MavlinkUdpEndpoint | None,
                 events, airborne: bool = False, odometry_child_frame: str = "local_ned", camera=None) -> None:
        self.index, self.kind = index, kind
        self.sysid = index + 1
        self.onboard, self.gcs = onboard, gcs
        self.links = [link for link in (onboard, gcs) if link is not None]
        self.events = events
        self.odometry_child_frame = odometry_child_frame
        self.camera = camera
        self.boot_s = time.monotonic()
        self.armed = airborne
        self.airborne = airborne
        self.crashed = False
        if kind is AutopilotKind.PX4:
            self.mode = "AUTO.LOITER" if airborne else "POSCTL"
        else:
            self.mode = "LOITER" if airborne else "STABILIZE"
        self.setpoint_frd = np.zeros(3)  # (vel_fwd, vel_down, yaw_rate) from the last setpoint
        self.setpoint_yaw_rad: float | None = None
        self.setpoint_pos_ned: np.ndarray | None = None  # a position target (None: velocity setpoints)
        self.guided_timeout_s = GUIDED_TIMEOUT_S  # ArduPilot GUID_TIMEOUT (sitl.vehicle --guid-timeout)
        self.last_setpoint_s = -math.inf
        self.stream_start_s = -math.inf
        self.setpoints_received = 0
        self.guided_velocity_active = False
        self.guided_timed_out = False
        self.takeoff_alt_m = 0.0
        self.landed_since_s: float | None = None
        self.gps_failed = False
        self.dropped_frames_warned: set[int] = set()
        self.streams = {id(link): self._default_streams() for link in self.links}
        self.next_due = {id(link): {} for link in self.links}
        self._heartbeat_now = False
        self._guided_takeoff = False  # ArduCopter: NAV_TAKEOFF in GUIDED is climbing
        self._yaw = 0.0  # heading at the last update (for NED setpoints)
        self._body: Body | None = None
        self._last_target_kind = "velocity"
        self.mode_changes: list[tuple[float, str, str]] = []
        self.obstacle_distance_received = 0  # OBSTACLE_DISTANCE messages (the autopilot's proximity input)
        self._obstacle_window: tuple[float, int] | None = None  # (start, count) of the current 1 s log window

    # ================================================================== helpers
    def _default_streams(self) -> dict[int, float]:
        streams = dict(_DEFAULT_STREAMS_HZ)
        if self.kind is AutopilotKind.ARDUPILOT:
            streams.pop(_MSG.MAVLINK_MSG_ID_ODOMETRY)
        return {msg_id: 1.0 / hz for msg_id, hz in streams.items()}

    def time_boot_ms(self) -> int:
        return int((time.monotonic() - self.boot_s) * 1000) & 0xFFFFFFFF

    @property
    def custom_mode(self) -> int:
        if self.kind is AutopilotKind.PX4:
            return px4_custom_mode(*PX4_MODE_BY_NAME[self.mode])
        return ARDUCOPTER_MODE_BY_NAME[self.mode]

    @property
    def in_companion_mode(self) -> bool:
        return self.mode == ("OFFBOARD" if self.kind is AutopilotKind.PX4 else "GUIDED")

    def _landing_mode(self) -> bool:
        return self.mode in ("AUTO.LAND", "LAND")

    def set_mode(self, mode: str, why: str) -> None:
        if mode == self.mode:
            return
        old, self.mode = self.mode, mode
        self.mode_changes.append((time.time(), old, mode))
        self.guided_velocity_active = False
        self.guided_timed_out = False
        self.setpoint_pos_ned = None  # a new mode starts without a target (as GUIDED does on entry)
        self._heartbeat_now = True
        self.events("mode", vehicle=self.index, mode=mode, previous=old, why=why)

    def set_armed(self, armed: bool, why: str) -> None:
        if armed == self.armed:
            return
        self.armed = armed
        self._heartbeat_now = True
        self.events("armed" if armed else "disarmed", vehicle=self.index, why=why)

    def statustext(self, severity: int, text: str) -> None:
        for link in self.links:
            link.mav.statustext_send(severity, text.encode()[:50])

    # ================================================================== receiving
    def handle(self, link: MavlinkUdpEndpoint, msg, now_s: float) -> None:
        """Act on one message received on ``link`` and forward it if it is for someone else."""
        kind = msg.get_type()
        target_sys = getattr(msg, "target_system", None)
        target_comp = getattr(msg, "target_component", None)
        for_me = target_sys in (None, 0, self.sysid) and target_comp in (None, 0, mavlink.MAV_COMP_ID_AUTOPILOT1)
        exclusively_me = target_sys == self.sysid and target_comp in (0, mavlink.MAV_COMP_ID_AUTOPILOT1)
        if not exclusively_me:  # a router forwards what is not only for itself
            for other in self.links:
                if other is not link:
                    other.forward(msg.get_msgbuf())
        if not for_me:
            return
        if kind == "COMMAND_LONG":
            self._on_command(link, msg, now_s)
        elif kind == "SET_MODE":
            ok = self._request_mode_from_custom(msg.custom_mode, now_s, "SET_MODE")
            self.events("set_mode_msg", vehicle=self.index, custom_mode=msg.custom_mode, accepted=ok)
        elif kind == "SET_POSITION_TARGET_LOCAL_NED" and target_sys == self.sysid:
            self._on_setpoint(msg, now_s)
        elif kind == "OBSTACLE_DISTANCE":
            self._on_obstacle_distance(msg, now_s)

    def _on_obstacle_distance(self, msg, now_s: float) -> None:
        """Count OBSTACLE_DISTANCE and log, once a second, its rate and the latest message's bins.

        What a real autopilot's proximity driver would read; the simulated vehicle does not avoid.
        """
        self.obstacle_distance_received += 1
        if self._obstacle_window is None:  # the first message starts the window (intervals are counted)
            self._obstacle_window = (now_s, 0)
            return
        start, count = self._obstacle_window
        count += 1
        if now_s - start >= 1.0:
            self.events("obstacle_distance", vehicle=self.index, messages=count, rate_hz=round(count / (now_s - start), 2),
                        frame=msg.frame, angle_offset_deg=msg.angle_offset, increment_deg=msg.increment_f or msg.increment,
                        min_distance_cm=msg.min_distance, max_distance_cm=msg.max_distance, distances_cm=list(msg.distances))
            start, count = now_s, 0
        self._obstacle_window = (start, count)

    def _ack(self, link: MavlinkUdpEndpoint, msg, result: int) -> None:
        link.mav.command_ack_send(msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())

    def _on_command(self, link: MavlinkUdpEndpoint, msg, now_s: float) -> None:
        cmd = msg.command
        R = mavlink
        if cmd == R.MAV_CMD_COMPONENT_ARM_DISARM:
            self._ack(link, msg, self._arm_disarm(msg.param1 > 0.5, int(msg.param2) == 21196))
        elif cmd == R.MAV_CMD_DO_SET_MODE:
            if not int(msg.param1) & R.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                self._ack(link, msg, R.MAV_RESULT_UNSUPPORTED)
                return
            if self.kind is AutopilotKind.PX4:
                custom = px4_custom_mode(int(msg.param2), int(msg.param3))
            else:
                custom = int(msg.param2)
            ok = self._request_mode_from_custom(custom, now_s, f"DO_SET_MODE from {msg.get_srcSystem()}/{msg.get_srcComponent()}")
            self._ack(link, msg, R.MAV_RESULT_ACCEPTED if ok else R.MAV_RESULT_TEMPORARILY_REJECTED)
        elif cmd == R.MAV_CMD_NAV_TAKEOFF:
            self._ack(link, msg, self._takeoff(msg.param7))
        elif cmd == R.MAV_CMD_NAV_LAND:
            if self.crashed or not self.armed:
                self._ack(link, msg, R.MAV_RESULT_DENIED)
            else:
                self.set_mode("AUTO.LAND" if self.kind is AutopilotKind.PX4 else "LAND", "NAV_LAND")
                self._ack(link, msg, R.MAV_RESULT_ACCEPTED)
        elif cmd == R.MAV_CMD_SET_MESSAGE_INTERVAL:
            self._ack(link, msg, self._set_interval(link, int(msg.param1), msg.param2))
        elif cmd == R.MAV_CMD_REQUEST_MESSAGE:
            self._ack(link, msg, R.MAV_RESULT_ACCEPTED if self._send_message(link, int(msg.param1), force=True)
                      else R.MAV_RESULT_UNSUPPORTED)
        elif cmd == R.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self._ack(link, msg, R.MAV_RESULT_ACCEPTED)
            self._send_message(link, R.MAVLINK_MSG_ID_AUTOPILOT_VERSION, force=True)
        elif cmd == R.MAV_CMD_INJECT_FAILURE:
            self._ack(link, msg, self._inject_failure(int(msg.param1), int(msg.param2)))
        else:
            self._ack(link, msg, R.MAV_RESULT_UNSUPPORTED)

    def _arm_disarm(self, arm: bool, force: bool) -> int:
        R = mavlink
        if arm:
            if self.crashed or self._landing_mode():
                return R.MAV_RESULT_DENIED
            self.set_armed(True, "ARM command")
            return R.MAV_RESULT_ACCEPTED
        if self.airborne and not force:
            self.statustext(R.MAV_SEVERITY_CRITICAL, "Disarming denied: not landed")
            return R.MAV_RESULT_DENIED
        if self.airborne:
            self.crashed = True  # a forced disarm in the air ends the flight
            self.events("crash", vehicle=self.index, reason="forced disarm in flight")
        self.set_armed(False, "DISARM command")
        return R.MAV_RESULT_ACCEPTED

    def _request_mode_from_custom(self, custom_mode: int, now_s: float, why: str) -> bool:
        if self.kind is AutopilotKind.PX4:
            main, sub = px4_main_sub(custom_mode)
            name = PX4_MODES.get((main, sub)) or (PX4_MODES.get((main, 0)) if main != 4 else None)
        else:
            name = ARDUCOPTER_MODES.get(custom_mode)
        return self.request_mode(name, now_s, why) if name else False

    def request_mode(self, name: str, now_s: float, why: str) -> bool:
        """Switch to ``name`` if this autopilot would; False if it refuses."""
        if self.crashed:
            return False
        if self.kind is AutopilotKind.PX4:
            if name == "OFFBOARD":
                streaming = (now_s - self.last_setpoint_s < SETPOINT_GAP_MAX_S
                             and self.last_setpoint_s - self.stream_start_s >= OFFBOARD_STREAM_MIN_S)
                if not streaming:
                    self.statustext(mavlink.MAV_SEVERITY_CRITICAL, "Switching to Offboard is currently not available")
                    self.events("mode_refused", vehicle=self.index, mode=name, reason="no setpoint stream")
                    return False
                if self.gps_failed:
                    return False
            elif name == "AUTO.TAKEOFF":
                if not self.armed:
                    return False
                self.takeoff_alt_m = PX4_DEFAULT_TAKEOFF_ALT_M
            elif name not in _PILOT_HOLD_MODES_PX4 and name != "AUTO.LAND":
                self.events("mode_refused", vehicle=self.index, mode=name, reason="not simulated")
                return False
        else:
            if name == "GUIDED" and self.gps_failed:
                return False
            if name not in _PILOT_HOLD_MODES_APM and name not in ("GUIDED", "LAND"):
                self.events("mode_refused", vehicle=self.index, mode=name, reason="not simulated")
                return False
        self.set_mode(name, why)
        return True

    def _takeoff(self, param7: float) -> int:
        R = mavlink
        if self.crashed or not self.armed or self.airborne:
            return R.MAV_RESULT_DENIED
        if self.kind is AutopilotKind.PX4:
            alt = param7 - HOME_ALT_AMSL_M if math.isfinite(param7) else PX4_DEFAULT_TAKEOFF_ALT_M
            if not alt > 0.5:
                return R.MAV_RESULT_DENIED
            self.takeoff_alt_m = alt
            self.set_mode("AUTO.TAKEOFF", "NAV_TAKEOFF")
            return R.MAV_RESULT_ACCEPTED
        if self.mode != "GUIDED" or not (math.isfinite(param7) and param7 > 0.5):
            return R.MAV_RESULT_FAILED
        self.takeoff_alt_m = param7
        self._guided_takeoff = True
        self.events("takeoff", vehicle=self.index, alt_m=param7)
        return R.MAV_RESULT_ACCEPTED

    def _set_interval(self, link: MavlinkUdpEndpoint, msg_id: int, interval_us: float) -> int:
        R = mavlink
        streams = self.streams[id(link)]
        defaults = self._default_streams()
        if msg_id == R.MAVLINK_MSG_ID_ODOMETRY and self.kind is AutopilotKind.ARDUPILOT:
            return R.MAV_RESULT_UNSUPPORTED  # ArduPilot sends no ODOMETRY
        if msg_id not in _DEFAULT_STREAMS_HZ:
            return R.MAV_RESULT_UNSUPPORTED
        if interval_us < 0:
            streams.pop(msg_id, None)
        elif interval_us == 0:
            streams[msg_id] = defaults.get(msg_id, 1.0)
        else:
            streams[msg_id] = max(interval_us * 1e-6, 0.005)  # at most 200 Hz
        self.next_due[id(link)].pop(msg_id, None)
        self.events("message_interval", vehicle=self.index, link=link.name, msg_id=msg_id,
                    rate_hz=None if msg_id not in streams else round(1.0 / streams[msg_id], 2))
        return R.MAV_RESULT_ACCEPTED

    def _inject_failure(self, unit: int, failure_type: int) -> int:
        R = mavlink
        fault = FAILURE_TYPES.get(failure_type)
        if fault is None:
            return R.MAV_RESULT_UNSUPPORTED
        if unit == FAILURE_UNIT_SENSOR_GPS and fault in ("ok", "off"):
            self.gps_failed = fault == "off"
        elif unit == FAILURE_UNIT_SENSOR_DISTANCE_SENSOR and self.camera is not None:
            self.camera.fault[self.index] = fault
        elif unit == FAILURE_UNIT_SYSTEM_MAVLINK_SIGNAL and fault in ("ok", "off"):
            self.onboard.silenced = fault == "off"
        else:
            return R.MAV_RESULT_UNSUPPORTED
        self.events("failure_injected", vehicle=self.index, unit=unit, type=fault)
        return R.MAV_RESULT_ACCEPTED

    def _on_setpoint(self, msg, now_s: float) -> None:
        """A SET_POSITION_TARGET_LOCAL_NED: velocity (+ yaw or yaw rate) setpoints only."""
        frame = msg.coordinate_frame
        accepted = {1, 8} if self.kind is AutopilotKind.PX4 else {1, 7, 8, 9}
        if frame not in accepted:
            if frame not in self.dropped_frames_warned:
                self.dropped_frames_warned.add(frame)
                self.events("setpoint_dropped", vehicle=self.index, frame=frame, reason="coordinate frame not accepted")
            return
        mask = msg.type_mask
        position_target = not mask & 0b111 and mask & 0b111000 == 0b111000
        if position_target:
            if frame != 1 or not self._on_position_target(msg, now_s):
                if -2 not in self.dropped_frames_warned:
                    self.dropped_frames_warned.add(-2)
                    self.events("setpoint_dropped", vehicle=self.index, frame=frame,
                                reason="position targets are simulated in LOCAL_NED (1) with finite x, y, z only")
            return
        if mask & 0b111000:  # neither velocity nor a pure position target: not simulated
            if -1 not in self.dropped_frames_warned:
                self.dropped_frames_warned.add(-1)
                self.events("setpoint_dropped", vehicle=self.index, frame=frame,
                            reason="only velocity setpoints and position targets are simulated")
            return
        vel = np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64)
        if not np.all(np.isfinite(vel)):
            return
        if frame in (1, 7):  # NED velocity: project on the heading (the kinematic model flies forward)
            vel_fwd = float(ned_to_frd(vel, self._yaw)[0])
        else:
            vel_fwd = vel[0]
        yaw_rate = 0.0
        self.setpoint_yaw_rad = None
        if not mask & 0b100000000000 and math.isfinite(msg.yaw_rate):
            yaw_rate = msg.yaw_rate
        elif not mask & 0b10000000000 and math.isfinite(msg.yaw):
            self.setpoint_yaw_rad = msg.yaw
        self.setpoint_frd = np.array([np.clip(vel_fwd, -MAX_SPEED_M_S, MAX_SPEED_M_S),
                                      np.clip(vel[2], -MAX_SPEED_M_S, MAX_SPEED_M_S),
                                      np.clip(yaw_rate, -MAX_YAW_RATE_RAD_S, MAX_YAW_RATE_RAD_S)])
        self.setpoint_pos_ned = None
        self._setpoint_received(now_s)

    def _on_position_target(self, msg, now_s: float) -> bool:
        """A LOCAL_NED position target (yaw too unless masked); False if it cannot be flown."""
        pos = np.array([msg.x, msg.y, msg.z], dtype=np.float64)
        if not np.all(np.isfinite(pos)):
            return False
        self.setpoint_pos_ned = pos
        self.setpoint_yaw_rad = msg.yaw if not msg.type_mask & 0b10000000000 and math.isfinite(msg.yaw) else None
        self.setpoint_frd = np.zeros(3)
        if self._last_target_kind != "position":  # logged when the target kind changes, not every message
            self.events("position_target", vehicle=self.index, pos_ned=pos.round(3).tolist(), mode=self.mode)
        self._setpoint_received(now_s)
        return True

    def _setpoint_received(self, now_s: float) -> None:
        self._last_target_kind = "position" if self.setpoint_pos_ned is not None else "velocity"
        if now_s - self.last_setpoint_s > SETPOINT_GAP_MAX_S:
            self.stream_start_s = now_s
        self.last_setpoint_s = now_s
        self.setpoints_received += 1
        if self.in_companion_mode:
            self.guided_velocity_active = True
            if self.guided_timed_out:
                self.guided_timed_out = False
                self.events("guided_resumed", vehicle=self.index)

    def _position_command(self, body: Body) -> np.ndarray:
        """FRD (fwd, down, yaw rate) flying to and holding :attr:`setpoint_pos_ned` (a P law)."""
        error = self.setpoint_pos_ned - body.pos_ned
        along = float(ned_to_frd(error, body.yaw_rad)[0])
        fwd = float(np.clip(POSITION_GAIN_1_S * along, -POSITION_MAX_SPEED_M_S, POSITION_MAX_SPEED_M_S))
        down = float(np.clip(POSITION_GAIN_1_S * error[2], -POSITION_MAX_CLIMB_M_S, POSITION_MAX_CLIMB_M_S))
        yaw_rate = 0.0
        if self.setpoint_yaw_rad is not None:
            yaw_rate = float(np.clip(2.0 * float(wrap_angle_rad(self.setpoint_yaw_rad - body.yaw_rad)), -1.0, 1.0))
        return np.array([fwd, down, yaw_rate])

    # ================================================================== flying
    def velocity_command(self, now_s: float, body: Body) -> tuple[np.ndarray, bool]:
        """The FRD velocity command the vehicle tracks now, and whether it is flying."""
        self._yaw = body.yaw_rad
        if self.crashed or not self.armed:
            return np.zeros(3), False
        alt = -body.pos_ned[2]
        if self.mode == "AUTO.TAKEOFF" or self._guided_takeoff:
            return np.array([0.0, -min(TAKEOFF_SPEED_M_S, max(0.3, 1.5 * (self.takeoff_alt_m - alt))), 0.0]), True
        if self._landing_mode():
            return np.array([0.0, LAND_SPEED_M_S if self.kind is AutopilotKind.PX4 else 0.5, 0.0]), self.airborne
        if self.in_companion_mode:
            if self.kind is AutopilotKind.ARDUPILOT and (not self.guided_velocity_active or self.guided_timed_out):
                return np.zeros(3), self.airborne
            if self.setpoint_pos_ned is not None:
                return self._position_command(body), self.airborne or self.setpoint_pos_ned[2] < body.pos_ned[2] - 0.05
            cmd = self.setpoint_frd.copy()
            if self.setpoint_yaw_rad is not None:
                error = float(wrap_angle_rad(self.setpoint_yaw_rad - body.yaw_rad))
                cmd[2] = float(np.clip(2.0 * error, -1.0, 1.0))
            if not self.airborne and cmd[1] >= -0.05:
                return np.zeros(3), False  # on the ground, nothing pulls it up
            return cmd, True
        return np.zeros(3), self.airborne  # pilot modes and hold: sticks centred

    def update(self, now_s: float, body: Body) -> None:
        """Mode logic that depends on time and state: failsafes, takeoff and landing."""
        alt = -body.pos_ned[2]
        if self.kind is AutopilotKind.PX4 and self.mode == "OFFBOARD" and now_s - self.last_setpoint_s > OFFBOARD_LOSS_S:
            self.set_mode("AUTO.LOITER", "failsafe: offboard setpoints lost for 1 s")
            self.statustext(mavlink.MAV_SEVERITY_WARNING, "Failsafe: offboard signal lost, holding")
        if (self.kind is AutopilotKind.ARDUPILOT and self.mode == "GUIDED" and self.guided_velocity_active
                and self.setpoint_pos_ned is None  # GUID_TIMEOUT is for velocity targets: a position is held
                and not self.guided_timed_out and now_s - self.last_setpoint_s > self.guided_timeout_s):
            self.guided_timed_out = True
            self.events("guided_timeout", vehicle=self.index,
                        why=f"no setpoint for GUID_TIMEOUT {self.guided_timeout_s:g} s: stopping")
        if self.mode == "AUTO.TAKEOFF" and alt >= self.takeoff_alt_m - 0.1:
            self.set_mode("AUTO.LOITER", "takeoff complete")
        if self._guided_takeoff and (alt >= self.takeoff_alt_m - 0.1 or self.mode != "GUIDED"):
            self._guided_takeoff = False
            self.events("takeoff_complete", vehicle=self.index, alt_m=round(alt, 2))
        if self.landed_since_s is not None and self.armed:
            delay = 0.0 if self._landing_mode() else (2.0 if self.kind is AutopilotKind.PX4 else 10.0)
            if now_s - self.landed_since_s >= delay:
                self.set_armed(False, "landed")

    def touched_down(self, now_s: float) -> None:
        self.airborne = False
        self.landed_since_s = now_s
        self.events("landed", vehicle=self.index)

    def lifted_off(self) -> None:
        self.airborne = True
        self.landed_since_s = None
        self.events("lifted_off", vehicle=self.index)

    def crash(self, reason: str, outcome: str) -> None:
        """The vehicle is lost: disarmed for good. ``outcome`` is the evaluation's code for it
        (``collision_uav`` or ``collision_ground``, as :mod:`sitl.sim.env`), ``reason`` the words."""
        if not self.crashed:
            self.crashed = True
            self.set_armed(False, f"crash: {reason}")
            self.events("crash", vehicle=self.index, reason=reason, outcome=outcome)
            self.statustext(mavlink.MAV_SEVERITY_EMERGENCY, f"Crash: {reason}"[:50])

    # ================================================================== telemetry
    def send_telemetry(self, now_s: float, body: Body) -> None:
        """Send every stream that is due on every link (and a heartbeat on a mode change)."""
        for link in self.links:
            due = self.next_due[id(link)]
            for msg_id, interval in self.streams[id(link)].items():
                if msg_id == _MSG.MAVLINK_MSG_ID_HEARTBEAT and self._heartbeat_now:
                    due[msg_id] = now_s
                t = due.get(msg_id)
                if t is None:
                    due[msg_id] = now_s + (interval if msg_id != _MSG.MAVLINK_MSG_ID_HEARTBEAT else 0.0)
                    if msg_id != _MSG.MAVLINK_MSG_ID_HEARTBEAT:
                        continue
                    t = now_s
                if now_s >= t:
                    self._send_message(link, msg_id, body=body)
                    due[msg_id] = max(t + interval, now_s + interval * 0.5)
        self._heartbeat_now = False
        self._body = body

    def _send_message(self, link: MavlinkUdpEndpoint, msg_id: int, body: Body | None = None, force: bool = False) -> bool:
        body = body or self._body
        R = mavlink
        mav = link.mav
        if body is None:
            return False
        if msg_id in _POSITION_MESSAGES and self.gps_failed:
            return True  # no position estimate: the stream is silent
        t_ms = self.time_boot_ms()
        yaw = body.yaw_rad
        if msg_id == R.MAVLINK_MSG_ID_HEARTBEAT:
            base = R.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (R.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
            status = (R.MAV_STATE_EMERGENCY if self.crashed else R.MAV_STATE_ACTIVE if self.armed else R.MAV_STATE_STANDBY)
            autopilot = MAV_AUTOPILOT_PX4 if self.kind is AutopilotKind.PX4 else MAV_AUTOPILOT_ARDUPILOTMEGA
            mav.heartbeat_send(R.MAV_TYPE_QUADROTOR, autopilot, base, self.custom_mode, status)
        elif msg_id == R.MAVLINK_MSG_ID_ODOMETRY:
            if self.kind is not AutopilotKind.PX4:
                return False
            q = yaw_to_quaternion(yaw)
            if self.odometry_child_frame == "body_frd":  # PX4 up to 1.13: velocity in the body frame
                vel = ned_to_frd(body.vel_ned, yaw).tolist()
                child = R.MAV_FRAME_BODY_FRD
            else:
                vel, child = list(body.vel_ned), R.MAV_FRAME_LOCAL_NED
            cov = [math.nan] + [0.0] * 20
            mav.odometry_send(int((time.monotonic() - self.boot_s) * 1e6), R.MAV_FRAME_LOCAL_NED, child,
                              *body.pos_ned, q, *vel, 0.0, 0.0, body.yaw_rate_rad_s, cov, cov, 0,
                              R.MAV_ESTIMATOR_TYPE_AUTOPILOT, 100)
        elif msg_id == R.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            mav.local_position_ned_send(t_ms, *body.pos_ned, *body.vel_ned)
        elif msg_id == R.MAVLINK_MSG_ID_ATTITUDE:
            mav.attitude_send(t_ms, 0.0, 0.0, yaw, 0.0, 0.0, body.yaw_rate_rad_s)
        elif msg_id == R.MAVLINK_MSG_ID_ATTITUDE_QUATERNION:
            mav.attitude_quaternion_send(t_ms, *yaw_to_quaternion(yaw), 0.0, 0.0, body.yaw_rate_rad_s)
        elif msg_id == R.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            lat, lon, _ = ned_to_geodetic(body.pos_ned, HOME_LAT_DEG, HOME_LON_DEG, HOME_ALT_AMSL_M)
            hdg = int(round(math.degrees(yaw) % 360 * 100)) % 36000
            mav.global_position_int_send(t_ms, int(lat * 1e7), int(lon * 1e7),
                                         int((HOME_ALT_AMSL_M - body.pos_ned[2]) * 1000), int(-body.pos_ned[2] * 1000),
                                         *(int(v * 100) for v in body.vel_ned), hdg)
        elif msg_id == R.MAVLINK_MSG_ID_SYS_STATUS:
            sensors = 0b1111111  # gyro, accel, mag, baro, ..., gps
            health = sensors & ~(R.MAV_SYS_STATUS_SENSOR_GPS if self.gps_failed else 0)
            mav.sys_status_send(sensors, sensors, health, 200, 16200, 500, 90, 0, 0, 0, 0, 0, 0)
        elif msg_id == R.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            landed = (R.MAV_LANDED_STATE_IN_AIR if self.airborne else R.MAV_LANDED_STATE_ON_GROUND)
            if self.mode == "AUTO.TAKEOFF" or self._guided_takeoff:
                landed = R.MAV_LANDED_STATE_TAKEOFF
            elif self._landing_mode() and self.airborne:
                landed = R.MAV_LANDED_STATE_LANDING
            mav.extended_sys_state_send(R.MAV_VTOL_STATE_UNDEFINED, landed)
        elif msg_id == R.MAVLINK_MSG_ID_HOME_POSITION:
            mav.home_position_send(int(HOME_LAT_DEG * 1e7), int(HOME_LON_DEG * 1e7), int(HOME_ALT_AMSL_M * 1000),
                                   0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0)
        elif msg_id == R.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            caps = (R.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | R.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                    | R.MAV_PROTOCOL_CAPABILITY_COMMAND_INT)
            version = (1 << 24) | (14 << 16) if self.kind is AutopilotKind.PX4 else (4 << 24) | (5 << 16)
            mav.autopilot_version_send(caps, version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, self.sysid, [0] * 18)
        else:
            return False
        return True

