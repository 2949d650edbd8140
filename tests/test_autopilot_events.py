"""The autopilots' failsafes and their reasons, read back after a real-autopilot run (sitl.realtime.autopilot_events).

``data/px4_sih_offboard_loss.ulg`` is a real PX4 SIH log (session 55, vehicle 3 of a circle of 8 flown while the
machine was loaded), cut by pyulog to its ``event`` topic and the event metadata PX4 embeds: 39 events, among them two
offboard-loss failsafes. Nothing here needs PX4 built.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("pyulog")

from sitl.realtime.autopilot_events import (  # noqa: E402
    EventsError,
    format_failsafes,
    px4_failsafes,
    read_px4_events,
    run_failsafes,
)

ROOT = Path(__file__).resolve().parents[1]
ULOG = ROOT / "tests" / "data" / "px4_sih_offboard_loss.ulg"


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sitl.real_autopilots", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=60)


def test_px4_events_are_decoded_with_the_metadata_in_the_log():
    events = read_px4_events(ULOG)
    names = [e.name for e in events]
    assert len(events) == 39
    assert "commander_armed_by" in names and "commander_takeoff_detected" in names
    armed = events[names.index("commander_armed_by")]
    assert armed.message == "Armed by external command" and armed.group == "default"
    assert armed.t_unix_s is not None and armed.t_unix_s > 1.7e9  # PX4 SITL logs its UTC boot time


def test_a_failsafe_names_the_check_that_started_failing_with_it():
    failsafes = px4_failsafes(read_px4_events(ULOG), vehicle=3)
    assert [f.message for f in failsafes] == ["Failsafe activated: switching to RTL"] * 2
    first, second = failsafes
    # Mission and manual control were failing since boot (SITL has neither); the offboard signal is what was new.
    assert first.because == ["No offboard signal"]
    assert set(first.failing_checks) == {"No offboard signal", "No valid mission available", "No manual control input"}
    assert second.because == [] and "No offboard signal" in second.failing_checks  # still lost: nothing new
    assert 1.0 < second.t_boot_s - first.t_boot_s < 2.0
    assert "vehicle 3" in format_failsafes(failsafes) and "because: No offboard signal" in format_failsafes(failsafes)


def test_events_command_reads_a_run_folder(tmp_path):
    run = tmp_path / "run"
    (run / "px4_3" / "log" / "2026-12-01").mkdir(parents=True)
    shutil.copy(ULOG, run / "px4_3" / "log" / "2026-12-01" / "04_20_31.ulg")
    (run / "px4_0" / "log").mkdir(parents=True)  # a vehicle whose log is missing has no failsafe to report
    done = _cli("events", str(run))
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout.strip().splitlines()[-1])
    records = out["runs"][str(run)]
    assert [r["vehicle"] for r in records] == [3, 3] and records[0]["because"] == ["No offboard signal"]
    assert json.loads((run / "autopilot_failsafes.json").read_text()) == records
    assert "because: No offboard signal" in done.stderr


def test_ardupilot_failsafes_come_from_the_companions_logs(tmp_path):
    lines = [{"t": 10.0, "kind": "event", "event": "autopilot_text", "severity": 2, "text": "Radio Failsafe"},
             {"t": 11.0, "kind": "event", "event": "autopilot_text", "severity": 6, "text": "EKF3 IMU0 is using GPS"}]
    (tmp_path / "companion_1.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))
    failsafes = run_failsafes(tmp_path)
    assert [(f.vehicle, f.message, f.t_boot_s) for f in failsafes] == [(1, "Radio Failsafe", None)]


def test_bad_runs_are_one_line_errors(tmp_path):
    with pytest.raises(EventsError, match="not a sitl.real_autopilots run"):
        run_failsafes(tmp_path)
    done = _cli("events", str(tmp_path))
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "error:" in done.stderr
    broken = tmp_path / "px4_0" / "log" / "d"
    broken.mkdir(parents=True)
    (broken / "x.ulg").write_bytes(ULOG.read_bytes()[:40])  # the header only, cut mid-definition
    done = _cli("events", str(tmp_path))
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "ulg" in done.stderr, done.stderr
