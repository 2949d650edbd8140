"""Face the goal first (``companion.face_goal``): the turn law, the simulator's hold, and the command lines.

The companion's side (the real process over MAVLink) is flown in tests/test_companion_flight.py ("face_goal").
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from companion.face_goal import FaceGoalSpec, face_goal_commands, goal_bearing_frd_rad
from sitl.eval.cli import main
from sitl.eval.evaluate import EvalSettings, sim_config_for
from sitl.eval.methods import resolve_method
from sitl.sim.config import ScenarioConfig
from sitl.sim.env import SwarmEnv
from sitl.sim.episodes import face_goal_actor


def test_the_turn_is_towards_the_goal_and_within_the_yaw_limit():
    pos = np.zeros((4, 3))
    goal = np.array([[10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [0.0, -10.0, 0.0], [10.0, 1.0, -3.0]])
    yaw = np.zeros(4)  # all facing north
    bearing = goal_bearing_frd_rad(pos, yaw, goal)
    assert bearing == pytest.approx([0.0, math.pi / 2, -math.pi / 2, math.atan2(1.0, 10.0)])
    cmd = face_goal_commands(pos, yaw, goal, 0.5, FaceGoalSpec(gain_per_s=2.0))
    assert np.all(cmd[:, :2] == 0.0)  # hold position: no forward speed, no climb, even towards a goal 3 m up
    assert cmd[:, 2] == pytest.approx([0.0, 0.5, -0.5, 2.0 * math.atan2(1.0, 10.0)], abs=1e-6)
    # a vehicle facing east sees a goal to its north on its left
    assert goal_bearing_frd_rad(np.zeros(3), math.pi / 2, np.array([5.0, 0.0, 0.0])) == pytest.approx(-math.pi / 2)


@pytest.mark.parametrize("values, message", [
    ({"hold_s": 0.0}, "hold must be"), ({"hold_s": math.inf}, "hold must be"), ({"gain_per_s": -1.0}, "gain must be")])
def test_bad_settings_are_refused(values, message):
    with pytest.raises(ValueError, match=message):
        FaceGoalSpec(**values)


def test_the_simulated_swarm_turns_in_place_then_flies_together():
    """A circle whose swarm starts on one heading: for the hold every UAV stays where it is and turns to its goal;
    at its end each faces its goal; then the controller's own commands fly."""
    spec = FaceGoalSpec(hold_s=7.0)
    settings = EvalSettings(scenario=ScenarioConfig(name="circle", circle_heading="common"), num_uavs=6, episodes=1)
    env = SwarmEnv(sim_config_for(resolve_method("straight"), settings, num_worlds=1), seed=3)
    obs = env.reset()
    start = env.dynamics.pos_ned.copy()
    assert np.ptp(env.dynamics.yaw_rad) == 0.0  # one heading for the whole swarm
    forward = face_goal_actor(lambda o: np.tile(np.float32([2.0, 0.0, 0.0]), (env.num_agents, 1)), spec, env, 0.5)
    hold_steps = round(spec.hold_s / env.config.control_period_s)
    for _ in range(hold_steps):
        obs, *_ = env.step(forward(obs))
    assert env.acting.all()
    assert np.abs(goal_bearing_frd_rad(env.dynamics.pos_ned, env.dynamics.yaw_rad, env.goal_ned)).max() < math.radians(3)
    assert np.linalg.norm(env.dynamics.pos_ned - start, axis=1).max() < 0.05
    for _ in range(10):
        obs, *_ = env.step(forward(obs))
    assert np.linalg.norm(env.dynamics.pos_ned - start, axis=1).min() > 0.5  # the controller's 2 m/s flies now


def test_swarm_test_face_goal_names_the_hold(tmp_path, capsys):
    """``--face-goal 3``: the controller's label, the default folder and the JSON carry it; straight stays plain."""
    code = main(["--policy", "straight", "--face-goal", "3", "--circle-heading", "common", "--n", "4", "--episodes", "2",
                 "--out", str(tmp_path / "f"), "--plot-episodes", "0", "--no-progress"])
    assert code == 0
    data = json.loads((tmp_path / "f" / "metrics.json").read_text())
    assert data["method"]["label"] == "straight+face-goal" and data["method"]["face_goal"]["hold_s"] == 3.0
    assert "straight+face-goal" in capsys.readouterr().out
    first = [r for r in data["records"] if r["episode"] == 0]
    for r in first:  # 30 steps of turning in place, then flying
        path = np.asarray(r["path_ned"])
        assert np.linalg.norm(path[29] - path[0]) < 0.05 and np.linalg.norm(path[-1] - path[0]) > 5.0


@pytest.mark.parametrize("value", ["0", "-2", "61", "soon"])
def test_bad_hold_gives_one_line(value, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--policy", "straight", "--face-goal", value])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--face-goal must be seconds in (0, 60]" in err and "Traceback" not in err
