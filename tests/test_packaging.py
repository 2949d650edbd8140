"""The installed package: the onboard core does not depend on the simulator; the CLIs answer."""

from __future__ import annotations

import json
import subprocess
import sys


def test_companion_does_not_import_sitl():
    code = "import sys, companion.observation, companion.cli; assert not [m for m in sys.modules if m.startswith('sitl')]"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_companion_describe_prints_the_contract():
    out = subprocess.run([sys.executable, "-m", "companion.cli", "--describe"], check=True, capture_output=True, text=True)
    contract = json.loads(out.stdout)
    assert contract["state"][0] == "goal_fwd_m" and contract["action"]["high"] == [2.0, 0.5, 0.5]


def test_demo_runs_and_rejects_bad_values(tmp_path):
    ok = subprocess.run([sys.executable, "-m", "sitl.demo", "--n", "4", "--episodes", "2", "--out", str(tmp_path)],
                        capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0, ok.stderr
    assert "success rate" in ok.stdout and (tmp_path / "trajectories.png").stat().st_size > 1000
    assert json.loads((tmp_path / "metrics.json").read_text())["summary"]["uav_episodes"] == 8
    bad = subprocess.run([sys.executable, "-m", "sitl.demo", "--scenario", "spiral"], capture_output=True, text=True)
    assert bad.returncode == 2 and "invalid choice: 'spiral'" in bad.stderr
