"""One test per failsafe, end to end: the real companion flying the real simulated vehicle.

Each test lets the policy fly, breaks one thing (through the vehicle's MAV_CMD_INJECT_FAILURE,
a pilot's mode switch, a kill -9 or a bad model file) and checks that the safe reaction —
a zero-velocity hold, or no commanding at all — happens within two control periods and that
the companion says why. Times compared across the two processes are UNIX times on one machine.
The flying scenarios start together (:class:`ScenarioPool`) so their start-ups overlap.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import warnings
import zipfile

import pytest
import torch

from tests.companion_helpers import (
    CONTROL_PERIOD_S,
    GroundStation,
    Rig,
    ScenarioPool,
    env,
    free_udp_ports,
    make_policy,
    scenario,
)

pytestmark = pytest.mark.timeout(120)

T = CONTROL_PERIOD_S
SCHED_SLACK_S = 0.06  # process wake-up and UDP delivery on a busy 2-core machine
FAILURE_UNIT_GPS, FAILURE_UNIT_DEPTH_CAMERA, FAILURE_UNIT_MAVLINK_SIGNAL = 4, 7, 105
FAILURE_OK, FAILURE_OFF, FAILURE_GARBAGE = 0, 1, 3
MAV_CMD_INJECT_FAILURE, MAV_CMD_DO_SET_MODE = 420, 176


def _flying_starter(nan_policy: bool = False):
    """A PX4 vehicle hovering at 3 m and a companion flying it towards a goal 500 m ahead."""
    def start(rig: Rig, tmp) -> None:
        policy = make_policy(tmp / "policy.pt", nan_above_speed=0.6 if nan_policy else 0.0)
        rig.start_vehicle("--airborne", "--start", "0,0,-3")
        rig.start_companion(policy, "--goal", "500,0,-3", "--arm", "--takeoff", "3", "--exit-on-arrival",
                            "--timeout", "150")
    return start


@pytest.fixture(scope="module")
def rigs(request, tmp_path_factory):
    pool = ScenarioPool(request, tmp_path_factory, {
        name: _flying_starter(nan_policy=name == "nan")
        for name in ("camera", "odometry", "malformed", "pilot", "stall", "nan", "link")})
    yield pool
    pool.stop_all()


def _flying(rigs, name: str) -> tuple[Rig, GroundStation]:
    rig = rigs[name]
    gcs = GroundStation(rig.gcs_port)
    # The pool starts seven vehicles and companions at once: on a cold start (no bytecode yet) their
    # imports alone can take longer than the default 20 s on 2 cores.
    gcs.wait_heartbeat(60)
    rig.wait_flying(60)
    return rig, gcs


def _vehicle_event_t(rig: Rig, event: str, **match) -> float:
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:
        for r in rig.vehicle_records():
            if r["event"] == event and all(r.get(k) == v for k, v in match.items()):
                return r["t"]
        time.sleep(0.05)
    raise AssertionError(f"the vehicle never logged {event} {match}")


def _inject(rig: Rig, gcs: GroundStation, unit: int, failure_type: int) -> float:
    """Inject a failure through the ground station; return the UNIX time the vehicle applied it."""
    sent = time.time()
    assert gcs.command(MAV_CMD_INJECT_FAILURE, unit, failure_type) == 0
    kind = {0: "ok", 1: "off", 3: "garbage"}[failure_type]
    return min(r["t"] for r in rig.vehicle_records()
               if r["event"] == "failure_injected" and r["unit"] == unit and r["type"] == kind and r["t"] >= sent)


def _assert_hold_within_two_periods(rig: Rig, t_fault: float, reason: str, timeout_s: float = 3.0) -> dict:
    """The first hold for ``reason`` came within 2 control periods of the fault, after <= 2 policy steps.

    Stale inputs (older than 1.5 periods) are held at once, between ticks if need be, so the
    bound holds whatever the phase of the ticks.
    """
    hold = rig.wait_for_event(lambda r: r.get("kind") == "step" and r["t"] >= t_fault
                              and (r.get("hold") or "").startswith(reason), timeout_s, f"a hold for {reason!r}")
    assert hold["sent"] and hold["cmd"] == [0.0, 0.0, 0.0] and hold["phase"] == "flying_to_goal"
    assert hold["t"] - t_fault <= 2 * T, f"hold {hold['t'] - t_fault:.3f} s after the fault"
    steps = [r for r in rig.companion_records() if r.get("kind") == "step" and t_fault <= r["t"] < hold["t"]]
    assert len(steps) <= 2 and all(s["sent"] for s in steps)
    return hold


def _assert_flies_again(rig: Rig, after_t: float) -> None:
    rig.wait_for_event(lambda r: r.get("kind") == "event" and r.get("event") == "failsafe" and r.get("cleared")
                       and r["t"] > after_t, 3.0, "the failsafe clearing")
    rig.wait_for_event(lambda r: r.get("kind") == "step" and r["t"] > after_t and not r.get("hold")
                       and (r.get("cmd") or [0])[0] > 0.1, 3.0, "policy steps after recovery")


@scenario("camera")
def test_camera_stops(rigs):
    rig, gcs = _flying(rigs, "camera")
    procs = rig.procs
    with procs:
        t_fault = _inject(rig, gcs, FAILURE_UNIT_DEPTH_CAMERA, FAILURE_OFF)
        hold = _assert_hold_within_two_periods(rig, t_fault, "depth stale")
        time.sleep(0.5)
        steps = [r for r in rig.companion_records() if r.get("kind") == "step" and r["t"] > hold["t"]]
        assert steps and all(s["hold"].startswith("depth stale") and s["cmd"] == [0, 0, 0] for s in steps)
        t_back = _inject(rig, gcs, FAILURE_UNIT_DEPTH_CAMERA, FAILURE_OK)
        _assert_flies_again(rig, t_back)
        gcs.close()
    assert "HOLD (zero velocity): depth stale" in procs.stderr("companion")


@scenario("odometry")
def test_odometry_stops(rigs):
    rig, gcs = _flying(rigs, "odometry")
    procs = rig.procs
    with procs:
        t_fault = _inject(rig, gcs, FAILURE_UNIT_GPS, FAILURE_OFF)  # the autopilot loses its position estimate
        _assert_hold_within_two_periods(rig, t_fault, "odometry stale")
        t_back = _inject(rig, gcs, FAILURE_UNIT_GPS, FAILURE_OK)
        _assert_flies_again(rig, t_back)
        gcs.close()
    assert "HOLD (zero velocity): odometry stale" in procs.stderr("companion")


@scenario("malformed")
def test_malformed_depth_frame(rigs):
    rig, gcs = _flying(rigs, "malformed")
    procs = rig.procs
    with procs:
        t_fault = _inject(rig, gcs, FAILURE_UNIT_DEPTH_CAMERA, FAILURE_GARBAGE)  # truncated datagrams
        hold = _assert_hold_within_two_periods(rig, t_fault, "malformed depth frame")
        assert "truncated or corrupted" in hold["hold"]
        t_back = _inject(rig, gcs, FAILURE_UNIT_DEPTH_CAMERA, FAILURE_OK)
        _assert_flies_again(rig, t_back)
        gcs.close()
    assert "HOLD (zero velocity): malformed depth frame" in procs.stderr("companion")


@scenario("pilot")
def test_pilot_switches_mode(rigs):
    rig, gcs = _flying(rigs, "pilot")
    procs = rig.procs
    with procs:
        assert gcs.command(MAV_CMD_DO_SET_MODE, 1, 3, 0) == 0  # the pilot selects POSCTL
        t_switch = _vehicle_event_t(rig, "mode", mode="POSCTL")
        code = rig.wait_companion(10)
        gcs.close()
        time.sleep(0.3)
    assert code == 6  # PILOT_TOOK_OVER (with --exit-on-arrival)
    records = rig.companion_records()
    last_sent = max(r["t"] for r in records if r.get("kind") == "step" and r["sent"])
    assert last_sent - t_switch <= 2 * T + SCHED_SLACK_S
    handed = [r for r in records if r.get("event") == "phase" and r.get("to") == "handed_back"]
    assert handed and "pilot took over: mode POSCTL" in handed[0]["message"]
    modes = [r["mode"] for r in rig.vehicle_records() if r["event"] == "mode"]
    assert modes[-1] == "POSCTL" and modes.count("OFFBOARD") == 1  # never requested back
    assert "pilot took over" in procs.stderr("companion")


@scenario("stall")
def test_companion_stall_is_named_when_the_autopilot_takes_over(rigs):
    """The computer stops the companion 1.6 s (SIGSTOP): PX4's offboard-loss failsafe (1 s) switches to a hold mode;
    the companion logs its own stall and hands back naming it, not a pilot."""
    rig, gcs = _flying(rigs, "stall")
    procs = rig.procs
    with procs:
        os.kill(rig.companion.pid, signal.SIGSTOP)
        try:
            time.sleep(1.6)
        finally:
            os.kill(rig.companion.pid, signal.SIGCONT)
        code = rig.wait_companion(10)
        gcs.close()
    assert code == 6  # PILOT_TOOK_OVER (with --exit-on-arrival): the takeover is final, whoever made it
    records = rig.companion_records()
    stalls = [r for r in records if r.get("event") == "stall"]
    assert stalls and 1.5 <= stalls[0]["gap_s"] < 3.0, stalls
    handed = [r for r in records if r.get("event") == "phase" and r.get("to") == "handed_back"]
    assert handed and "autopilot took over (its setpoint-loss failsafe" in handed[0]["message"], handed
    assert "mode AUTO.LOITER" in handed[0]["message"]
    assert [r["mode"] for r in rig.vehicle_records() if r["event"] == "mode"][-1] == "AUTO.LOITER"
    assert "this computer stalled" in procs.stderr("companion")


@scenario("nan")
def test_policy_returns_nan(rigs):
    rig, gcs = _flying(rigs, "nan")  # its policy is finite at rest and NaN above 0.6 m/s
    procs = rig.procs
    with procs:
        rig.wait_for_event(lambda r: r.get("kind") == "step" and (r.get("hold") or "").startswith("policy output not finite"),
                           10, "a NaN hold")
        time.sleep(1.5)
        gcs.close()
        statuses = [r for r in rig.vehicle_records() if r["event"] == "status"]
    steps = [r for r in rig.companion_records() if r.get("kind") == "step" and r["phase"] == "flying_to_goal"]
    nan_steps = [s for s in steps if s["policy"] is not None and None in s["policy"]]
    assert len(nan_steps) >= 3
    for s in nan_steps:  # held in the very step the NaN came out (0 periods)
        assert s["sent"] and s["cmd"] == [0.0, 0.0, 0.0] and s["hold"].startswith("policy output not finite")
    assert max(abs(v) for r in statuses for v in r["vel_ned"]) < 1.3  # never reached cruise speed
    assert "HOLD (zero velocity): policy output not finite" in procs.stderr("companion")


@scenario("link")
def test_link_dies(rigs):
    rig, gcs = _flying(rigs, "link")
    procs = rig.procs
    with procs:
        # The companion link goes silent both ways (the camera keeps streaming).
        t_fault = _inject(rig, gcs, FAILURE_UNIT_MAVLINK_SIGNAL, FAILURE_OFF)
        _assert_hold_within_two_periods(rig, t_fault, "odometry stale")
        code = rig.wait_companion(10)
        t_failsafe = _vehicle_event_t(rig, "mode", mode="AUTO.LOITER")  # the autopilot's offboard-loss failsafe
        gcs.close()
    assert code == 5  # LINK
    assert 0.9 <= t_failsafe - t_fault <= 1.6
    lost = [r for r in rig.companion_records() if r.get("event") == "phase" and r.get("to") == "link_lost"]
    assert lost and 1.0 <= lost[0]["t"] - t_fault <= 2.0 + T + SCHED_SLACK_S  # 2 s after the last 1 Hz heartbeat
    after = [r for r in rig.companion_records() if r.get("kind") == "step" and r["t"] >= lost[0]["t"]]
    assert all(not r["sent"] for r in after)  # left to the autopilot's failsafe
    assert "link lost: no heartbeat" in procs.stderr("companion")


def _not_a_policy(path):
    path.write_bytes(b"this is not a model\n")


def _no_metadata(path):
    with warnings.catch_warnings():  # torch 2.13 deprecates TorchScript; the policy contract still uses it
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.jit.save(torch.jit.script(torch.nn.Linear(6, 3)), str(path))


def _nan_policy(path):
    make_policy(path, nan_above_speed=-1.0)  # NaN on every input, even the blank check


def _wrong_state_layout(path):
    make_policy(path)
    with zipfile.ZipFile(path) as z:
        files = {n: z.read(n) for n in z.namelist()}
    meta_name = next(n for n in files if n.endswith("extra/policy.json"))
    files[meta_name] = files[meta_name].replace(b'"goal_fwd_m"', b'"goal_x_m"')
    with zipfile.ZipFile(path, "w") as z:
        for n, data in files.items():
            z.writestr(n, data)


WRONG_MODELS = {
    "not_a_policy": (_not_a_policy, "not a TorchScript policy file"),
    "no_metadata": (_no_metadata, "no policy.json inside"),
    "nan_on_blank": (_nan_policy, "forward returned non-finite actions"),
    "wrong_state_layout": (_wrong_state_layout, "state layout"),
}


def test_wrong_model_file_is_refused_before_connecting(tmp_path):
    procs = {}
    try:
        for name, (make, _reason) in WRONG_MODELS.items():  # the four start together
            path = tmp_path / f"{name}.pt"
            make(path)
            (port,) = free_udp_ports(1)
            procs[name] = subprocess.Popen(
                [sys.executable, "-m", "companion.cli", "--connect", f"udpin:127.0.0.1:{port}", "--model", str(path),
                 "--camera", "sitl:1", "--log", str(tmp_path / f"{name}.jsonl")],
                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env())
        for name, proc in procs.items():
            _stdout, stderr = proc.communicate(timeout=60)
            reason = WRONG_MODELS[name][1]
            assert proc.returncode == 3, f"{name}: exit {proc.returncode}\n{stderr}"
            assert reason in stderr and "cannot use the model" in stderr, f"{name}: {stderr}"
            assert "connected to" not in stderr  # nothing was commanded: the link was never opened
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def test_no_autopilot_heartbeat_is_a_clear_error(tmp_path):
    policy = make_policy(tmp_path / "policy.pt")
    port, depth_port = free_udp_ports(2)
    started = time.monotonic()
    out = subprocess.run([sys.executable, "-m", "companion.cli", "--connect", f"udpin:127.0.0.1:{port}", "--model",
                          str(policy), "--camera", f"sitl:{depth_port}", "--heartbeat-timeout", "1",
                          "--log", str(tmp_path / "log.jsonl")], capture_output=True, text=True, env=env(), timeout=60)
    assert out.returncode == 5
    assert f"no heartbeat from an autopilot on udpin:127.0.0.1:{port} within 1 s" in out.stderr
    assert time.monotonic() - started < 20
