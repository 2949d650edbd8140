"""The fuzz harness in CI: ``benchmarks/fuzz_companion.py --smoke`` against the real companion and vehicle.

Issue 16's targets, on a short run (4000 inputs at 800/s, 3 hostile model files): no crash,
no setpoint outside the action bounds or non-finite on the wire, no link drop and no hold
caused by malformed MAVLink, no out-of-range goal accepted, no step flown on a blinded,
stale or foreign depth frame, every hostile model refused with exit 3 and no traceback;
with signing, no behaviour change from forged or replayed traffic. A unit test first shows
the harness's wire check does catch bad setpoints, so a clean run means something.
"""

from __future__ import annotations

import importlib
import json
import math
import subprocess
import sys

from tests.companion_helpers import REPO, env

HARNESS = REPO / "benchmarks" / "fuzz_companion.py"


def _harness_module():
    if str(HARNESS.parent) not in sys.path:
        sys.path.insert(0, str(HARNESS.parent))
    return importlib.import_module("fuzz_companion")


def test_wire_check_catches_out_of_bounds_and_non_finite_setpoints():
    harness = _harness_module()
    from companion.spec import ActionSpec
    from fuzz_inputs import mavlink

    checker = harness.SetpointChecker(ActionSpec())
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)

    def setpoint(fwd: float, down: float, yaw_rate: float) -> bytes:
        msg = mav.set_position_target_local_ned_encode(0, 1, 1, 8, 1479, 0, 0, 0, fwd, 0, down, 0, 0, 0, 0, yaw_rate)
        return msg.pack(mav)

    checker.check(setpoint(2.0, -0.5, 0.5))  # the bounds themselves are fine
    checker.check(setpoint(50.0, -20.0, 5.0))  # issue 16 item 6: what a +-100 bounds model sent
    checker.check(setpoint(math.nan, 0.0, 0.0))
    checker.check(setpoint(1.0, 0.0, 0.0) + setpoint(-0.1, 0.0, 0.0))  # two frames in one datagram
    assert (checker.checked, checker.out_of_bounds, checker.non_finite) == (5, 2, 1)


def _run_smoke(*extra: str) -> dict:
    proc = subprocess.run([sys.executable, str(HARNESS), "--smoke", *extra], cwd=REPO, env=env(),
                          capture_output=True, text=True, timeout=300)
    lines = proc.stdout.strip().splitlines()
    assert lines, f"no output (exit {proc.returncode}); stderr:\n{proc.stderr[-3000:]}"
    report = json.loads(lines[-1])
    assert proc.returncode in (0, 1) and not report.get("error"), \
        f"the harness could not run (exit {proc.returncode}): {report.get('error')}\n{proc.stderr[-3000:]}"
    return report


def _assert_targets(report: dict) -> None:
    # The run measured something: inputs went out and the wire check saw the companion's setpoints.
    assert report["inputs_by_phase"].get("mavlink", 0) >= 1500, report["inputs_by_phase"]
    assert report["inputs_by_phase"].get("depth", 0) >= 1000, report["inputs_by_phase"]
    assert report["setpoints_checked"] >= 30, report["setpoints_checked"]
    assert all(p["steps"] > 0 for p in report["depth_probes"].values()), report["depth_probes"]
    # Issue 16's targets.
    assert report["crashes"] == 0, report["crash_details"]
    assert report["setpoints_out_of_bounds"] == 0, report["setpoint_examples"]
    assert report["setpoints_non_finite"] == 0, report["setpoint_examples"]
    assert report["link_drops"] == 0, report["link_drops_by_phase"]
    assert report["mavlink_phase_hold_findings"] == [], report["holds_by_phase"].get("mavlink")
    assert not report["goals_accepted_by_phase"], report["goals_accepted_by_phase"]
    assert report["depth_steps_flown_on_refusable_frames"] == 0, report["depth_flown_on_refusable_by_kind"]
    assert report["models"]["tracebacks"] == 0, report["models"]["not_refused"]
    assert report["models"]["not_refused"] == [], report["models"]["not_refused"]
    assert report["findings"] == [], report["findings"]


def test_fuzz_smoke():
    report = _run_smoke()
    _assert_targets(report)


def test_fuzz_smoke_signing():
    report = _run_smoke("--signing", "--seed", "1")
    assert report["inputs_by_phase"].get("signing", 0) >= 1000, report["inputs_by_phase"]
    assert report["signing_behaviour_changes"] == 0, report["signing_behaviour_changes_by_kind"]
    _assert_targets(report)
