"""The systemd unit and its environment file: valid, notify + watchdog, devices reachable,
and the command line it builds is one the companion accepts. (READY=1 and WATCHDOG=1 from a
real companion are checked in test_companion_flight.py.)"""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

from companion import cli

SYSTEMD = Path(__file__).resolve().parents[1] / "systemd"


def _directives(text: str) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith(("#", "[")) and "=" in line:
            key, value = line.split("=", 1)
            out.setdefault(key, []).append(value)
    return out


def test_unit_is_notify_with_watchdog_restart_and_reachable_devices():
    unit = _directives((SYSTEMD / "companion.service").read_text())
    assert unit["Type"] == ["notify"] and unit["NotifyAccess"] == ["main"]
    assert float(unit["WatchdogSec"][0]) > 0 and unit["Restart"] == ["on-failure"]
    assert unit["EnvironmentFile"] == ["/etc/swarmnav/companion.env"]
    assert "PrivateDevices" not in unit and "DevicePolicy" not in unit  # UART and camera must stay reachable
    groups = unit["SupplementaryGroups"][0].split()
    assert {"dialout", "video"} <= set(groups)
    assert unit["NoNewPrivileges"] == ["yes"] and unit["ProtectSystem"] == ["strict"]


def test_env_example_builds_a_command_line_the_companion_accepts(tmp_path):
    unit = _directives((SYSTEMD / "companion.service").read_text())
    env = {}
    for line in (SYSTEMD / "companion.env.example").read_text().splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            key, value = line.split("=", 1)
            env[key.strip()] = value.strip()
    exec_start = unit["ExecStart"][0]
    # systemd: ${VAR} is one argument, $VAR is split on whitespace.
    words = []
    for word in shlex.split(exec_start):
        if re.fullmatch(r"\$\{\w+\}", word):
            words.append(env[word[2:-1]])
        elif re.fullmatch(r"\$\w+", word):
            words.extend(env.get(word[1:], "").split())
        else:
            words.append(word)
    assert words[0].endswith("/companion")
    log_dir = "/var/log/" + unit["LogsDirectory"][0]
    assert env["COMPANION_LOG"].startswith(log_dir + "/")  # the unit's LogsDirectory=, which systemd creates
    # --log refuses a missing directory, and this machine has no /var/log/swarmnav: stand in a
    # directory that exists, as systemd's LogsDirectory= does on the vehicle.
    args = cli.parse_args([w.replace(log_dir, str(tmp_path)) for w in words[1:]])
    assert args.connect == "/dev/ttyTHS1,921600" and args.camera.startswith("realsense")
    assert args.model.endswith("policy.pt") and args.log == env["COMPANION_LOG"].replace(log_dir, str(tmp_path))


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_analyze_verifies_the_unit(tmp_path):
    # Installed, ExecStart points into the venv; here it points at an executable that exists.
    text = (SYSTEMD / "companion.service").read_text().replace("/opt/swarmnav/venv/bin/companion", "/bin/true")
    unit = tmp_path / "companion.service"
    unit.write_text(text)
    out = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stderr.strip() == "" and out.stdout.strip() == "", out.stderr
