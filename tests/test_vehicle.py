"""``python -m sitl.vehicle`` over real sockets: it must behave like PX4 SITL and ArduCopter SITL
towards a companion (this test plays the companion with pymavlink)."""

from __future__ import annotations

import json
import math
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from companion.depth_wire import decode_frame
from companion.flight_modes import px4_custom_mode
from tests.companion_helpers import GroundStation, Processes, Rig, env

pytestmark = pytest.mark.timeout(90)

MAV_RESULT_ACCEPTED, MAV_RESULT_TEMPORARILY_REJECTED, MAV_RESULT_UNSUPPORTED = 0, 1, 3
BODY_NED, BODY_FRD, BODY_OFFSET_NED = 8, 12, 9
VELOCITY_YAW_RATE = 1479


class Companionish(GroundStation):
    """pymavlink on the vehicle's onboard port, as component 191."""

    def __init__(self, port: int) -> None:
        from pymavlink import mavutil

        mavutil.set_dialect("common")
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1, source_component=191,
                                               dialect="common")
        self.mav = self.conn.mav
        self.latest: dict = {}
        self.last_setpoint_sent = 0.0

    def pump(self, seconds: float, setpoint: tuple | list | None = None, rate_hz: float = 10.0) -> None:
        """Read messages for ``seconds``, sending ``(frame, vx, vz)`` setpoints (or a list of them, in turn)."""
        end = time.monotonic() + seconds
        next_send = time.monotonic()
        cycle = setpoint if isinstance(setpoint, list) else [setpoint]
        sent = 0
        while time.monotonic() < end:
            if setpoint is not None and time.monotonic() >= next_send:
                frame, vx, vz = cycle[sent % len(cycle)]
                sent += 1
                self.mav.set_position_target_local_ned_send(0, 1, 1, frame, VELOCITY_YAW_RATE, 0, 0, 0, vx, 0, vz,
                                                            0, 0, 0, 0, 0)
                self.last_setpoint_sent = time.monotonic()
                next_send += 1.0 / rate_hz
            msg = self.conn.recv_match(blocking=True, timeout=0.02)
            while msg is not None:
                self.latest[msg.get_type()] = (time.monotonic(), msg)
                msg = self.conn.recv_match(blocking=False)

    def command_while_streaming(self, command: int, *params: float, setpoint=None) -> int:
        padded = list(params) + [0.0] * (7 - len(params))
        self.mav.command_long_send(1, 1, command, 0, *padded)
        deadline = time.monotonic() + 3.0
        self.latest.pop("COMMAND_ACK", None)
        while time.monotonic() < deadline:
            self.pump(0.05, setpoint)
            ack = self.latest.get("COMMAND_ACK")
            if ack and ack[1].command == command:
                return ack[1].result
        raise AssertionError(f"no COMMAND_ACK for {command}")

    def heartbeat(self):
        return self.latest["HEARTBEAT"][1]


def test_px4_vehicle_offboard_rules_failsafe_odometry_and_depth(tmp_path):
    with Processes(tmp_path) as procs:
        rig = Rig(procs, tmp_path)
        depth_rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        depth_rx.bind(("127.0.0.1", rig.depth_port))
        depth_rx.settimeout(10.0)
        # the paper camera (32x32, 90 deg, 20 m): the pixel arithmetic below is for it
        rig.start_vehicle("--cylinder", "6,0,0.5", "--camera-hz", "30", "--camera", "paper", gcs=False)
        ap = Companionish(rig.mav_port)
        try:
            hb = ap.wait_heartbeat()
            assert hb.autopilot == 12 and hb.type == 2 and hb.custom_mode == px4_custom_mode(3)  # POSCTL
            assert not hb.base_mode & 128

            # Depth frames: 30 Hz by the sender's capture stamps, the pole 6 m ahead at 5.5 m planar depth.
            frames = [decode_frame(depth_rx.recv(65535)) for _ in range(20)]
            intervals_ms = np.diff([f.stamp_us for f in frames]) / 1000.0
            assert np.median(intervals_ms) == pytest.approx(1000.0 / 30.0, abs=3.0)
            assert frames[-1].depth_m.shape == (32, 32) and frames[-1].depth_m[10, 15:17].min() == pytest.approx(5.5, abs=0.05)
            assert frames[-1].depth_m[10, 0] == 20.0  # nothing there (row 10 is above the horizon)

            assert ap.command_while_streaming(511, 331, 20000) == MAV_RESULT_ACCEPTED  # ODOMETRY at 50 Hz
            # OFFBOARD needs >= 1 s of setpoints; frames 12 and 9 do not count (PX4 drops them).
            assert ap.command_while_streaming(176, 1, 6, 0) == MAV_RESULT_TEMPORARILY_REJECTED
            dropped = [(BODY_FRD, 0.0, 0.0), (BODY_OFFSET_NED, 0.0, 0.0)]  # each alone still streams at 5 Hz
            ap.pump(1.3, dropped)
            assert ap.command_while_streaming(176, 1, 6, 0, setpoint=dropped) == MAV_RESULT_TEMPORARILY_REJECTED
            hold = (BODY_NED, 0.0, 0.0)
            ap.pump(1.2, hold)
            assert ap.command_while_streaming(400, 1, setpoint=hold) == MAV_RESULT_ACCEPTED
            assert ap.command_while_streaming(176, 1, 6, 0, setpoint=hold) == MAV_RESULT_ACCEPTED
            ap.pump(0.3, hold)
            assert ap.heartbeat().custom_mode == px4_custom_mode(6) and ap.heartbeat().base_mode & 128

            ap.pump(2.0, (BODY_NED, 1.0, -0.5))  # climb and go forward in OFFBOARD
            t_odom, odom = ap.latest["ODOMETRY"]
            assert odom.child_frame_id == 1 and odom.frame_id == 1  # PX4 1.14+: velocity in LOCAL_NED
            assert odom.z < -0.4 and odom.vx > 0.5 and time.monotonic() - t_odom < 0.1

            # Offboard loss: no setpoint for 1 s -> AUTO.LOITER (Hold).
            # Timed from the last send, which can be up to one 10 Hz period before pump() returns.
            last_setpoint = ap.last_setpoint_sent
            while ap.heartbeat().custom_mode == px4_custom_mode(6):
                ap.pump(0.05)
                assert time.monotonic() - last_setpoint < 2.0, "offboard-loss failsafe did not trigger"
            assert 0.9 <= time.monotonic() - last_setpoint <= 1.8  # COM_OF_LOSS_T = 1 s (+ this reader's delays)
            assert ap.heartbeat().custom_mode == px4_custom_mode(4, 3)
        finally:
            ap.close()
            depth_rx.close()


def test_ardupilot_vehicle_guided_timeout_and_no_odometry(tmp_path):
    with Processes(tmp_path) as procs:
        rig = Rig(procs, tmp_path)
        rig.start_vehicle("--autopilot", "ardupilot", gcs=False)
        ap = Companionish(rig.mav_port)
        try:
            hb = ap.wait_heartbeat()
            assert hb.autopilot == 3 and hb.custom_mode == 0  # STABILIZE
            assert ap.command_while_streaming(511, 331, 20000) == MAV_RESULT_UNSUPPORTED  # no ODOMETRY
            assert ap.command_while_streaming(511, 32, 20000) == MAV_RESULT_ACCEPTED
            assert ap.command_while_streaming(176, 1, 4) == MAV_RESULT_ACCEPTED  # GUIDED without a stream
            assert ap.command_while_streaming(400, 1) == MAV_RESULT_ACCEPTED
            assert ap.command_while_streaming(22, 0, 0, 0, math.nan, 0, 0, 2.0) == MAV_RESULT_ACCEPTED
            deadline = time.monotonic() + 5.0
            while ap.latest["LOCAL_POSITION_NED"][1].z > -1.85:
                ap.pump(0.1)
                assert time.monotonic() < deadline, "guided takeoff did not climb"
            assert "ODOMETRY" not in ap.latest

            ap.pump(1.0, (BODY_FRD, 1.0, 0.0))  # ArduPilot drops frame 12
            assert abs(ap.latest["LOCAL_POSITION_NED"][1].vx) < 0.05
            ap.pump(1.5, (BODY_NED, 1.0, 0.0))
            assert ap.latest["LOCAL_POSITION_NED"][1].vx > 0.8
            ap.pump(2.3)  # setpoints stopped 2.3 s ago: still following the last one
            assert ap.latest["LOCAL_POSITION_NED"][1].vx > 0.8
            ap.pump(1.5)  # > 3 s: GUIDED stops the vehicle but stays GUIDED
            assert abs(ap.latest["LOCAL_POSITION_NED"][1].vx) < 0.1 and ap.heartbeat().custom_mode == 4
        finally:
            ap.close()


def test_vehicle_rejects_bad_options():
    out = subprocess.run([sys.executable, "-m", "sitl.vehicle", "--airborne"], capture_output=True, text=True,
                         env=env(), timeout=60)
    assert out.returncode == 2 and "--airborne needs a start altitude" in out.stderr


def test_vehicle_response_draws_each_vehicles_response_once_and_says_so(tmp_path):
    """``--response``: the vehicle flies a drawn response (here a command delay and a slower lag), logged before
    ``ready``; jsbsim and a bad spec are refused in one line."""
    from tests.companion_helpers import free_udp_ports

    log = tmp_path / "vehicle.jsonl"
    mav, depth = free_udp_ports(2)
    out = subprocess.run([sys.executable, "-m", "sitl.vehicle", "--response", "command_delay_s=0.1:0.2,tau_horizontal_s=0.4",
                          "--duration", "1", "--gcs-port", "0", "--base-port", str(mav), "--depth-port", str(depth),
                          "--log", str(log)], capture_output=True, text=True, env=env(), timeout=60)
    assert out.returncode == 0, out.stderr
    events = [json.loads(line) for line in log.read_text().splitlines()]
    drawn = next(e for e in events if e["event"] == "response")
    assert drawn["spec"] == "tau_horizontal_s=0.4,command_delay_s=0.1:0.2"
    [vehicle] = drawn["vehicles"]
    assert vehicle["tau_horizontal_s"] == 0.4 and 0.1 <= vehicle["command_delay_s"] <= 0.2
    assert vehicle["tau_vertical_s"] == 0.25  # what the spec does not name stays nominal
    assert next(e for e in events if e["event"] == "ready")["response"] == drawn["spec"]
    for argv, why in [(["--response", "command_delay_s=0.1", "--dynamics", "jsbsim"], "kinematic backend"),
                      (["--response", "command_delay_s=3"], "command_delay_s must be"),
                      (["--response-seed", "2"], "give --response too"),
                      (["--response", "command_delay_s=0.1", "--response-seed", "-1"], "must be >= 0")]:
        bad = subprocess.run([sys.executable, "-m", "sitl.vehicle", *argv], capture_output=True, text=True, env=env(),
                             timeout=60)
        assert bad.returncode == 2 and why in bad.stderr and "Traceback" not in bad.stderr
        assert bad.stderr.strip().count("\n") == 0
