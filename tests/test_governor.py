"""The speed governor (companion.governor): its cap, its turn, and the simulator flying it as the companion does."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from companion.governor import GOVERNOR_PRESETS, GovernorSpec, SpeedGovernor
from companion.spec import CAMERA_PRESETS
from sitl.eval.evaluate import EvalSettings, evaluate_method
from sitl.eval.methods import resolve_method
from sitl.sim.baselines import straight_actor
from sitl.sim.config import ScenarioConfig
from sitl.sim.episodes import governed_actor
from tests.sim_helpers import pole_world

CAMERA = CAMERA_PRESETS["realsense_d435"]
FAR = CAMERA.max_range_m


def _frames(fill: float = FAR, k: int = 1) -> np.ndarray:
    return np.full((k, CAMERA.height, CAMERA.width), fill, dtype=np.float32)


def test_a_wall_ahead_caps_the_forward_speed_to_a_stop_before_it():
    gov = SpeedGovernor(CAMERA)
    spec = gov.spec
    walls = np.stack([_frames(d)[0] for d in (FAR, 5.0, 2.0, 1.2, 0.8)])
    nearest, cap = gov.forward_limit(walls)
    assert nearest.tolist() == pytest.approx([FAR, 5.0, 2.0, 1.2, 0.8])
    a, t = spec.brake_acc_m_s2, spec.delay_s
    for d, v in zip(nearest, cap):
        room = max(d - spec.stop_distance_m, 0.0)
        assert v == pytest.approx(-a * t + math.sqrt((a * t) ** 2 + 2 * a * room), rel=1e-5)
        if room > 0:  # from v the vehicle stops within the room: lag distance plus braking distance
            assert v * t + v * v / (2 * a) == pytest.approx(room, rel=1e-4)
    assert cap[0] > 2.0 and cap[-1] == 0.0  # open sky: no cap within the action range; inside the stop distance: stop

    commands = np.array([[2.0, -0.3, 0.1]] * 5, dtype=np.float32)
    out, capped, _, _ = gov.apply(walls, commands)
    assert out[:, 0].tolist() == pytest.approx(np.minimum(2.0, cap).tolist())
    assert capped.tolist() == [False, False, True, True, True]  # from 5 m the cap (3.4 m/s) is above 2 m/s
    assert np.all(out[:, 1] == -0.3)  # climb is the policy's
    assert np.all(commands[:, 0] == 2.0)  # the input is not modified


def test_only_what_lies_in_the_corridor_counts():
    gov = SpeedGovernor(CAMERA)
    # A pole 2 m ahead seen in one column: inside the corridor at the image centre, outside it at the edge.
    x_offset_m = 2.0 * gov.tan_u  # lateral offset of each column's point at 2 m
    centre, edge = int(np.argmin(np.abs(x_offset_m))), 0
    assert abs(x_offset_m[centre]) <= gov.spec.corridor_half_width_m < abs(x_offset_m[edge])
    frames = _frames(k=2)
    frames[0, :, centre] = 2.0
    frames[1, :, edge] = 2.0
    nearest, cap = gov.forward_limit(frames)
    assert nearest[0] == pytest.approx(2.0) and cap[0] < 2.0
    assert nearest[1] == FAR and cap[1] > 2.0  # the corridor shows open sky (no data reads as the range)
    # The ground 1.5 m below fills the lower rows: outside the corridor's height, not an obstacle.
    ground = _frames()
    rows = np.flatnonzero(gov.tan_v > 0)
    ground[0, rows, :] = (1.5 / gov.tan_v[rows])[:, None]
    assert gov.forward_limit(ground)[0][0] == FAR


def test_a_stopped_uav_turns_towards_the_freer_side_unless_the_policy_turns():
    gov = SpeedGovernor(CAMERA)
    frames = _frames(1.1, k=4)  # a wall 1.1 m ahead everywhere: stopped
    half = CAMERA.width // 2
    frames[0, :, :half] = 0.9  # nearer on the left: turn right
    frames[1, :, half:] = 0.9  # nearer on the right: turn left
    commands = np.array([[1.5, 0.0, 0.0], [1.5, 0.0, 0.0], [1.5, 0.0, 0.0], [1.5, 0.0, -0.4]], dtype=np.float32)
    out, capped, _, _ = gov.apply(frames, commands)
    assert capped.all() and np.all(out[:, 0] < 0.5 * 1.5)
    rate = gov.spec.turn_rate_rad_s
    assert out[:, 2].tolist() == pytest.approx([rate, -rate, rate, -0.4])  # a tie turns right; a turning policy keeps its turn
    # A sticky turn holds its direction over the policy's yaw until the corridor is clear.
    sticky = SpeedGovernor(CAMERA, GovernorSpec(release_margin_m=1.0))
    turning = np.array([-1.0], dtype=np.float32)
    for depth, expected in ((1.1, -1.0), (1.9, -1.0), (2.0, 0.0)):
        out, _, _, turning = sticky.apply(_frames(depth), np.array([[1.5, 0.0, 0.4]], dtype=np.float32), turning)
        assert turning[0] == expected and out[0, 2] == pytest.approx(0.4 if expected == 0 else -rate)
    # A cap that leaves more than half the command does not turn.
    out, capped, _, _ = gov.apply(_frames(2.0), np.array([[1.5, 0.0, 0.0]], dtype=np.float32))
    assert capped[0] and out[0, 2] == 0.0


def test_climb_in_view_keeps_the_flight_path_inside_the_vertical_view():
    """``view_climb_margin_deg``: |climb| <= forward * tan(vfov/2 -+ pitch - margin), at least ``blind_climb_m_s``."""

    assert math.isinf(GovernorSpec().view_climb_margin_deg)  # off unless asked
    spec = GOVERNOR_PRESETS["swarm-view"]
    assert spec.view_climb_margin_deg == 5.0 and spec.describe().endswith("vertical view less 5 deg")
    gov = SpeedGovernor(CAMERA, spec)
    steepest = math.tan(math.radians(CAMERA.vertical_fov_deg / 2 - 5.0))  # the D435: 29 - 5 = 24 deg
    commands = np.array([[2.0, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [0.0, -0.5, 0.0], [0.5, 0.1, 0.0]],
                        dtype=np.float32)
    out, _, _, _ = gov.apply(_frames(k=5), commands)
    assert out[:, 1].tolist() == pytest.approx([-0.5, -0.5 * steepest, 0.5 * steepest, -spec.blind_climb_m_s, 0.1])
    assert out[:, 0].tolist() == pytest.approx(commands[:, 0].tolist())  # forward and yaw are the policy's
    # the flight path's angle never leaves the view less the margin (the blind floor aside)
    angle = np.degrees(np.arctan2(np.abs(out[:3, 1]), out[:3, 0]))
    assert np.all(angle <= CAMERA.vertical_fov_deg / 2 - 5.0 + 1e-4)
    # a camera pitched up 10 deg may climb more steeply than it descends
    pitched = SpeedGovernor(dataclasses.replace(CAMERA, mount_pitch_deg=10.0), spec)
    assert pitched.climb_per_forward == pytest.approx(math.tan(math.radians(29 + 10 - 5.0)), rel=1e-3)
    assert pitched.descent_per_forward == pytest.approx(math.tan(math.radians(29 - 10 - 5.0)), rel=1e-3)
    # a policy file that predates the setting reads as trained without it; a new one records it (null: off)
    assert GovernorSpec().to_dict()["view_climb_margin_deg"] is None


def test_the_climb_cap_clips_climb_and_descent_and_nothing_else():
    """``max_climb_m_s``: |down velocity| <= the cap whatever the forward speed; off (inf) unless asked."""

    assert math.isinf(GovernorSpec().max_climb_m_s)
    spec = GOVERNOR_PRESETS["swarm-slow-climb"]
    assert spec == dataclasses.replace(GOVERNOR_PRESETS["swarm"], max_climb_m_s=0.25)
    assert spec.describe().endswith("climb and descend at most 0.25 m/s")
    commands = np.array([[2.0, -0.5, 0.1], [0.0, 0.5, -0.2], [1.0, 0.1, 0.0], [0.5, -0.25, 0.0]], dtype=np.float32)
    out, _, _, _ = SpeedGovernor(CAMERA, spec).apply(_frames(k=4), commands)
    assert out[:, 1].tolist() == pytest.approx([-0.25, 0.25, 0.1, -0.25])
    np.testing.assert_allclose(out[:, [0, 2]], commands[:, [0, 2]])  # forward and yaw untouched
    plain, _, _, _ = SpeedGovernor(CAMERA, GOVERNOR_PRESETS["swarm"]).apply(_frames(k=4), commands)
    assert plain[:, 1].tolist() == pytest.approx(commands[:, 1].tolist())
    assert GovernorSpec().to_dict()["max_climb_m_s"] is None  # JSON has no inf: null is "off"


@pytest.mark.parametrize("field, value", [("stop_distance_m", -1.0), ("brake_acc_m_s2", 0.0),
                                          ("corridor_half_width_m", math.nan)])
def test_bad_settings_are_refused(field, value):
    with pytest.raises(ValueError, match=field):
        GovernorSpec(**{field: value})


def _pole_run(spec: GovernorSpec | None) -> tuple[str, float]:
    """One UAV flying straight at its goal 10 m north through a 0.2 m pole: its outcome and closest approach."""
    env, obs = pole_world()
    act = straight_actor(env)
    if spec is not None:
        act = governed_actor(act, spec, env)
    closest = math.inf
    for _ in range(400):
        obs, _, term, _, _ = env.step(act(obs))
        closest = min(closest, float(np.hypot(*env.dynamics.pos_ned[0, :2])))
        if term[0]:
            break
    return env.finish()[0].outcome, closest


def test_the_governor_keeps_a_straight_flight_off_a_pole_and_a_sticky_turn_takes_it_past():
    assert _pole_run(None)[0] == "collision_obstacle"
    touching = 0.2 + 0.3  # the pole's radius plus the UAV's R
    # Turning afresh each step it stops in front of the pole and dithers: the straight line yaws back
    # at its goal as soon as the corridor clears, and the pole is in the way again.
    outcome, closest = _pole_run(GovernorSpec(release_margin_m=math.inf))
    assert outcome == "timeout" and closest > touching
    # Holding the turn until the corridor is clear, it slides round the pole and arrives.
    outcome, closest = _pole_run(GovernorSpec(release_margin_m=1.0))
    assert outcome == "arrived" and closest > touching


def test_evaluation_flies_a_governed_controller_under_its_own_label():
    method = resolve_method("straight").with_governor(GovernorSpec(release_margin_m=0.5))
    assert method.label == "straight+governor" and method.info()["governor"]["release_margin_m"] == 0.5
    assert GovernorSpec(release_margin_m=math.inf).to_dict()["release_margin_m"] is None  # JSON has no infinity: null
    settings = EvalSettings(scenario=ScenarioConfig(name="circle", circle_radius_m=6.0), num_uavs=2, episodes=4,
                            camera="realsense_d435", max_episode_steps=150)

    def rates(m):
        s = evaluate_method(m, settings, progress=False).summary
        return s["success_rate"], s["collision_uav_rate"], s["timeout_rate"]

    # Two UAVs meeting head-on: the straight line collides; governed afresh each step, both stop and
    # dither nose to nose; with the sticky turn both turn right, pass and arrive.
    assert rates(resolve_method("straight")) == (0.0, 1.0, 0.0)
    assert rates(resolve_method("straight").with_governor(GovernorSpec(release_margin_m=math.inf))) == (0.0, 0.0, 1.0)
    assert rates(method) == (1.0, 0.0, 0.0)


def test_the_named_settings_reach_the_evaluation_and_the_companion_command_line():
    """``--governor`` alone is the default (stop and turn); ``--governor swarm`` stops 0.6 m short and never turns."""
    from companion.cli import build_parser as companion_parser
    from companion.governor import DEFAULT_GOVERNOR
    from sitl.eval.cli import parse_args

    swarm = GOVERNOR_PRESETS["swarm"]
    assert GOVERNOR_PRESETS[DEFAULT_GOVERNOR] == GovernorSpec()
    assert swarm.stop_distance_m == 0.6 and swarm.turn_when_capped_below == 0.0
    assert resolve_method("straight").with_governor(swarm).label == "straight+governor-swarm"
    assert resolve_method("straight").with_governor(GovernorSpec()).label == "straight+governor"
    assert parse_args(["--policy", "straight", "--governor", "--n", "2"]).governor == DEFAULT_GOVERNOR
    assert parse_args(["--policy", "straight", "--governor", "swarm"]).governor == "swarm"
    assert parse_args(["--policy", "straight"]).governor is None
    base = ["--connect", "udp:14540", "--model", "m.pt", "--camera", "sitl:14640"]
    assert companion_parser().parse_args([*base, "--governor"]).governor == DEFAULT_GOVERNOR
    assert companion_parser().parse_args([*base, "--governor", "swarm"]).governor == "swarm"
    from sitl.learn.config import resolve_configs
    from sitl.learn.trainer import flight_governor, train_governor

    assert train_governor(resolve_configs({"governor": True, "governor_setting": "swarm"}, {})[0]) == swarm
    assert train_governor(resolve_configs({"governor": True}, {})[0]) == GovernorSpec()
    assert train_governor(resolve_configs({"governor_setting": "swarm"}, {})[0]) is None
    with pytest.raises(ValueError, match="unknown governor_setting"):
        resolve_configs({"governor_setting": "fast"}, {})
    # The governor the policy flies with (validation, the final choice, policy.json): the training one unless named.
    flown = resolve_configs({"governor": True, "governor_setting": "swarm",
                             "flight_governor_setting": "swarm-slow-climb"}, {})[0]
    assert train_governor(flown) == swarm and flight_governor(flown) == GOVERNOR_PRESETS["swarm-slow-climb"]
    assert flight_governor(resolve_configs({"governor": True, "governor_setting": "swarm"}, {})[0]) == swarm
    assert flight_governor(resolve_configs({}, {})[0]) is None
    with pytest.raises(ValueError, match="unknown flight_governor_setting"):
        resolve_configs({"governor": True, "flight_governor_setting": "fast"}, {})
    with pytest.raises(ValueError, match="needs governor"):
        resolve_configs({"flight_governor_setting": "swarm"}, {})
    # A governor that stops but never turns leaves the policy's yaw alone: nose to nose, nobody passes.
    governor = SpeedGovernor(CAMERA, swarm)
    frame = np.full((1, CAMERA.height, CAMERA.width), 0.8, dtype=np.float32)  # a wall 0.8 m ahead
    out, capped, nearest, turning = governor.apply(frame, np.array([[2.0, 0.0, 0.1]], dtype=np.float32))
    assert capped[0] and out[0, 0] < 0.5 and out[0, 2] == pytest.approx(0.1) and turning[0] == 0


def test_every_help_text_describes_the_settings_from_the_specs_themselves():
    """The words for what a setting does come from its numbers, so a changed preset cannot leave a stale help text."""
    import argparse

    from companion.cli import build_parser as companion_parser
    from companion.governor import GOVERNOR_PRESETS, describe_presets
    from sitl.cli_args import add_governor_flag

    assert GovernorSpec(stop_distance_m=0.7, turn_when_capped_below=0.0).describe() == \
        "stop 0.7 m short in a +-0.35 m corridor, never turn"
    assert GovernorSpec().describe().endswith("turn to the freer side when stopped")
    for name, spec in GOVERNOR_PRESETS.items():
        assert f"{name}: {spec.describe()}" in describe_presets()
    sim_parser = argparse.ArgumentParser()
    add_governor_flag(sim_parser)
    for parser in (companion_parser(), sim_parser):
        help_text = " ".join(next(a.help for a in parser._actions if "--governor" in a.option_strings).split())
        assert describe_presets() in help_text


def test_a_stored_flown_cell_is_reused_only_for_the_same_governor_settings(tmp_path):
    from sitl.eval.flown import flown_cells, run_flown_cell

    cell = next(c for c in flown_cells(episodes=1, batch=1, jsbsim=False) if c.name == "random-small")
    first = resolve_method("straight").with_governor(GovernorSpec())
    other = resolve_method("straight").with_governor(GovernorSpec(stop_distance_m=0.5))
    assert run_flown_cell(cell, first, tmp_path, progress=False)[1] == "computed"
    assert run_flown_cell(cell, first, tmp_path, progress=False)[1] == "stored"
    assert run_flown_cell(cell, other, tmp_path, progress=False)[1] == "computed"  # same label, other settings


def test_a_policy_trained_with_the_governor_carries_it_and_flies_with_it(tmp_path):
    from companion.policy import PolicyFileError, build_metadata, load_policy, save_policy
    from tests.companion_helpers import GoalSeeker, make_policy

    plain = resolve_method(str(make_policy(tmp_path / "plain.pt")))
    assert plain.governor is None and load_policy(plain.path).governor is None
    spec = GovernorSpec(stop_distance_m=1.5, release_margin_m=math.inf)
    governed = resolve_method(str(make_policy(tmp_path / "governed.pt", governor=spec)))
    assert governed.governor == spec and governed.label.endswith("+governor") and governed.trained_with_governor
    assert not plain.trained_with_governor and not resolve_method("straight").with_governor(spec).trained_with_governor
    # --governor on top changes nothing: the file's settings fly, as in the companion
    assert governed.with_governor(GovernorSpec()) is governed
    meta = load_policy(governed.path).metadata
    assert meta["governor"]["release_margin_m"] is None  # JSON has no infinity: null, read back as inf

    def refused(governor) -> str:
        camera = CAMERA_PRESETS["realsense_d435"]
        bad = build_metadata(camera, load_policy(governed.path).action, 0.1, {}) | {"governor": governor}
        path = tmp_path / "bad.pt"
        module = GoalSeeker([0.0, -0.5, -0.5], [2.0, 0.5, 0.5], 0.0, 0.0)
        save_policy(module, bad, path)
        with pytest.raises(PolicyFileError) as err:
            load_policy(path)
        assert "\n" not in str(err.value)
        return str(err.value)

    good = GovernorSpec().to_dict()
    assert "unknown settings ['speed']" in refused(good | {"speed": 1})
    assert "governor stop_distance_m must be a number" in refused(good | {"stop_distance_m": "1"})
    assert "governor delay_s must be a number" in refused({k: v for k, v in good.items() if k != "delay_s"})
    assert "must be a finite number >= 0" in refused(good | {"brake_acc_m_s2": -1.0})
    assert "governor must be a JSON object" in refused([1, 2])
    # a file written before the climb-in-view settings existed names only the first ten: it flies without them
    older = {k: v for k, v in good.items() if k not in ("view_climb_margin_deg", "blind_climb_m_s")}
    camera = CAMERA_PRESETS["realsense_d435"]
    save_policy(GoalSeeker([0.0, -0.5, -0.5], [2.0, 0.5, 0.5], 0.0, 0.0),
                build_metadata(camera, load_policy(governed.path).action, 0.1, {}) | {"governor": older},
                tmp_path / "older.pt")
    assert load_policy(tmp_path / "older.pt").governor == GovernorSpec()


def test_training_with_the_governor_flies_governed_commands_and_exports_the_governor(tmp_path):
    """``sitl.train --governor``: the UAVs fly the governed commands, the replay keeps the policy's own
    (the governor is part of the environment), and the exported file carries the governor it flies with
    (``--flight-governor-setting``: here the climb-capped one, while the rollouts keep the uncapped default)."""
    from companion.policy import load_policy
    from sitl.learn.config import PRESETS, resolve_configs
    from sitl.learn.trainer import make_trainer

    cfg, agent_cfg = resolve_configs(
        {**PRESETS["flown"]["train"], "preset": "flown", "governor": True, "scenario": "mixed",
         "circle_fraction": 0.0, "obstacle_fraction": 1.0, "num_worlds": 2, "total_updates": 2, "init_steps": 600,
         "batch_size": 16, "eval_every_updates": 0, "final_eval_episodes": 0,
         "flight_governor_setting": "swarm-slow-climb"},
        {"hidden_dim": 32})
    trainer = make_trainer(cfg, agent_cfg, tmp_path)
    env, flown = trainer.env, []
    step = env.step

    def record(action):  # what the simulator is asked to fly, per acting UAV, in the replay's order
        flown.append(np.array(action)[env.acting])
        return step(action)

    env.step = record
    trainer.run()
    buf = trainer.buffer
    stored = buf.action[:buf.size]  # the policy's (here the initial random) actions, in [-1, 1]
    flew = trainer.agent.to_unit_action(np.concatenate(flown)[:buf.size])
    assert np.all(flew[:, 0] <= stored[:, 0] + 1e-5)  # the governor only ever lowers the forward speed
    assert np.mean(flew[:, 0] < stored[:, 0] - 1e-3) > 0.01  # ... and did, among obstacles and other UAVs
    assert np.any(np.abs(flew[:, 2] - stored[:, 2]) > 1e-3)  # ... and turned some away
    # climb is never changed: the rollouts fly the training governor, not the flight one's 0.25 m/s cap
    np.testing.assert_array_equal(flew[:, 1], stored[:, 1])
    assert np.any(np.abs(stored[:, 1]) > 0.5 + 1e-3)  # (the random actions climb beyond that cap: 0.5 is 0.25 m/s)
    assert load_policy(tmp_path / "policy.pt").governor == GOVERNOR_PRESETS["swarm-slow-climb"]


def test_the_companion_names_the_governor_it_flies_before_anything_else_can_fail(tmp_path):
    """``companion --governor swarm``: the log says which setting and what it does right after the model,
    so a flight log shows it even when the camera then fails (here a missing replay: exit 4)."""
    import json
    import subprocess
    import sys

    from tests.companion_helpers import REPO, env

    proc = subprocess.run([sys.executable, "-m", "companion.cli", "--connect", "udp:14540", "--model",
                           str(REPO / "models" / "policy.pt"), "--camera", f"replay:{tmp_path / 'none.npz'}",
                           "--governor", "swarm"], cwd=tmp_path, env=env(), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 4, proc.stderr
    events = [json.loads(line) for line in proc.stdout.splitlines()]
    (governor,) = [e for e in events if e.get("event") == "governor"]
    assert governor["setting"] == "swarm" and governor["governor"]["stop_distance_m"] == 0.6
    assert "never turn" in governor["message"]
    assert [e["event"] for e in events].index("governor") < [e["event"] for e in events].index("exit")
