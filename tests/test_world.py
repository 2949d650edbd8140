"""``python -m sitl.world``: depth cameras for autopilots it does not simulate, over real sockets.

``python -m sitl.vehicle`` processes stand in for PX4 SITL instances (no autopilot binary is
installable here): their ground-station links all reach one UDP port like PX4's 14550, or
the world takes their onboard links with ``--connect``. Their own depth frames go to ports
nobody reads, so every frame a test (or a companion) receives was rendered by the world from
MAVLink telemetry alone. A small in-test fake plays PX4 instances whose local frames start at
their own spawn points (as in Gazebo), which the stand-ins cannot.
"""

from __future__ import annotations

import math
import os
import signal
import socket
import threading
import time

import numpy as np
import pytest

from companion.depth_wire import WireFrame, decode_frame
from companion.recording import read_recording
from companion.spec import CameraSpec
from tests.companion_helpers import Processes, free_udp_blocks, make_policy, read_jsonl

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

pytestmark = pytest.mark.timeout(90)

BODY_RADIUS_M = 0.3  # the camera sees a UAV's front 0.3 m before its centre
CENTRE = (slice(15, 17), slice(15, 17))  # the 2x2 pixels around the optical axis of a 32x32 image
GPS_OFF, GPS_OK = 1, 0


# --------------------------------------------------------------------------- ports, frames, logs


class DepthReceiver:
    """Plays the companions' depth sockets: one UDP socket per vehicle on consecutive ports."""

    def __init__(self, first_port: int, count: int) -> None:
        self.socks = []
        for i in range(count):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", first_port + i))
            s.setblocking(False)
            self.socks.append(s)

    def collect(self, seconds: float) -> list[list[WireFrame]]:
        """Every frame that arrives on each port within ``seconds``."""
        frames: list[list[WireFrame]] = [[] for _ in self.socks]
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            time.sleep(0.01)
            for i, s in enumerate(self.socks):
                while True:
                    try:
                        frames[i].append(decode_frame(s.recv(65535)))
                    except BlockingIOError:
                        break
        return frames

    def wait_all(self, timeout_s: float, what: str, procs: Processes) -> None:
        """Wait until every port has received a frame."""
        seen = [False] * len(self.socks)
        deadline = time.monotonic() + timeout_s
        while not all(seen):
            assert time.monotonic() < deadline, f"no {what} frames on ports {[i for i, s in enumerate(seen) if not s]}; " \
                                                f"world stderr:\n{procs.stderr('world')[-2000:]}"
            for i, frames in enumerate(self.collect(0.1)):
                seen[i] |= bool(frames)

    def close(self) -> None:
        for s in self.socks:
            s.close()


def start_standins(procs: Processes, tmp_path, n: int, base_port: int, sink_port: int, gcs_port: int, *extra: str):
    """``n`` simulated PX4 vehicles; their own depth frames (the paper camera, as :func:`start_world`'s)
    go to ``sink_port`` + i, where nobody listens."""
    camera = () if "--camera" in extra else ("--camera", "paper")
    return procs.start("vehicle", ["-m", "sitl.vehicle", "--n", str(n), "--base-port", str(base_port),
                                   "--depth-port", str(sink_port), "--gcs-port", str(gcs_port),
                                   "--log", str(tmp_path / "vehicle.jsonl"), "--duration", "120", *camera, *extra])


def start_world(procs: Processes, tmp_path, *args: str):
    """``sitl.world`` with the paper camera (32x32, 90 deg, 20 m) unless ``args`` name one: the depths and
    pixels these tests check are worked out for it."""
    camera = () if "--camera" in args else ("--camera", "paper")
    return procs.start("world", ["-m", "sitl.world", "--log", str(tmp_path / "world.jsonl"), "--duration", "120",
                                 *camera, *args])


def events(path, name: str) -> list[dict]:
    return [r for r in read_jsonl(path) if r.get("event") == name]


def wait_event(path, predicate, timeout_s: float, what: str) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for record in read_jsonl(path):
            if predicate(record):
                return record
        time.sleep(0.1)
    raise AssertionError(f"the world never logged {what}; log tail: {read_jsonl(path)[-5:]}")


def stop_world(procs: Processes, world, tmp_path, sig: signal.Signals = signal.SIGTERM) -> None:
    """SIGTERM or SIGINT (Ctrl-C): the world must close its sockets and exit 0."""
    os.killpg(world.pid, sig)
    assert world.wait(timeout=10) == 0, procs.stderr("world")[-2000:]
    assert events(tmp_path / "world.jsonl", "stopped")[-1]["reason"] == sig.name


# Two hovering vehicles at 5 m, vehicle 1 6 m east of vehicle 0, both facing east: vehicle 0
# looks straight at vehicle 1, vehicle 1 at open sky (and the ground below the horizon).
FACING_EAST_6M = ("--airborne", "--start", "0,0,-5", "--spacing", "6", "--yaw-deg", "90")


# --------------------------------------------------------------------------- tests


def test_px4_gcs_port_world_renders_each_vehicle_seeing_the_other(tmp_path):
    gcs, base, sink, depth = free_udp_blocks(1, 2, 2, 2)
    with Processes(tmp_path) as procs:
        rx = DepthReceiver(depth, 2)
        own = DepthReceiver(sink, 2)  # here only: the stand-ins' own cameras, to compare with
        try:
            start_standins(procs, tmp_path, 2, base, sink, gcs, *FACING_EAST_6M)
            world = start_world(procs, tmp_path, "--px4", "2", "--gcs-port", str(gcs), "--depth-port", str(depth))
            rx.wait_all(30, "depth", procs)
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # what real PX4 sends at start
                for _ in range(3):
                    s.sendto(unknown_message(411, sysid=2), ("127.0.0.1", gcs))
            frames = rx.collect(2.0)
            own_frames = own.collect(0.1)
            stop_world(procs, world, tmp_path)
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                s.bind(("0.0.0.0", gcs))  # the world let its port go
        finally:
            rx.close()
            own.close()

    for i in (0, 1):
        stamps_ms = np.array([f.stamp_us for f in frames[i]]) / 1000.0
        assert 45 <= len(frames[i]) <= 66, f"vehicle {i}: {len(frames[i])} frames in 2 s at 30 Hz"
        assert np.median(np.diff(stamps_ms)) == pytest.approx(1000.0 / 30.0, abs=3.0)
        f = frames[i][-1]
        assert f.depth_m.shape == (32, 32) and f.hfov_deg == 90.0 and f.max_range_m == 20.0 and f.vehicle == i
    seen_by_0, seen_by_1 = frames[0][-1].depth_m, frames[1][-1].depth_m
    # Vehicle 1's body, 6 m ahead of vehicle 0, in the middle of vehicle 0's image; nothing else above the horizon.
    assert seen_by_0[CENTRE].min() == pytest.approx(6.0 - BODY_RADIUS_M, abs=0.1)
    assert seen_by_0[15, :12].min() == 20.0 and seen_by_0[15, 20:].min() == 20.0 and seen_by_0[10, 15] == 20.0
    assert seen_by_1[:16].min() == 20.0  # vehicle 1 looks away from vehicle 0
    for i in (0, 1):  # hovering still: the very image sitl.vehicle renders itself
        np.testing.assert_allclose(frames[i][-1].depth_m, own_frames[i][-1].depth_m, atol=1e-4)

    log = tmp_path / "world.jsonl"
    assert sorted((e["vehicle"], e["sysid"], e["autopilot"]) for e in events(log, "connected")) == [(0, 1, "px4"), (1, 2, "px4")]
    # The stand-ins share one local frame and one home: the origins say there is nothing to add.
    assert [e["origin_offset_ned"] for e in events(log, "tracking")] == [[0.0, 0.0, 0.0]] * 2
    status = [e for e in events(log, "status") if e["state"] == "tracking"]
    assert status and all(e["pose_age_ms"] < 100 for e in status)
    # A message newer than pymavlink's dialect (PX4's CURRENT_EVENT_SEQUENCE) is logged once with
    # its real system id, not as an unknown system 0 (issue 18, item 9).
    assert [(e["msg_id"], e["sysid"]) for e in events(log, "unknown_message")] == [(411, 2)]
    assert not events(log, "ignored_system")
    asked = {(r["vehicle"], r["msg_id"], r["rate_hz"]) for r in events(tmp_path / "vehicle.jsonl", "message_interval")
             if r["link"] == "gcs"}
    assert asked == {(0, 32, 50.0), (0, 30, 50.0), (1, 32, 50.0), (1, 30, 50.0)}  # LOCAL_POSITION_NED, ATTITUDE


def test_one_connection_per_vehicle_with_explicit_spawn_offsets(tmp_path):
    base, sink, depth = free_udp_blocks(2, 2, 2)
    with Processes(tmp_path) as procs:
        rx = DepthReceiver(depth, 2)
        try:
            start_standins(procs, tmp_path, 2, base, sink, 0, *FACING_EAST_6M)  # no ground-station link
            # The world is each vehicle's onboard peer; vehicle 1's frame is declared 2 m west of vehicle 0's.
            world = start_world(procs, tmp_path, "--connect", f"udpin:127.0.0.1:{base}",
                                "--connect", f"udpin:127.0.0.1:{base + 1}", "--spawn-offsets", "0,0,0;0,-2,0",
                                "--depth-port", str(depth), "--trace", str(tmp_path / "trace.jsonl"))
            rx.wait_all(30, "depth", procs)
            frames = rx.collect(1.0)
            stop_world(procs, world, tmp_path, signal.SIGINT)
        finally:
            rx.close()
    assert frames[0] and frames[1]
    assert frames[0][-1].depth_m[CENTRE].min() == pytest.approx(6.0 - 2.0 - BODY_RADIUS_M, abs=0.1)
    assert frames[1][-1].depth_m[:16].min() == 20.0
    log = tmp_path / "world.jsonl"
    tracking = events(log, "tracking")
    assert [e["origin_offset_ned"] for e in tracking] == [[0.0, 0.0, 0.0], [0.0, -2.0, 0.0]]
    # The offsets used are --spawn-offsets', whatever origin the autopilots send (issue 18, item 5).
    assert [e["origin_source"] for e in tracking] == ["--spawn-offsets"] * 2
    # --trace: the world positions as drawn (vehicle 1 at 6 m east in its own frame, 2 m west of that), mode, armed.
    poses = [r for r in read_jsonl(tmp_path / "trace.jsonl") if r.get("event") == "pose" and None not in r["pos_ned"]]
    assert len(poses) >= 8
    last = poses[-1]
    np.testing.assert_allclose(np.array(last["pos_ned"]) - np.array(last["pos_ned"])[0], [[0, 0, 0], [0, 4, 0]], atol=0.05)
    assert last["armed"] == [True, True] and all(isinstance(m, str) for m in last["mode"])
    asked = {(r["vehicle"], r["msg_id"]) for r in events(tmp_path / "vehicle.jsonl", "message_interval")
             if r["link"] == "onboard"}
    assert asked == {(0, 32), (0, 30), (1, 32), (1, 30)}


def unknown_message(msg_id: int, sysid: int, compid: int = 1) -> bytes:
    """A MAVLink 2 frame of a message id pymavlink's common dialect lacks (an empty payload, any CRC)."""
    return bytes([0xFD, 0, 0, 0, 0, sysid, compid, msg_id & 0xFF, (msg_id >> 8) & 0xFF, msg_id >> 16, 0, 0])


class FakePx4Instances:
    """PX4 SITL instances whose local frames start at their own spawn points, as in Gazebo.

    Instance ``i`` (system id ``i + 1``) sends from its own port to the world's GCS port:
    heartbeats, LOCAL_POSITION_NED and ATTITUDE at 50 Hz, and GPS_GLOBAL_ORIGIN only when
    asked with REQUEST_MESSAGE. It records what the world sends it.
    """

    def __init__(self, gcs_port: int, origins: list[tuple[float, float, float]], pos_ned, yaw_rad) -> None:
        self.gcs_port, self.origins, self.pos_ned, self.yaw_rad = gcs_port, origins, pos_ned, yaw_rad
        self.received: list[list] = [[] for _ in origins]
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        socks, mavs, parsers = [], [], []
        for i in range(len(self.origins)):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", 0))
            s.setblocking(False)
            socks.append(s)
            mavs.append(mavlink.MAVLink(_Sender(s, self.gcs_port), srcSystem=i + 1, srcComponent=1))
            parsers.append(mavlink.MAVLink(None))
        start = time.monotonic()
        k = 0
        while not self.stop.is_set():
            t_ms = int((time.monotonic() - start) * 1000)
            for i, mav in enumerate(mavs):
                if k % 50 == 0:
                    mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, 12, 0, 0, mavlink.MAV_STATE_STANDBY)
                mav.local_position_ned_send(t_ms, *self.pos_ned[i], 0.0, 0.0, 0.0)
                mav.attitude_send(t_ms, 0.0, 0.0, self.yaw_rad[i], 0.0, 0.0, 0.0)
                while True:
                    try:
                        data = socks[i].recv(65535)
                    except BlockingIOError:
                        break
                    for msg in parsers[i].parse_buffer(data) or []:
                        self.received[i].append(msg)
                        if msg.get_type() == "COMMAND_LONG" and msg.command == 512 and int(msg.param1) == 49:
                            lat, lon, alt = self.origins[i]
                            mav.gps_global_origin_send(int(round(lat * 1e7)), int(round(lon * 1e7)), int(alt * 1000))
            k += 1
            time.sleep(0.02)
        for s in socks:
            s.close()

    def __enter__(self) -> FakePx4Instances:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.thread.join(timeout=5)


class _Sender:
    def __init__(self, sock: socket.socket, port: int) -> None:
        self.sock, self.port = sock, port

    def write(self, buf: bytes) -> None:
        try:
            self.sock.sendto(buf, ("127.0.0.1", self.port))
        except OSError:
            pass


def test_default_layout_places_vehicles_by_their_global_origins(tmp_path):
    """Both report local (0, 0, -5) facing north; instance 1's origin lies 4 m north of instance 0's."""
    from sitl.realtime.depth_bridge import shift_global

    gcs, depth = free_udp_blocks(1, 2)
    origin0 = (47.397742, 8.545594, 488.0)
    origin1 = shift_global(origin0, 4.0, 0.0)
    with Processes(tmp_path) as procs, FakePx4Instances(gcs, [origin0, origin1], [(0.0, 0.0, -5.0)] * 2, [0.0, 0.0]) as fake:
        rx = DepthReceiver(depth, 2)
        try:
            world = start_world(procs, tmp_path, "--px4", "2", "--gcs-port", str(gcs), "--depth-port", str(depth))
            rx.wait_all(30, "depth", procs)
            time.sleep(2.2)  # two heartbeats' worth
            frames = rx.collect(0.5)
            stop_world(procs, world, tmp_path)
        finally:
            rx.close()
    assert frames[0][-1].depth_m[CENTRE].min() == pytest.approx(4.0 - BODY_RADIUS_M, abs=0.1)
    assert frames[1][-1].depth_m[:16].min() == 20.0
    tracking = events(tmp_path / "world.jsonl", "tracking")
    assert [t["origin_source"] for t in tracking] == ["GPS_GLOBAL_ORIGIN"] * 2
    assert np.allclose([t["origin_offset_ned"] for t in sorted(tracking, key=lambda t: t["vehicle"])],
                       [[0, 0, 0], [4.0, 0, 0]], atol=0.02)
    for got in fake.received:  # each instance: GCS heartbeats at 1 Hz and the stream requests, addressed to it
        beats = [m for m in got if m.get_type() == "HEARTBEAT"]
        assert len(beats) >= 2 and all(m.type == mavlink.MAV_TYPE_GCS for m in beats)
        intervals = {(int(m.param1), m.param2) for m in got if m.get_type() == "COMMAND_LONG" and m.command == 511}
        assert intervals == {(32, 20000.0), (30, 20000.0)}
    assert {m.target_system for m in fake.received[1] if m.get_type() == "COMMAND_LONG"} == {2}


def test_a_companion_flies_to_its_goal_on_the_worlds_frames(tmp_path):
    gcs, base, sink, depth = free_udp_blocks(1, 1, 1, 1)
    record = tmp_path / "flight.snrec"
    with Processes(tmp_path) as procs:
        # Hovering at 10 m; the stand-in's own camera goes nowhere. The policy is the tests' contract-following
        # goal seeker: this test is about whose frames the companion flies on, not about the learned policy
        # (which, trained among other UAVs, climbs and stalls when alone with a tall pole in view).
        start_standins(procs, tmp_path, 1, base, sink, gcs, "--airborne", "--start", "0,0,-10")
        # A pole only the world knows about, 8 m left of the path: it must show in what the companion sees.
        start_world(procs, tmp_path, "--px4", "1", "--gcs-port", str(gcs), "--depth-port", str(depth),
                    "--cylinder", "10,-8,0.5")
        companion = procs.start("companion", [
            "-m", "companion.cli", "--connect", f"udpin:127.0.0.1:{base}",
            "--model", str(make_policy(tmp_path / "p.pt", camera=CameraSpec())),
            "--camera", f"sitl:{depth}", "--goal", "12,0,-10", "--arm", "--takeoff", "10", "--exit-on-arrival",
            "--timeout", "60", "--heartbeat-timeout", "20", "--record", str(record), "--log", str(tmp_path / "companion.jsonl")])
        try:
            code = companion.wait(timeout=80)
        except Exception:
            raise AssertionError(f"companion did not finish; stderr:\n{procs.stderr('companion')[-3000:]}") from None
        status = wait_event(tmp_path / "world.jsonl", lambda r: r.get("event") == "status" and r["frames_sent"] > 0,
                            5, "frames sent")
    assert code == 0, procs.stderr("companion")[-3000:]
    log = read_jsonl(tmp_path / "companion.jsonl")
    (arrived,) = [r for r in log if r.get("kind") == "event" and r.get("event") == "arrived"]
    assert arrived["dist_m"] <= 0.5
    steps = [r for r in log if r.get("kind") == "step" and r.get("phase") == "flying_to_goal"]
    # Flown on fresh frames: a loaded CI machine may delay a few, never most of them.
    assert len(steps) > 30 and sum(bool(s["hold"]) for s in steps) <= 0.1 * len(steps)
    assert np.median([s["depth_age_ms"] for s in steps]) < 100
    assert status["depth_port"] == depth and status["sysid"] == 1
    _header, records = read_recording(record)
    upper_left = records["depth_m"][:, :15, :16].min(axis=(1, 2))  # above the horizon, left half
    assert upper_left[0] < 14.0  # the pole (12.8 m away at the start; nothing else above the horizon: 20 m)
    assert records["depth_m"][0][:15, 16:].min() == 20.0  # and nothing on the right


def test_stale_telemetry_stops_that_vehicles_frames_and_hides_its_body(tmp_path):
    from pymavlink import mavutil

    gcs, base, sink, depth = free_udp_blocks(1, 2, 2, 2)
    log = tmp_path / "world.jsonl"
    with Processes(tmp_path) as procs:
        rx = DepthReceiver(depth, 2)
        onboard1 = None
        try:
            vehicles = start_standins(procs, tmp_path, 2, base, sink, gcs, *FACING_EAST_6M)
            world = start_world(procs, tmp_path, "--px4", "2", "--gcs-port", str(gcs), "--depth-port", str(depth))
            rx.wait_all(30, "depth", procs)
            assert rx.collect(0.3)[0][-1].depth_m[CENTRE].min() == pytest.approx(5.7, abs=0.1)

            # Vehicle 1's position estimate fails (GPS off): it stops sending LOCAL_POSITION_NED.
            onboard1 = mavutil.mavlink_connection(f"udpin:127.0.0.1:{base + 1}", source_system=2, source_component=191,
                                                  dialect="common")
            assert onboard1.wait_heartbeat(timeout=10) is not None
            onboard1.mav.command_long_send(2, 1, 420, 0, 4, GPS_OFF, 0, 0, 0, 0, 0)  # MAV_CMD_INJECT_FAILURE
            lost = wait_event(log, lambda r: r.get("event") == "lost" and r["vehicle"] == 1, 5, "vehicle 1 lost")
            assert lost["why"].startswith("telemetry ") and float(lost["why"].split()[1]) >= 0.5
            rx.collect(0.2)  # frames in flight
            frames = rx.collect(1.5)
            assert frames[1] == []  # no frames for vehicle 1: its companion's camera failsafe holds
            assert len(frames[0]) >= 30 and frames[0][-1].depth_m[CENTRE].min() == 20.0  # and it is not drawn

            onboard1.mav.command_long_send(2, 1, 420, 0, 4, GPS_OK, 0, 0, 0, 0, 0)
            frames = rx.collect(1.5)
            assert frames[1] and frames[0][-1].depth_m[CENTRE].min() == pytest.approx(5.7, abs=0.1)

            # Both stand-ins die: every frame stops, the world waits for them.
            os.killpg(vehicles.pid, signal.SIGKILL)
            vehicles.wait(timeout=5)
            killed = time.monotonic()
            rx.collect(0.8)
            frames = rx.collect(1.5)
            assert frames == [[], []] and world.poll() is None
            assert time.monotonic() - killed < 5
            assert {e["vehicle"] for e in events(log, "lost")} == {0, 1}
            stop_world(procs, world, tmp_path)
        finally:
            rx.close()
            if onboard1 is not None:
                onboard1.close()
    waiting = [e for e in events(log, "status") if e["vehicle"] == 0 and e["state"] == "lost"]
    assert waiting and waiting[-1]["why"].startswith("telemetry")


def test_bad_arguments_exit_2_with_the_reason(capsys):
    from sitl.realtime.depth_bridge import parse_args

    cases = [
        ([], "one of the arguments --px4 --connect is required"),
        (["--px4", "0"], "must be >= 1"),
        (["--px4", "2", "--connect", "tcp:127.0.0.1:5760"], "not allowed with argument"),
        (["--connect", "tcp:nowhere"], "invalid connection"),
        (["--px4", "2", "--spawn-offsets", "0,0,0"], "gives 1 offset(s) but there are 2 vehicles"),
        (["--px4", "2", "--spawn-offsets", "0,0;1,1"], "--spawn-offsets needs 3 finite numbers"),
        (["--px4", "2", "--spacing", "3", "--offset-line", "0,3"], "not allowed with argument"),
        (["--px4", "2", "--px4-first-instance", "254"], "beyond MAVLink's 1..255"),
        (["--connect", "udp:14540", "--px4-first-instance", "1"], "only applies to --px4"),
        (["--px4", "1", "--camera-size", "32"], "WIDTHxHEIGHT"),
        (["--px4", "1", "--depth-port", "65535", "--px4-first-instance", "1"], "would pass 65535"),
    ]
    for argv, message in cases:
        with pytest.raises(SystemExit) as exit_info:
            parse_args(argv)
        assert exit_info.value.code == 2, argv
        assert message in capsys.readouterr().err, argv


def test_a_busy_gcs_port_exits_1_with_the_reason(capsys):
    from sitl.realtime.depth_bridge import main

    (port,) = free_udp_blocks(1)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as busy:  # as QGroundControl on 14550 would
        busy.bind(("127.0.0.1", port))
        assert main(["--px4", "1", "--gcs-host", "127.0.0.1", "--gcs-port", str(port)]) == 1
    assert f"cannot listen on udp 127.0.0.1:{port}" in capsys.readouterr().err


def test_layout_options_and_origin_arithmetic():
    from sitl.realtime.depth_bridge import Layout, Vehicle, ned_offset_m, parse_args, shift_global

    line = parse_args(["--px4", "3", "--offset-line", "0,3"]).offsets  # PX4 gazebo-classic: 3 m apart northwards
    assert np.allclose(line, [[0, 0, 0], [3, 0, 0], [6, 0, 0]])
    assert np.allclose(parse_args(["--connect", "udp:1", "--connect", "udp:2", "--spacing", "4"]).offsets,
                       [[0, 0, 0], [0, 4, 0]])
    assert parse_args(["--px4", "2"]).offsets is None  # default: from the global origins
    home = (47.397742, 8.545594, 488.0)
    moved = shift_global(home, 30.0, -12.0)
    assert np.allclose(ned_offset_m(home, moved), [30.0, -12.0, 0.0], atol=1e-3)
    vehicles = [Vehicle(0, "a", 1), Vehicle(1, "b", 2)]
    layout = Layout(None)
    assert layout.offset_ned(1, vehicles) is None  # unknown until both origins are
    vehicles[0].origin, vehicles[1].origin = home, (moved[0], moved[1], 530.0)  # altitude ignored: one flat ground
    assert np.allclose(layout.offset_ned(1, vehicles), [30.0, -12.0, 0.0], atol=1e-3)
    assert math.isclose(layout.offset_ned(0, vehicles)[0], 0.0)
