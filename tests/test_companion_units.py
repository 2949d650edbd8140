"""The companion's parts on their own: connection strings, depth conversion and transport,
recordings, odometry frames, modes, the control clock, systemd notify, signing keys, the CLI."""

from __future__ import annotations

import json
import math
import socket
import subprocess
import sys
import time
from types import SimpleNamespace

import numpy as np
import pytest

from companion import cli
from companion.depth_sources import DepthConverter, DepthFault, ReplayDepthSource, SitlDepthSource, z16_to_metres
from companion.depth_wire import HEADER_SIZE, decode_frame, encode_frame
from companion.flight_modes import AutopilotKind, is_companion_mode, mode_name, px4_custom_mode, px4_main_sub
from companion.mavlink_link import load_signing_key, normalize_connection, odometry_from_msg
from companion.observation import DepthFrameError
from companion.recording import FlightRecorder, RecordingError, read_recording
from companion.clock import ControlClock
from companion.sdnotify import SystemdNotifier
from companion.spec import CameraSpec
from tests.companion_helpers import env


# --------------------------------------------------------------------------- connection strings

@pytest.mark.parametrize("text, expected", [
    ("udp:14540", "udpin:0.0.0.0:14540"),
    ("udp:127.0.0.1:14541", "udpin:127.0.0.1:14541"),
    ("udpout:10.0.0.2:14550", "udpout:10.0.0.2:14550"),
    ("tcp:127.0.0.1:5760", "tcp:127.0.0.1:5760"),
    ("/dev/ttyTHS1,921600", "/dev/ttyTHS1,921600"),
    ("/dev/ttyACM0", "/dev/ttyACM0"),
])
def test_connection_strings(text, expected):
    assert normalize_connection(text) == expected


@pytest.mark.parametrize("text", ["udp:", "udp:99999", "14540", "tcp:host", "serial", "udp:a:b"])
def test_bad_connection_strings_are_refused(text):
    with pytest.raises(ValueError, match="invalid connection"):
        normalize_connection(text)


# --------------------------------------------------------------------------- the command line

@pytest.mark.parametrize("argv, message", [
    (["--connect", "udp:14540", "--model", "p.pt", "--goal", "1,2"], "goal must be three finite numbers"),
    (["--connect", "udp:14540", "--model", "p.pt", "--goal", "1,nan,2"], "goal must be three finite numbers"),
    (["--connect", "bogus", "--model", "p.pt"], "invalid connection 'bogus'"),
    (["--connect", "udp:14540", "--model", "p.pt", "--camera", "sitl:abc"], "the port must be a number"),
    (["--connect", "udp:14540", "--model", "p.pt", "--camera", "kinect"], "invalid camera 'kinect'"),
    (["--connect", "udp:14540", "--model", "p.pt", "--arm"], "--arm needs --takeoff"),
    (["--connect", "udp:14540", "--model", "p.pt", "--arm", "--takeoff", "-3"], "--takeoff must be > 0"),
    (["--connect", "udp:14540"], "--model is required"),
    (["--model", "p.pt"], "--connect is required"),
])
def test_bad_cli_values_exit_2_with_a_reason(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.parse_args(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_cli_process_rejects_a_bad_value_with_status_2():
    out = subprocess.run([sys.executable, "-m", "companion.cli", "--connect", "udp:14540", "--model", "x.pt",
                          "--takeoff", "abc", "--arm"], capture_output=True, text=True, env=env(), timeout=60)
    assert out.returncode == 2 and "--takeoff must be a number" in out.stderr


# --------------------------------------------------------------------------- depth conversion

def test_z16_zeros_are_no_data_not_obstacles_and_objects_survive_min_pooling():
    policy_cam = CameraSpec(width=32, height=32, hfov_deg=90.0, max_range_m=20.0)
    z16 = np.full((64, 64), 5000, dtype=np.uint16)  # 5 m wall at 1 mm per unit
    z16[:, :10] = 0  # a band of holes (no stereo match)
    z16[30, 40] = 1500  # a single-pixel object at 1.5 m
    depth = DepthConverter(policy_cam).convert(z16_to_metres(z16, 0.001), 90.0)
    assert depth.shape == (32, 32) and depth.dtype == np.float32
    assert depth.min() == pytest.approx(1.5)  # one source pixel survives the 2x2 min-pool
    assert depth[15, 20] == pytest.approx(1.5)
    assert np.all(depth[:, :5] == 20.0)  # holes read max range, never 0 m
    assert np.allclose(depth[:, 5:][depth[:, 5:] > 2.0], 5.0) and (depth[:, 5:] < 2.0).sum() == 1


def test_a_wider_camera_is_cropped_to_the_policy_fov():
    policy_cam = CameraSpec(width=32, height=32, hfov_deg=90.0)
    wide = np.full((96, 96), 10.0, dtype=np.float32)  # 126.87 deg: tan(half) = 2
    wide[:, :24] = 1.0  # only outside the policy's field of view
    wide[:, 72:] = 1.0
    depth = DepthConverter(policy_cam).convert(wide, math.degrees(2 * math.atan(2.0)))
    assert depth.shape == (32, 32) and np.all(depth == 10.0)
    with pytest.raises(DepthFrameError, match="narrower than the policy"):
        DepthConverter(policy_cam).convert(np.ones((64, 64), np.float32), 87.0)


@pytest.mark.parametrize("frame, message", [
    (np.full((32, 32), np.nan, np.float32), "depth blinded: 100 % of pixels invalid"),
    (np.ones((32,), np.float32), "2-D"),
    (np.ones((32, 32), np.int32), "floating-point"),
    (np.ones((16, 16), np.float32), "smaller than the policy"),
])
def test_unusable_frames_are_refused_with_the_reason(frame, message):
    with pytest.raises(DepthFrameError, match=message):
        DepthConverter(CameraSpec()).convert(frame, 90.0)


# --------------------------------------------------------------------------- the SITL depth transport

def test_depth_wire_roundtrip_float_and_z16():
    depth = np.random.default_rng(0).uniform(0.5, 19.0, (24, 40)).astype(np.float32)
    depth[3, 4] = 0.0
    wire = decode_frame(encode_frame(depth, vehicle=2, seq=7, stamp_us=123, hfov_deg=100.0, max_range_m=20.0))
    assert np.array_equal(wire.depth_m, depth) and (wire.vehicle, wire.seq, wire.stamp_us) == (2, 7, 123)
    z16 = decode_frame(encode_frame(depth, vehicle=0, seq=1, stamp_us=0, hfov_deg=100.0, max_range_m=20.0,
                                    depth_scale=0.001))
    assert np.allclose(z16.depth_m, depth, atol=0.0006) and z16.depth_m[3, 4] == 0.0


@pytest.mark.parametrize("mangle, message", [
    (lambda d: d[: len(d) // 2], "truncated or corrupted"),
    (lambda d: b"XXXX" + d[4:], "not a swarmnav depth frame"),
    (lambda d: d[:HEADER_SIZE - 1], "shorter than the 40-byte header"),
    (lambda d: d[:4] + bytes([9]) + d[5:], "version 9 is not supported"),
])
def test_malformed_datagrams_are_refused(mangle, message):
    good = encode_frame(np.ones((32, 32), np.float32), vehicle=0, seq=0, stamp_us=0, hfov_deg=90.0, max_range_m=20.0)
    with pytest.raises(DepthFrameError, match=message):
        decode_frame(mangle(good))


def test_sitl_source_reports_frames_and_malformed_datagrams_over_a_real_socket():
    source = SitlDepthSource("127.0.0.1", 0, CameraSpec())
    source.start()
    port = source.sock.getsockname()[1]
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    frame = np.full((32, 32), 7.0, np.float32)
    try:
        tx.sendto(encode_frame(frame, vehicle=0, seq=5, stamp_us=0, hfov_deg=90.0, max_range_m=20.0), ("127.0.0.1", port))
        time.sleep(0.05)
        items = source.poll(time.monotonic())
        assert len(items) == 1 and items[0].seq == 5 and np.all(items[0].depth_m == 7.0)
        assert items[0].arrival_s <= time.monotonic()
        tx.sendto(b"SNDP garbage", ("127.0.0.1", port))
        time.sleep(0.05)
        (fault,) = source.poll(time.monotonic())
        assert isinstance(fault, DepthFault) and fault.reason.startswith("malformed depth frame")
    finally:
        tx.close()
        source.close()


# --------------------------------------------------------------------------- recordings and replay

def test_recording_roundtrip_and_replay_timing(tmp_path):
    cam = CameraSpec()
    path = tmp_path / "flight.snrec"
    rec = FlightRecorder(path, cam, 0.1, "policy.pt")
    for k in range(5):
        rec.write(t_wall_s=1000.0 + k * 0.1, t_mono_s=50.0 + k * 0.1, step=k, frame_seq=100 + k, hold=k == 3,
                  depth_m=np.full((32, 32), 1.0 + k, np.float32), state=np.arange(6, dtype=np.float32),
                  action=np.array([1.0, 0.0, 0.1]), pos_ned_m=np.array([k, 0.0, -3.0]), yaw_rad=0.0)
    rec.close()
    with open(path, "ab") as f:
        f.write(b"\x00" * 17)  # a record cut short by a power loss
    header, records = read_recording(path)
    assert header["camera"]["width"] == 32 and len(records) == 5
    assert records["hold"].tolist() == [0, 0, 0, 1, 0] and records["frame_seq"][-1] == 104
    replay = ReplayDepthSource(str(path), cam)
    replay.start()
    t0 = replay._t0
    assert [f.seq for f in replay.poll(t0 + 0.001)] == [100]
    assert replay.poll(t0 + 0.05) == []
    (frame,) = replay.poll(t0 + 0.25)  # two more are due: only the newest matters
    assert frame.seq == 102 and np.all(frame.depth_m == 3.0)
    (bad := tmp_path / "bad.snrec").write_bytes(b"not a recording\n")
    with pytest.raises(RecordingError, match="not a swarmnav recording"):
        read_recording(bad)


def test_a_recording_keeps_a_longer_state_and_refuses_a_bad_state_dim(tmp_path):
    """A policy with remembered depth records its whole state (the header says how long); a recording
    without ``state_dim`` (written before it existed) reads as the paper's 6."""
    cam = CameraSpec(width=8, height=8)
    path = tmp_path / "memory.snrec"
    rec = FlightRecorder(path, cam, 0.1, "policy.pt", state_dim=32)
    rec.write(t_wall_s=1.0, t_mono_s=1.0, step=0, frame_seq=0, hold=False, depth_m=np.ones((8, 8), np.float32),
              state=np.arange(32, dtype=np.float32), action=np.zeros(3), pos_ned_m=np.zeros(3), yaw_rad=0.0)
    rec.close()
    header, records = read_recording(path)
    assert header["state_dim"] == 32 and records["state"][0].tolist() == list(range(32))
    line, body = path.read_bytes().split(b"\n", 1)
    for bad in (True, 3, "32", 10 ** 6):
        (broken := tmp_path / "broken.snrec").write_bytes(
            json.dumps({**json.loads(line), "state_dim": bad}).encode() + b"\n" + body)
        with pytest.raises(RecordingError, match="state_dim must be an integer in 6..256"):
            read_recording(broken)


# --------------------------------------------------------------------------- odometry frames and modes

def _odometry(child_frame_id, vx, vy, vz, yaw):
    q = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
    return SimpleNamespace(frame_id=1, child_frame_id=child_frame_id, x=1.0, y=2.0, z=-3.0, q=q, vx=vx, vy=vy, vz=vz,
                           rollspeed=0.0, pitchspeed=0.0, yawspeed=0.2)


def test_odometry_velocity_follows_child_frame_id():
    yaw = math.radians(90.0)  # heading east, flying east at 2 m/s
    ned = odometry_from_msg(_odometry(1, 0.0, 2.0, 0.1, yaw), 0.0)  # PX4 1.14+: LOCAL_NED
    body = odometry_from_msg(_odometry(12, 2.0, 0.0, 0.1, yaw), 0.0)  # PX4 <= 1.13: BODY_FRD
    assert np.allclose(ned.vel_ned, [0.0, 2.0, 0.1], atol=1e-6)
    assert np.allclose(body.vel_ned, ned.vel_ned, atol=1e-6)
    assert ned.yaw_rad == pytest.approx(yaw) and ned.yaw_rate_rad_s == pytest.approx(0.2)
    with pytest.raises(ValueError, match="child_frame_id 99"):
        odometry_from_msg(_odometry(99, 0, 0, 0, 0), 0.0)


def test_px4_and_ardupilot_mode_encoding():
    assert px4_custom_mode(6) == 6 << 16 == 393216
    assert px4_main_sub(px4_custom_mode(4, 3)) == (4, 3)
    assert mode_name(AutopilotKind.PX4, px4_custom_mode(4, 6)) == "AUTO.LAND"
    assert is_companion_mode(AutopilotKind.PX4, px4_custom_mode(6)) and not is_companion_mode(AutopilotKind.PX4, 3 << 16)
    assert is_companion_mode(AutopilotKind.ARDUPILOT, 4) and mode_name(AutopilotKind.ARDUPILOT, 5) == "LOITER"


# --------------------------------------------------------------------------- the control clock

def test_control_clock_locks_its_ticks_just_after_frame_arrivals():
    period, camera = 0.1, 1 / 30
    rng = np.random.default_rng(1)
    # 30 Hz frames at an arbitrary phase, delivered late by a scheduling noise (mostly < 1 ms, 3 % ~5 ms).
    grid = 0.0137 + np.arange(600) * camera
    arrivals = grid + np.where(rng.random(600) < 0.03, 0.005, rng.exponential(0.0004, 600))
    clock = ControlClock(period, 0.0, lock=True)
    ages, periods, reported, last_tick = [], [], 0, None
    for _tick in range(150):
        t = clock.next_tick_s
        while reported < len(arrivals) and arrivals[reported] <= t:
            clock.frame_arrived(arrivals[reported])
            reported += 1
        ages.append(t - arrivals[reported - 1] if reported else None)
        if last_tick is not None:
            periods.append(t - last_tick)
        last_tick = t
        clock.advance(t)
    locked_ages = np.array(ages[-60:])
    assert np.median(locked_ages) < 0.004  # a frame waits ~2 ms for its tick, not up to 33 ms
    assert np.mean(locked_ages < camera / 2) >= 0.93  # the tick comes after (nearly) every expected frame
    assert max(abs(p - period) for p in periods) <= 0.002 + 1e-9  # acquiring never bends a period by > 2 ms
    assert max(abs(p - period) for p in periods[-60:]) <= 0.001  # locked: well inside the 2 ms jitter budget
    assert clock.locked and 0.003 <= clock.margin_s < 0.008


def test_control_clock_skips_missed_ticks_instead_of_bursting():
    clock = ControlClock(0.1, 0.0, lock=False)
    clock.advance(0.35)  # the tick due at 0.1 ran at 0.35
    assert clock.next_tick_s == pytest.approx(0.4) and clock.missed_ticks == 2


# --------------------------------------------------------------------------- systemd notify and signing keys

def test_sd_notify_sends_ready_and_rate_limited_watchdog(tmp_path, monkeypatch):
    path = tmp_path / "notify.sock"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(str(path))
    server.settimeout(1.0)
    monkeypatch.setenv("NOTIFY_SOCKET", str(path))
    monkeypatch.setenv("WATCHDOG_USEC", "2000000")
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    try:
        notifier = SystemdNotifier()
        notifier.ready("up")
        assert server.recv(4096).decode().startswith("READY=1\nSTATUS=up")
        notifier.watchdog(10.0)
        notifier.watchdog(10.1)  # within WatchdogSec/4: not resent
        notifier.watchdog(10.6)
        assert [server.recv(4096), server.recv(4096)] == [b"WATCHDOG=1", b"WATCHDOG=1"]
        server.settimeout(0.1)
        with pytest.raises(socket.timeout):
            server.recv(4096)
    finally:
        server.close()


def test_signing_key_files(tmp_path):
    raw = bytes(range(32))
    (tmp_path / "raw.key").write_bytes(raw)
    (tmp_path / "hex.key").write_text(raw.hex() + "\n")
    (tmp_path / "short.key").write_text("secret")
    assert load_signing_key(tmp_path / "raw.key") == raw == load_signing_key(tmp_path / "hex.key")
    with pytest.raises(ValueError, match="must hold 32 raw bytes or 64 hex characters"):
        load_signing_key(tmp_path / "short.key")
