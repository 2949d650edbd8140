"""Each vehicle's velocity response: fitted from a flight's logs, drawn per UAV in evaluation and training.

``sitl.realtime.response_fit`` (``python -m sitl.real_autopilots fit``) must recover a known response from
logs in the format the companion and the world write; ``--response`` must reach the simulator in
``swarm_test`` and ``sitl.train``.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sitl.sim.dynamics import (RESPONSE_PRESETS, KinematicDynamics, KinematicParams, KinematicRandomization,
                               describe_response, nominal_ranges, parse_response)

ROOT = Path(__file__).resolve().parents[1]
T0 = 1_800_000_000.0  # UNIX seconds of the synthetic flight's first tick


def _fly_logs(folder: Path, vehicles: list[dict], seconds: float = 24.0) -> None:
    """Write a run folder as ``sitl.real_autopilots`` leaves it (companion_I.jsonl steps, trace.jsonl poses) for
    vehicles flown through the kinematic law with known responses. ``delay_s``: the vehicle acts on each command
    that much after the companion logged it. A 2 s position hold in the middle (logged with its hold point, as the
    companion's station-keeping is) must be left out of the fit."""
    rng = np.random.default_rng(5)
    period, n = 0.1, len(vehicles)
    ticks = int(seconds / period)
    # Forward steps between 0 and 2 m/s, climbs of +-0.5 m/s and turns, changing every 1.5-3 s.
    cmd = np.zeros((ticks, 3))
    k = 0
    while k < ticks:
        run = int(rng.uniform(15, 30))
        cmd[k:k + run] = [rng.choice([0.0, 0.6, 1.2, 2.0]), rng.uniform(-0.5, 0.5), rng.choice([0.0, -0.4, 0.4])]
        k += run
    hold = (ticks // 2, ticks // 2 + 20)  # position-target ticks: the vehicle does what it likes meanwhile
    dyn = KinematicDynamics(n)
    for name in ("tau_horizontal_s", "drag_horizontal_per_s", "integral_horizontal_per_s2", "tau_vertical_s"):
        dyn.response[name][:] = [v.get(name, getattr(KinematicParams(), name)) for v in vehicles]
    dyn.reset(np.arange(n), np.tile([0.0, 0.0, -8.0], (n, 1)), np.zeros(n))
    delay_ticks = [int(round(v.get("delay_s", 0.0) / 0.02)) for v in vehicles]
    step_s = 0.02
    sub = int(round(period / step_s))
    history = [np.zeros((n, 3))] * 50
    poses, steps = [], [[] for _ in range(n)]
    for k in range(ticks):
        t = T0 + k * period
        for i in range(n):
            held = hold[0] <= k < hold[1]
            steps[i].append({"t": t, "kind": "step", "phase": "flying_to_goal", "sent": True,
                             "cmd": [0.0, 0.0, 0.0] if held else cmd[k].tolist(),
                             "hold_point_ned": [0.0, 0.0, -8.0] if held else None})
        for _ in range(sub):
            history.append(np.tile(cmd[k], (n, 1)) if not hold[0] <= k < hold[1] else np.tile([0.3, 0.2, 0.0], (n, 1)))
            applied = np.stack([history[-1 - delay_ticks[i]][i] for i in range(n)])
            dyn.step(applied, step_s, np.ones(n, dtype=bool))
        poses.append({"t": t + period, "event": "pose", "pos_ned": dyn.pos_ned.tolist(), "vel_ned": dyn.vel_ned.tolist(),
                      "yaw_rad": dyn.yaw_rad.tolist(), "mode": ["OFFBOARD"] * n, "armed": [True] * n})
    for i in range(n):
        (folder / f"companion_{i}.jsonl").write_text("".join(json.dumps(s) + "\n" for s in steps[i]))
    (folder / "trace.jsonl").write_text("".join(json.dumps(p) + "\n" for p in poses))


def test_fit_recovers_known_responses(tmp_path):
    """Two vehicles with different responses (a plain fast lag; PX4 SIH's PI loop against drag with a delay):
    the fit finds each within one grid step, and fits the second better than a plain lag can."""
    from sitl.realtime.response_fit import fit_run, response_spec

    truth = [{"tau_horizontal_s": 0.35, "tau_vertical_s": 0.2},
             {"tau_horizontal_s": 0.8, "drag_horizontal_per_s": 0.5, "integral_horizontal_per_s2": 0.2,
              "tau_vertical_s": 0.4, "delay_s": 0.1}]
    _fly_logs(tmp_path, truth)
    fast, px4 = fit_run(tmp_path)
    assert fast.tau_horizontal_s == pytest.approx(0.35, abs=0.051)
    assert fast.drag_horizontal_per_s <= 0.05 and fast.delay_s <= 0.05
    assert fast.tau_vertical_s == pytest.approx(0.2, abs=0.051)
    assert px4.tau_horizontal_s == pytest.approx(0.8, abs=0.101)
    assert px4.drag_horizontal_per_s == pytest.approx(0.5, abs=0.101)
    assert px4.delay_s == pytest.approx(0.1, abs=0.051)
    assert px4.tau_vertical_s == pytest.approx(0.4, abs=0.101)
    # Not exact: after the hold the fit restarts the integrator from 0, where the vehicle's had wound up.
    assert px4.rms_error_m_s < 0.05 and px4.lag_only_rms_error_m_s > 2 * px4.rms_error_m_s
    assert fast.fitted_s == pytest.approx(22.0, abs=0.5)  # the 2 s position hold is not fitted
    spec = parse_response(response_spec([fast, px4]), nominal_ranges())
    assert spec.tau_horizontal_s == (fast.tau_horizontal_s, px4.tau_horizontal_s)


def test_fit_command_line(tmp_path):
    """``python -m sitl.real_autopilots fit RUN --plot PNG``: the table on stderr, one JSON line on stdout with the
    spec, RUN/response_fit.json and the figure written; a folder without logs is one line and exit 2."""
    _fly_logs(tmp_path, [{"tau_horizontal_s": 0.5}], seconds=12.0)
    run = subprocess.run([sys.executable, "-m", "sitl.real_autopilots", "fit", str(tmp_path), "--plot",
                          str(tmp_path / "fig" / "fits.png")], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout.strip().splitlines()[-1])
    assert out["response"].startswith("tau_horizontal_s=0.5:0.5,")
    assert json.loads((tmp_path / "response_fit.json").read_text())["vehicles"][0]["tau_horizontal_s"] == 0.5
    assert "quick gain" in run.stderr
    assert (tmp_path / "fig" / "fits.png").stat().st_size > 5000
    bad = subprocess.run([sys.executable, "-m", "sitl.real_autopilots", "fit", str(tmp_path / "nothing")], cwd=ROOT,
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert bad.stderr.strip().count("\n") == 0 and "trace.jsonl: no such file" in bad.stderr


def test_parse_response():
    base = nominal_ranges()
    assert all(lo == hi for lo, hi in (getattr(base, f.name) for f in dataclasses.fields(base)))
    px4 = parse_response("px4-sih", base)
    assert px4.tau_horizontal_s == RESPONSE_PRESETS["px4-sih"]["tau_horizontal_s"]
    assert px4.tau_yaw_s == base.tau_yaw_s  # what the preset does not name stays nominal
    later = parse_response("px4-sih,tau_horizontal_s=1.2", base)
    assert later.tau_horizontal_s == (1.2, 1.2)
    assert describe_response(later, base).startswith("tau_horizontal_s=1.2,")
    assert describe_response(base, base) == "nominal"
    for bad, why in [("fast", "expected a preset"), ("tau_horizontal_s=", "finite numbers"), ("tau=0.5", "FIELD one of"),
                     ("tau_horizontal_s=1:0.5", "low <= high"), ("", "names nothing"),
                     ("tau_horizontal_s=nan", "finite")]:
        with pytest.raises(ValueError, match=why):
            parse_response(bad, base)


def test_command_delay_shifts_the_response_by_the_delay():
    """``command_delay_s``: a UAV flies the command it was sent that long ago, so its velocity is the undelayed
    UAV's, shifted by the delay (whole periods, and 0.06 s, three 0.02 s sub-steps); before its first command, and
    again after a reset, it holds (the previous episode's commands are gone)."""
    period = 0.1
    dyn = KinematicDynamics(3)
    dyn.response["command_delay_s"][:] = [0.0, 0.2, 0.06]
    rows, active = np.arange(3), np.ones(3, dtype=bool)

    def fly(ticks: int) -> np.ndarray:
        dyn.reset(rows, np.tile([0.0, 0.0, -5.0], (3, 1)), np.zeros(3))
        speeds = []
        for k in range(ticks):
            command = [2.0, -0.5, 0.3] if k < 10 else [0.5, 0.4, -0.2]
            dyn.step(np.tile(command, (3, 1)), period, active)
            speeds.append(dyn.vel_ned.copy())
        return np.array(speeds)

    first = fly(25)
    assert np.all(first[:2, 1] == 0.0) and first[2, 1, 0] > 0  # two periods of hold, then the first command acts
    np.testing.assert_allclose(first[2:, 1], first[:-2, 0], atol=1e-12)
    with_sub_steps = KinematicDynamics(1, KinematicParams(substep_s=0.02))  # 0.06 s = 3 sub-steps: compare at 0.02 s
    with_sub_steps.reset(np.arange(1), np.array([[0.0, 0.0, -5.0]]), np.zeros(1))
    fine = []
    for k in range(125):
        with_sub_steps.step(np.array([[2.0, -0.5, 0.3] if k < 50 else [0.5, 0.4, -0.2]]), 0.02, active[:1])
        fine.append(with_sub_steps.vel_ned[0].copy())
    np.testing.assert_allclose(first[:, 2], np.array(fine)[np.arange(25) * 5 + 4 - 3], atol=1e-12)
    again = fly(25)  # the same episode after a reset: the last episode's commands do not leak into it
    np.testing.assert_array_equal(again, first)


def test_command_delay_ranges():
    """A delay range parses like the others, is off (no draw) by default and is bounded by MAX_COMMAND_DELAY_S."""
    from sitl.sim.dynamics.kinematic import MAX_COMMAND_DELAY_S

    base = nominal_ranges()
    assert base.command_delay_s == (0.0, 0.0)
    drawn = parse_response("command_delay_s=0:0.2", KinematicRandomization())
    assert drawn.command_delay_s == (0.0, 0.2)
    assert describe_response(drawn, KinematicRandomization()) == "command_delay_s=0:0.2"
    with pytest.raises(ValueError, match="command_delay_s must be"):
        parse_response(f"command_delay_s=0:{MAX_COMMAND_DELAY_S + 0.5:g}", base)
    dyn, rng = KinematicDynamics(64), np.random.default_rng(0)
    dyn.randomize(np.arange(64), drawn, rng)
    delays = dyn.response["command_delay_s"]
    assert 0.0 <= delays.min() < 0.05 and 0.15 < delays.max() <= 0.2
    # Off draws nothing: the same generator then draws the same lags as before the field existed.
    a, b = KinematicDynamics(8), KinematicDynamics(8)
    a.randomize(np.arange(8), KinematicRandomization(), np.random.default_rng(3))
    b.randomize(np.arange(8), drawn, np.random.default_rng(3))
    np.testing.assert_array_equal(a.response["tau_horizontal_s"], b.response["tau_horizontal_s"])


def test_swarm_test_response_reaches_the_simulator(tmp_path):
    """``swarm_test --response``: the drawn responses fly (slower UAVs need longer), the JSON records them,
    and the options that cannot go with it are refused in one line."""
    from sitl.eval.cli import main
    from sitl.eval.evaluate import EvalSettings, evaluate_method
    from sitl.eval.methods import resolve_method
    from sitl.sim.config import ScenarioConfig

    scenario = ScenarioConfig(name="circle", circle_radius_m=6.0)
    settings = EvalSettings(scenario=scenario, num_uavs=2, episodes=4, record_paths=False)
    slow = dataclasses.replace(settings, response=parse_response("tau_horizontal_s=1.5,drag_horizontal_per_s=0.8",
                                                                 nominal_ranges()))
    straight = resolve_method("straight")
    nominal, drawn = (evaluate_method(straight, s, progress=False) for s in (settings, slow))
    assert np.mean([r.duration_s for r in drawn.records]) > np.mean([r.duration_s for r in nominal.records]) + 1.0
    assert "response tau_horizontal_s=1.5" in slow.describe()

    out = tmp_path / "run"
    rc = main(["--policy", "straight", "--n", "2", "--radius", "6", "--altitude", "8", "--scatter", "1", "--episodes",
               "2", "--response", "px4-sih", "--no-reference", "--plot-episodes", "0", "--no-progress", "--out", str(out)])
    assert rc == 0
    data = json.loads(next(out.glob("*.json")).read_text())
    assert data["settings"]["response"]["tau_horizontal_s"] == list(RESPONSE_PRESETS["px4-sih"]["tau_horizontal_s"])
    assert data["settings"]["scenario"]["circle_alt_m"] == 8 and data["settings"]["scenario"]["circle_scatter_m"] == 1
    for argv, why in [(["--response", "px4-sih", "--dynamics", "jsbsim"], "kinematic backend"),
                      (["--scenario", "random", "--scatter", "1"], "shape the circle")]:
        run = subprocess.run([sys.executable, "-m", "sitl.swarm_test", *argv], cwd=ROOT, capture_output=True, text=True,
                             timeout=60)
        assert run.returncode == 2 and why in run.stderr and "Traceback" not in run.stderr


def test_train_response_widens_training_dynamics_only():
    """``sitl.train --response``: training worlds draw the named ranges over KinematicRandomization's; validation
    flies the nominal vehicle; it needs --randomize-dynamics."""
    from sitl.learn.config import TrainConfig, make_sim_config

    cfg = TrainConfig(preset="flown-fast", geometry="flown", scenario="mixed", randomize_dynamics=True,
                      response="tau_horizontal_s=0.15:1,drag_horizontal_per_s=0:0.8")
    train = make_sim_config(cfg, 1).dynamics_randomization
    assert train.tau_horizontal_s == (0.15, 1.0) and train.drag_horizontal_per_s == (0.0, 0.8)
    assert train.max_acc_horizontal_m_s2 == KinematicRandomization().max_acc_horizontal_m_s2
    assert make_sim_config(cfg, 1, scenario_name="circle").dynamics_randomization is None
    with pytest.raises(ValueError, match="needs randomize_dynamics"):
        TrainConfig(response="px4-sih")
    with pytest.raises(ValueError, match="expected a preset"):
        TrainConfig(randomize_dynamics=True, response="px5")


def test_flown_cell_keys_without_a_response_are_unchanged():
    """Stored flown cells (keyed before --response existed) are still reused: a nominal cell's key has no
    ``response``."""
    from sitl.eval.flown import _cell_key, flown_cells
    from sitl.eval.methods import resolve_method

    for cell in flown_cells(episodes=2, jsbsim=False):
        key = _cell_key(cell, resolve_method("straight"))
        assert ("response" in key["settings"]) == (cell.settings.response is not None)
        if cell.name == "circle-n8-px4-sih":  # stored before the command delay existed: its key has none
            assert "command_delay_s" not in key["settings"]["response"]
        if cell.name == "random-medium-delay":
            assert key["settings"]["response"]["command_delay_s"] == [0.0, 0.2]
