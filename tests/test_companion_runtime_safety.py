"""Issue 16, the runtime's part: a final takeover, a blinded camera, stale/replayed/foreign depth
frames, a slow policy, goal range checks, cheap summaries and size-capped logs and recordings.

Unit-level tests use the real depth source on a real loopback socket; the flights drive the real
companion against the real simulated vehicle (:class:`ScenarioPool` starts them together).
Times compared across processes are UNIX times on one machine.
"""

from __future__ import annotations

import json
import math
import re
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import torch
from torch import nn

from companion.depth_sources import DepthConverter, DepthFault, DepthFrame, FrameTiming, SitlDepthSource
from companion.depth_wire import encode_frame
from companion.flightlog import FlightLog, RotatingTextFile, RunningStats, percentiles_ms
from companion.observation import DepthBlindedError, DepthFrameError, validate_depth_frame
from companion.policy import build_metadata, save_policy
from companion.recording import FlightRecorder, read_recording
from companion.spec import MAX_GOAL_DISTANCE_M, ActionSpec, CameraSpec, goal_problem
from tests.companion_helpers import (
    CONTROL_PERIOD_S,
    GoalSeeker,
    GroundStation,
    Rig,
    ScenarioPool,
    env,
    free_udp_ports,
    make_policy,
    scenario,
)

pytestmark = pytest.mark.timeout(150)

T = CONTROL_PERIOD_S
STALE_S = 1.5 * T
SCHED_SLACK_S = 0.06  # process wake-up and UDP delivery on a busy 2-core machine
FAILURE_UNIT_MAVLINK_SIGNAL, FAILURE_OK, FAILURE_OFF = 105, 0, 1
MAV_CMD_INJECT_FAILURE, MAV_CMD_DO_SET_MODE = 420, 176


# =========================================================================== depth: blinded sensor (item 5)

def _frame(fill: float, invalid_fraction: float = 0.0, invalid_value: float = 0.0) -> np.ndarray:
    frame = np.full((32, 32), fill, np.float32)
    frame.reshape(-1)[: int(round(invalid_fraction * frame.size))] = invalid_value
    return frame


@pytest.mark.parametrize("frame, what", [
    (_frame(0.0), "zero 1024"),                       # a covered RealSense / a lens against a wall
    (_frame(-3.0), "negative 1024"),                  # never a distance
    (_frame(5.0, 0.95, 0.0), "zero 973"),             # 95 % holes
    (_frame(5.0, 1.0, np.nan), "NaN/inf 1024"),       # a dead sensor
])
def test_a_blinded_frame_is_a_fault_not_clear_sky(frame, what):
    for source_hfov, raw in ((90.0, frame), (90.0, np.kron(frame, np.ones((2, 2), np.float32)))):  # as is, pooled
        with pytest.raises(DepthFrameError, match=r"^depth blinded: \d+ % of pixels invalid") as err:
            DepthConverter(CameraSpec()).convert(raw, source_hfov)
        assert what.split()[0] in str(err.value)
    with pytest.raises(DepthFrameError, match="depth blinded"):
        validate_depth_frame(frame, CameraSpec())


def test_open_sky_with_holes_still_flies():
    sky = _frame(8.0, 0.6, 0.0)  # the upper 60 % without stereo data, ground below: a normal view
    depth = DepthConverter(CameraSpec()).convert(sky, 90.0)
    assert np.all(depth[:19] == 20.0) and np.all(depth[20:] == 8.0)  # holes still read max range


def test_the_blinded_limit_is_the_operators_choice(tmp_path):
    """A camera whose open-sky view is 95 % holes (e.g. high above featureless ground) is blinded at the
    default 90 % limit; --max-invalid-depth 0.97 lets it fly (checked through open_depth_source)."""
    from companion.depth_sources import open_depth_source

    mostly_sky = _frame(8.0, 0.95, 0.0)
    with pytest.raises(DepthBlindedError):
        DepthConverter(CameraSpec()).convert(mostly_sky, 90.0)
    source = open_depth_source("sitl:127.0.0.1:14999", CameraSpec(), max_invalid_fraction=0.97)  # built, not started
    depth = source.converter.convert(mostly_sky, 90.0)
    assert np.all(depth[:30] == 20.0) and np.all(depth[31:] == 8.0)


# =========================================================================== depth: stamps and vehicle (item 5)

class _Sender:
    """Sends depth datagrams to a real SitlDepthSource and returns what it made of them."""

    def __init__(self, source: SitlDepthSource) -> None:
        self.source = source
        self.port = source.sock.getsockname()[1]
        self.tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.seq = 0

    def send(self, *, stamp_us: int, vehicle: int = 0, fill: float = 7.0) -> DepthFrame | DepthFault:
        self.seq += 1
        self.tx.sendto(encode_frame(np.full((32, 32), fill, np.float32), vehicle=vehicle, seq=self.seq,
                                    stamp_us=stamp_us, hfov_deg=90.0, max_range_m=20.0), ("127.0.0.1", self.port))
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            items = self.source.poll(time.monotonic())
            if items:
                assert len(items) == 1
                return items[0]
            time.sleep(0.002)
        raise AssertionError("the datagram never arrived")


@pytest.fixture
def sender():
    source = SitlDepthSource("127.0.0.1", 0, CameraSpec())
    source.start()
    source.set_stale_limit(STALE_S)
    s = _Sender(source)
    yield s
    s.tx.close()
    source.close()


def _now_us() -> int:
    return int(time.time() * 1e6)


def test_replayed_reordered_and_foreign_frames_are_faults(sender):
    first = _now_us()
    assert isinstance(sender.send(stamp_us=first), DepthFrame)  # locks to vehicle 0
    fault = sender.send(stamp_us=first)  # the same frame again: a replay
    assert isinstance(fault, DepthFault) and fault.reason.startswith("depth frame stamp repeats")
    assert f"sitl:127.0.0.1:{sender.port}" in fault.reason  # names the source
    fault = sender.send(stamp_us=first - 50_000)  # an older frame after a newer one
    assert isinstance(fault, DepthFault) and fault.reason.startswith("depth frame stamp goes backwards")
    fault = sender.send(stamp_us=_now_us(), vehicle=1)  # another vehicle's camera on our port
    assert isinstance(fault, DepthFault)
    assert fault.reason == f"depth frame from vehicle 1, but sitl:127.0.0.1:{sender.port} is locked to vehicle 0"
    assert isinstance(sender.send(stamp_us=_now_us()), DepthFrame)  # our camera again: accepted
    blind = sender.send(stamp_us=_now_us(), fill=0.0)
    assert isinstance(blind, DepthFault) and blind.reason.startswith("depth blinded: 100 % of pixels invalid")
    assert f"sitl:127.0.0.1:{sender.port}" in blind.reason


def test_a_stray_datagram_after_our_frame_does_not_hide_it(sender):
    """Our camera's frame, then another vehicle's frame and junk in the same read: the fault is
    reported, and our frame (the newest of ours) still comes out last, so the policy flies on it."""
    assert isinstance(sender.send(stamp_us=_now_us()), DepthFrame)  # locks to vehicle 0
    for vehicle, payload in ((0, None), (3, None), (0, b"junk")):
        sender.seq += 1
        data = payload or encode_frame(np.full((32, 32), 7.0, np.float32), vehicle=vehicle, seq=sender.seq,
                                       stamp_us=_now_us(), hfov_deg=90.0, max_range_m=20.0)
        sender.tx.sendto(data, ("127.0.0.1", sender.port))
    # All three wait in the socket: one poll reads them together. Well under the 150 ms staleness
    # limit: a frame's age counts from its stamp to when it is read (0.2 s here once failed CI).
    time.sleep(0.05)
    items = sender.source.poll(time.monotonic())
    assert [type(i).__name__ for i in items] == ["DepthFault", "DepthFault", "DepthFrame"], items
    assert items[0].reason.startswith("depth frame from vehicle 3") and items[1].reason.startswith("malformed")


def test_a_frame_delayed_in_transit_is_stale_without_synchronized_clocks(sender):
    skew_us = -3_600_000_000  # the sender's clock is an hour behind ours: only differences matter
    for _ in range(5):
        assert isinstance(sender.send(stamp_us=_now_us() + skew_us), DepthFrame)
        time.sleep(0.02)
    captured = _now_us() + skew_us
    time.sleep(STALE_S + 0.1)  # the frame spends 250 ms in a congested transport
    fault = sender.send(stamp_us=captured)
    assert isinstance(fault, DepthFault) and fault.reason.startswith("depth frame stale: ")
    late_ms = float(re.search(r"stale: (\d+) ms", fault.reason).group(1))
    assert STALE_S * 1000 < late_ms < STALE_S * 1000 + 400
    assert isinstance(sender.send(stamp_us=_now_us() + skew_us), DepthFrame)  # fresh ones fly again


def test_one_forged_stamp_cannot_blind_the_camera_but_a_clock_step_is_followed():
    timing = FrameTiming(stale_limit_s=STALE_S, resync_frames=5)
    t = 1000.0
    for k in range(10):
        assert timing.check(int((t + k * 0.033) * 1e6), t + k * 0.033 + 0.002) is None
    t += 10 * 0.033
    assert "ahead" in timing.check(int((t + 3600) * 1e6), t + 0.002)  # one forged frame from the future
    assert timing.check(int((t + 0.033) * 1e6), t + 0.035) is None  # the real camera is not locked out
    # The sender's clock steps back by 10 s (NTP): refused until 5 consistent frames re-sync it.
    results = [timing.check(int((t + 0.066 + k * 0.033 - 10.0) * 1e6), t + 0.068 + k * 0.033) for k in range(6)]
    assert all(r is not None and "backwards" in r for r in results[:4]) and results[4] is None and results[5] is None


# =========================================================================== goals (item 14)

@pytest.mark.parametrize("goal, message", [
    ((3.4e38, 0.0, -3.0), "from home horizontally"),
    ((1e9, -1e9, -3.0), "from home horizontally"),
    ((10.0, 0.0, 50.0), "goal altitude -50 m"),  # 50 m underground
    ((10.0, 0.0, 0.0), "goal altitude 0 m"),
    ((10.0, 0.0, -500.0), "goal altitude 500 m"),
    ((math.nan, 0.0, -3.0), "finite"),
])
def test_goal_validator_refuses_out_of_range_goals(goal, message):
    assert message in goal_problem(goal)
    assert goal_problem((20.0, 0.0, -3.0)) is None
    assert goal_problem((MAX_GOAL_DISTANCE_M + 10, 0.0, -3.0), from_ned=(20.0, 0.0, -3.0)) is None  # from the vehicle
    assert goal_problem((MAX_GOAL_DISTANCE_M + 10, 0.0, -3.0)) is not None  # from home


@pytest.mark.parametrize("goal, message", [
    ("3.4e38,0,-3", "goal is 3.4e+38 m from home horizontally (max 2500 m)"),
    ("1e9,-1e9,-3", "from home horizontally"),
    ("10,0,50", "goal altitude -50 m (D = 50) is outside 0.5 to 120 m above home"),
])
def test_goal_option_out_of_range_is_a_one_line_error(goal, message):
    out = subprocess.run([sys.executable, "-m", "companion.cli", "--connect", "udp:14540", "--model", "p.pt",
                          "--goal", goal], capture_output=True, text=True, env=env(), timeout=60)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    (error,) = [line for line in out.stderr.splitlines() if "error" in line]
    assert error.startswith("companion: error: argument --goal: goal ") and message in error


# =========================================================================== summaries (smaller list)

def test_summary_cost_stays_small_with_full_statistics_buffers(tmp_path):
    """5.5 h at 10 Hz = 198,000 samples per series: the old summary sorted them all (40 ms in the tick)."""
    rng = np.random.default_rng(0)
    series = [RunningStats() for _ in range(4)]
    samples = rng.lognormal(math.log(0.004), 0.3, 200_000)
    for stats in series:
        for value in samples:
            stats.append(float(value))
        stats.window()  # the summaries written during those hours
    for stats in series:  # the last 10 s
        for value in samples[:100]:
            stats.append(float(value))
    log = FlightLog(open(tmp_path / "log.jsonl", "w"), human=None)
    started = time.perf_counter()
    log.summary(final=False, **{f"s{k}": s.window() for k, s in enumerate(series)})
    periodic_s = time.perf_counter() - started
    started = time.perf_counter()
    log.summary(final=True, **{f"s{k}": s.total() for k, s in enumerate(series)})
    final_s = time.perf_counter() - started
    log.close()
    assert periodic_s < 0.004 and final_s < 0.004, (periodic_s, final_s)  # 10 % of a 40 ms tick overrun
    exact = percentiles_ms(np.concatenate([samples, samples[:100]]))
    total = series[0].total()
    assert total["n"] == 200_100 and total["max"] == exact["max"]
    for q in ("p50", "p99"):
        assert abs(total[q] - exact[q]) <= 0.01 * exact[q]  # within 1 %
    records = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert records[0]["s0"]["n"] == 100 and records[1]["s0"]["n"] == 200_100


# =========================================================================== log and recording size caps

def test_step_log_rotates_past_its_cap(tmp_path):
    path = tmp_path / "companion.jsonl"
    stream = RotatingTextFile(path, max_bytes=20_000, keep=2)
    log = FlightLog(stream, human=None)
    for step in range(1000):  # ~190 bytes a line: ~190 kB, ten times the cap
        log.step(step=step, phase="flying_to_goal", cmd=np.array([1.0, 0.0, 0.1]), pos_ned=np.array([step, 0.0, -3.0]))
    log.close()
    files = sorted(tmp_path.iterdir())
    assert [f.name for f in files] == ["companion.jsonl", "companion.jsonl.1", "companion.jsonl.2"]
    line_bytes = max(len(line) for f in files for line in f.read_bytes().splitlines(keepends=True))
    for f in files:
        assert f.stat().st_size <= 20_000 + line_bytes
        steps = [json.loads(line)["step"] for line in f.read_text().splitlines()]
        assert steps == list(range(steps[0], steps[0] + len(steps)))  # whole lines, in order
    newest = [json.loads(line)["step"] for line in path.read_text().splitlines()]
    assert newest[-1] == 999
    kept = [json.loads(line)["step"] for f in (files[2], files[1], files[0]) for line in f.read_text().splitlines()]
    assert kept == list(range(kept[0], 1000))  # the kept files continue each other


def test_recording_rotates_into_parts_each_readable(tmp_path):
    cam = CameraSpec()
    path = tmp_path / "flight.snrec"
    rec = FlightRecorder(path, cam, 0.1, "policy.pt", max_bytes=50_000, keep=3)  # ~4.2 kB a record
    for k in range(60):
        rec.write(t_wall_s=1000.0 + k * 0.1, t_mono_s=50.0 + k * 0.1, step=k, frame_seq=k, hold=False,
                  depth_m=np.full((cam.height, cam.width), k, np.float32), state=np.zeros(6), action=np.zeros(3),
                  pos_ned_m=np.array([k, 0.0, -3.0]), yaw_rad=0.0)
    rec.close()
    parts = [path.with_name(f"flight.snrec.{i}") for i in (3, 2, 1)] + [path]
    assert all(p.exists() for p in parts) and not path.with_name("flight.snrec.4").exists()
    steps = []
    for part in parts:
        assert part.stat().st_size <= 50_000 + 4300
        header, records = read_recording(part)
        assert header["camera"] == cam.to_dict()
        steps += records["step"].tolist()
        assert np.all(records["depth_m"][:, 0, 0] == records["step"])
    assert steps == list(range(steps[0], 60))  # consecutive parts, the oldest dropped


# =========================================================================== flights

class SlowAboveSpeed(nn.Module):
    """The goal seeker, but each call takes ~0.6 s once flying faster than ``slow_above_m_s``."""

    def __init__(self, iterations: int, slow_above_m_s: float) -> None:
        super().__init__()
        action = ActionSpec()
        self.inner = GoalSeeker(list(action.low), list(action.high))
        self.iterations = iterations
        self.slow_above_m_s = slow_above_m_s
        self.register_buffer("w", torch.randn(256, 256) / 16.0)

    def forward(self, depth: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        action = self.inner(depth, state)
        if bool(state[0, 3] > self.slow_above_m_s):
            x = self.w
            for _ in range(self.iterations):
                x = torch.tanh(x @ self.w)
            action = action + 0.0 * x[0, 0]
        return action


def _slow_policy(path, seconds: float = 0.8):
    torch.set_num_threads(1)
    probe = torch.jit.script(SlowAboveSpeed(50, -1.0))
    depth, state = torch.full((1, 3, 32, 32), 20.0), torch.zeros(1, 6)
    durations = []
    for _ in range(4):  # the first calls profile and optimize: take the fastest
        started = time.perf_counter()
        probe(depth, state)
        durations.append(time.perf_counter() - started)
    per_iteration = min(durations) / 50
    module = SlowAboveSpeed(max(20, int(seconds / per_iteration)), slow_above_m_s=0.8)
    provenance = {"method": "slow test policy", "scenario": "none", "steps": 0, "wall_time_s": 0.0,
                  "git_commit": "test", "evaluation": {}}
    save_policy(module, build_metadata(CameraSpec(), ActionSpec(), T, provenance), path)
    return path


class CameraFeeder:
    """Stands in for the vehicle's camera on the companion's depth port: 30 Hz frames of the real
    wire format, clear sky (20 m) until a test switches ``mode``."""

    def __init__(self, port: int) -> None:
        self.port, self.mode = port, "clear"
        self.tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.seq = 0
        self.captured: bytes | None = None
        self.first_sent: dict[str, float] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def switch(self, mode: str) -> float:
        """Change what is sent; return the UNIX time the first frame of ``mode`` left."""
        self.mode = mode
        deadline = time.monotonic() + 2.0
        while mode not in self.first_sent and time.monotonic() < deadline:
            time.sleep(0.005)
        return self.first_sent[mode]

    def _run(self) -> None:
        while not self._stop.wait(1 / 30):
            mode = self.mode
            fill = {"zeros": 0.0, "negative": -2.0}.get(mode, 20.0)
            self.seq += 1
            datagram = encode_frame(np.full((32, 32), fill, np.float32), vehicle=1 if mode == "other_vehicle" else 0,
                                    seq=self.seq, stamp_us=int(time.time() * 1e6), hfov_deg=90.0, max_range_m=20.0)
            if mode == "clear" and self.captured is None:
                self.captured = datagram
            if mode == "replay":
                datagram = self.captured  # an old datagram of our own camera, sent again and again
            self.first_sent.setdefault(mode, time.time())
            try:
                self.tx.sendto(datagram, ("127.0.0.1", self.port))
            except OSError:
                pass
        self.tx.close()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)


def _start_takeover(rig: Rig, tmp) -> None:
    rig.start_vehicle("--airborne", "--start", "0,0,-3")
    rig.start_companion(make_policy(tmp / "policy.pt"), "--goal", "500,0,-3", "--arm", "--takeoff", "3",
                        "--timeout", "150")


def _start_landed(rig: Rig, tmp) -> None:
    rig.start_vehicle("--airborne", "--start", "0,0,-3")
    # The recording goes to /dev/full: every flush fails (ENOSPC), as on a full SD card in flight.
    rig.start_companion(make_policy(tmp / "policy.pt"), "--goal", "3,0,-3", "--arm", "--takeoff", "3",
                        "--land-on-arrival", "--timeout", "150", "--record", "/dev/full")


def _start_blind(rig: Rig, tmp) -> None:
    (elsewhere,) = free_udp_ports(1)  # the vehicle's own frames go nowhere: the test is the camera
    rig.start_vehicle("--airborne", "--start", "0,0,-3", "--depth-port", str(elsewhere))
    rig.feeder = CameraFeeder(rig.depth_port)  # the paper camera's frames: a policy for that camera
    rig.start_companion(make_policy(tmp / "policy.pt", camera=CameraSpec()), "--goal", "500,0,-3", "--arm", "--takeoff", "3",
                        "--exit-on-arrival", "--timeout", "150")


def _start_slow(rig: Rig, tmp) -> None:
    rig.start_vehicle("--airborne", "--start", "0,0,-3", "--camera", "paper")  # the slow policy's camera
    rig.start_companion(_slow_policy(tmp / "slow.pt"), "--goal", "500,0,-3", "--arm", "--takeoff", "3",
                        "--exit-on-arrival", "--timeout", "150")


@pytest.fixture(scope="module")
def rigs(request, tmp_path_factory):
    # "slow" first: it times its policy before the other rigs load the CPU.
    pool = ScenarioPool(request, tmp_path_factory, {"slow": _start_slow, "takeover": _start_takeover,
                                                    "blind": _start_blind, "landed": _start_landed})
    yield pool
    for rig in pool.rigs.values():
        if hasattr(rig, "feeder"):
            rig.feeder.stop()
    pool.stop_all()


def _steps(rig: Rig, after_t: float = -math.inf) -> list[dict]:
    return [r for r in rig.companion_records() if r.get("kind") == "step" and r["t"] >= after_t]


@scenario("takeover")
def test_goals_out_of_range_are_refused_in_flight(rigs):
    """Item 14: run-time goals out of range are refused, naming the sender; the flight goes on."""
    rig = rigs["takeover"]
    gcs = GroundStation(rig.gcs_port)
    gcs.wait_heartbeat()
    rig.wait_flying(60)
    try:
        t_goals = time.time()
        for goal in ((3.4e38, 0.0, -3.0), (1e9, -1e9, -3.0), (10.0, 0.0, 50.0)):
            gcs.send_goal(*goal)
        rig.wait_for_event(lambda r: len([x for x in rig.companion_records() if x.get("event") == "goal"
                                          and x["t"] >= t_goals]) >= 3, 5.0, "three goal events")
        refused = [r for r in rig.companion_records() if r.get("event") == "goal" and r["t"] >= t_goals]
        assert [bool(r.get("refused")) for r in refused] == [True, True, True], [r["message"] for r in refused]
        assert all("from system 255, unsigned" in r["message"] and r["sender"] == [255, 190] for r in refused)
        assert "from the vehicle horizontally" in refused[0]["reason"] and "from the vehicle" in refused[1]["reason"]
        assert "goal altitude -50 m" in refused[2]["reason"]  # 50 m underground
        assert all("keeping [500.0, 0.0, -3.0]" in r["message"] for r in refused)
        time.sleep(0.5)
        after = [s for s in _steps(rig, max(r["t"] for r in refused)) if s["phase"] == "flying_to_goal"]
        assert after and all(s["goal_ned"] == [500.0, 0.0, -3.0] for s in after)
        assert any(s["sent"] and not s["hold"] and s["cmd"][0] > 0.3 for s in after)  # still flying the old goal
        gcs.send_goal(400.0, 0.0, -3.0)  # a sane goal still goes through
        rig.wait_for_event(lambda r: r.get("event") == "goal" and not r.get("refused") and r["t"] >= t_goals,
                           5.0, "the sane goal accepted")
    finally:
        gcs.close()


@scenario("takeover")
def test_a_takeover_survives_a_link_outage(rigs):
    """Item 4: the pilot takes over, the link drops for 3 s and comes back: still handed back, for good."""
    rig = rigs["takeover"]
    gcs = GroundStation(rig.gcs_port)
    gcs.wait_heartbeat()
    rig.wait_flying(60)
    with rig.procs:
        assert gcs.command(MAV_CMD_DO_SET_MODE, 1, 3, 0) == 0  # the pilot selects POSCTL
        handed = rig.wait_for_event(lambda r: r.get("event") == "phase" and r.get("to") == "handed_back", 5.0,
                                    "handed_back")
        assert gcs.command(MAV_CMD_INJECT_FAILURE, FAILURE_UNIT_MAVLINK_SIGNAL, FAILURE_OFF) == 0
        time.sleep(3.0)  # a 3 s outage: longer than the 2 s link timeout
        assert gcs.command(MAV_CMD_INJECT_FAILURE, FAILURE_UNIT_MAVLINK_SIGNAL, FAILURE_OK) == 0
        time.sleep(4.0)  # the old code asked for OFFBOARD again ~3 s after the link's return
        assert rig.companion.poll() is None
        gcs.close()
    records = rig.companion_records()
    phases = [r for r in records if r.get("event") == "phase" and r["t"] > handed["t"]]
    assert phases == [], [p["message"] for p in phases]  # no link_lost -> waiting_for_telemetry -> switching_mode
    after = [r for r in records if r.get("kind") == "step" and r["t"] >= handed["t"]]
    assert len(after) > 30 and all(not r["sent"] and r["phase"] == "handed_back" for r in after)
    modes = [r["mode"] for r in rig.vehicle_records() if r["event"] == "mode"]
    assert modes[-1] == "POSCTL" and modes.count("OFFBOARD") == 1  # OFFBOARD never requested back
    requests = [r for r in rig.vehicle_records() if r["event"] in ("mode_refused", "set_mode_msg", "armed")
                and r["t"] > handed["t"]]
    assert requests == []
    links = [r for r in records if r.get("event") == "link" and r["t"] > handed["t"]]
    assert [r.get("lost") for r in links] == [True, False], [r["message"] for r in links]
    assert "staying handed back" in links[0]["message"] and "staying handed back" in links[1]["message"]


@scenario("landed")
def test_a_landed_flight_stays_over_after_a_link_outage(rigs):
    """A link blip after landing must not start a second flight (--arm): the companion stays landed, sends nothing.
    And a recording that fails in flight (a full disk) stops the recording, not the flight."""
    rig = rigs["landed"]
    landed = rig.wait_for_event(lambda r: r.get("event") == "phase" and r.get("to") == "landed", 90.0, "landed")
    gcs = GroundStation(rig.gcs_port)
    gcs.wait_heartbeat()
    with rig.procs:
        assert gcs.command(MAV_CMD_INJECT_FAILURE, FAILURE_UNIT_MAVLINK_SIGNAL, FAILURE_OFF) == 0
        time.sleep(3.0)  # longer than the 2 s link timeout
        assert gcs.command(MAV_CMD_INJECT_FAILURE, FAILURE_UNIT_MAVLINK_SIGNAL, FAILURE_OK) == 0
        rig.wait_for_event(lambda r: r.get("event") == "phase" and r.get("from") == "link_lost", 5.0, "link back")
        time.sleep(3.0)  # the old code was streaming and arming again by now
        assert rig.companion.poll() is None
        gcs.close()
    phases = [r["to"] for r in rig.companion_records() if r.get("event") == "phase" and r["t"] > landed["t"]]
    assert phases == ["link_lost", "landed"], phases
    after = [r for r in rig.companion_records() if r.get("kind") == "step" and r["t"] > landed["t"]]
    assert after and not any(r["sent"] for r in after)
    rearmed = [r for r in rig.vehicle_records() if r["event"] == "armed" and r["t"] > landed["t"]]
    assert rearmed == []
    # The full disk stopped the recording, not the flight (which landed above).
    stopped = [r for r in rig.companion_records() if r.get("event") == "recording"]
    assert len(stopped) == 1 and "recording stopped" in stopped[0]["message"], stopped


def _first_hold(rig: Rig, t_fault: float, reason: str) -> dict:
    hold = rig.wait_for_event(lambda r: r.get("kind") == "step" and r["t"] >= t_fault
                              and (r.get("hold") or "").startswith(reason), 3.0, f"a hold for {reason!r}")
    assert hold["sent"] and hold["cmd"] == [0.0, 0.0, 0.0] and hold["phase"] == "flying_to_goal"
    assert hold["t"] - t_fault <= 2 * T, f"hold {hold['t'] - t_fault:.3f} s after the first bad frame"
    assert f"sitl:127.0.0.1:{rig.depth_port}" in hold["hold"] or reason.startswith("depth frame from")
    policy_steps = [s for s in _steps(rig, t_fault) if s["t"] < hold["t"] and s["sent"] and not s["hold"]]
    assert len(policy_steps) <= 2  # at most the steps already computed from good frames
    return hold


@scenario("blind")
def test_blinded_replayed_and_foreign_depth_frames_hold_within_two_periods(rigs):
    rig = rigs["blind"]
    rig.wait_flying(60)
    feeder = rig.feeder
    faults = {"zeros": "depth blinded: 100 % of pixels invalid", "negative": "depth blinded: 100 % of pixels invalid",
              "other_vehicle": "depth frame from vehicle 1", "replay": "depth frame stamp goes backwards"}
    with rig.procs:
        for mode, reason in faults.items():
            t_fault = feeder.switch(mode)
            hold = _first_hold(rig, t_fault, reason)
            print(f"{mode}: hold {hold['t'] - t_fault:.3f} s after the first bad frame")
            time.sleep(0.4)
            held = _steps(rig, hold["t"])
            assert held and all(s["hold"] and s["hold"].startswith(reason) and s["cmd"] == [0.0, 0.0, 0.0]
                                for s in held)
            feeder.first_sent.pop("clear", None)
            t_back = feeder.switch("clear")
            rig.wait_for_event(lambda r, t=t_back: r.get("kind") == "step" and r["t"] > t and not r.get("hold")
                               and (r.get("cmd") or [0])[0] > 0.1, 3.0, "policy steps after clear frames")
            feeder.first_sent.pop(mode, None)
    assert "HOLD (zero velocity): depth blinded" in rig.procs.stderr("companion")


@scenario("slow")
def test_a_slow_policy_is_held_at_its_deadline_and_late_answers_are_discarded(rigs):
    rig = rigs["slow"]
    rig.wait_flying(60)
    with rig.procs:
        first = rig.wait_for_event(lambda r: r.get("kind") == "step" and (r.get("hold") or "").startswith(
            "policy inference late"), 20.0, "a late-inference hold")
        rig.wait_for_event(lambda r: r.get("event") == "policy_late", 5.0, "a discarded late answer")
        time.sleep(2.0)
    records = rig.companion_records()
    call_ms, frame_ms = (float(v) for v in re.search(r"no answer (\d+) ms into the call, (\d+) ms since the frame",
                                                     first["hold"]).groups())
    # Held at the deadline: when the frame went stale or the next tick was due, whichever first.
    assert frame_ms <= STALE_S * 1000 + SCHED_SLACK_S * 1000 and call_ms <= T * 1000 + SCHED_SLACK_S * 1000
    assert frame_ms >= STALE_S * 1000 or call_ms >= T * 1000
    window = [r for r in records if r.get("kind") == "step" and first["t"] - 1.0 <= r["t"] <= first["t"] + 2.0
              and r["phase"] == "flying_to_goal"]
    sent_t = [r["t"] for r in window if r["sent"]]
    gaps = np.diff(sent_t)
    print(f"setpoint gaps around slow inference: max {gaps.max():.3f} s over {len(sent_t)} setpoints")
    assert gaps.max() <= 2 * T + SCHED_SLACK_S  # the hold covers the inference: never silent
    late = [r for r in window if (r.get("hold") or "").startswith("policy inference late")]
    assert len(late) >= 5
    policy_sent = [r for r in records if r.get("kind") == "step" and r["sent"] and not r["hold"]
                   and r["phase"] == "flying_to_goal" and r["policy"] is not None]
    assert all(r["inference_ms"] is not None and r["inference_ms"] <= STALE_S * 1000 for r in policy_sent)
    discarded = [r for r in records if r.get("event") == "policy_late"]
    assert discarded and max(r["inference_ms"] for r in discarded) > 2 * STALE_S * 1000  # the slow calls
    print(f"first late hold {call_ms:.0f} ms into the call, {frame_ms:.0f} ms after its frame; late answers discarded: {len(discarded)}, "
          f"median {np.median([r['inference_ms'] for r in discarded]):.0f} ms")
