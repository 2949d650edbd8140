"""``python -m sitl.swarm_test``: metrics, the ORCA reference, plots, the paper run, argument errors.

Everything runs tiny settings (a few episodes, small swarms, a 16x16 contract policy) so the
file stays well under a minute.
"""

from __future__ import annotations

import importlib.util
import json
import math
import platform
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from companion.spec import DEFAULT_ACTION_SPEC, CameraSpec
from sitl.eval import cli as swarm_test
from sitl.sim.config import ScenarioConfig
from sitl.sim.metrics import UAVRecord, summarize
from sitl.eval.orca import OrcaParams, velocity_to_action
from sitl.eval.cli import main
from sitl.eval.evaluate import EvalSettings, evaluate_method
from sitl.eval.methods import resolve_method
from sitl.eval.paper import paper_cells, run_cell, run_paper
from sitl.eval.report import collision_rate, markdown_table
from sitl.sim.scenarios import EVAL_SEED_OFFSET


# The RVO2-3D binding has wheels for Linux x86_64 only (a pyproject dependency there); elsewhere
# the ORCA tests are skipped when it is not installed.
needs_rvo = pytest.mark.skipif(
    importlib.util.find_spec("rvo23d") is None
    and not (sys.platform.startswith("linux") and platform.machine() == "x86_64"),
    reason="jt-pyrvo23d (RVO2-3D) has no wheel for this platform")


@pytest.fixture(scope="module")
def contract_policy(tmp_path_factory) -> Path:
    """A small untrained policy that follows the policy-file contract (16x16 depth)."""
    from sitl.learn.agent import AgentConfig, SacAeAgent
    from sitl.learn.export import export_policy

    torch.manual_seed(0)
    torch.set_num_threads(1)
    agent = SacAeAgent(AgentConfig(hidden_dim=32), CameraSpec(width=16, height=16), DEFAULT_ACTION_SPEC)
    path = tmp_path_factory.mktemp("policy") / "policy.pt"
    export_policy(agent, path, 0.1, {"method": "sac_ae", "note": "untrained test policy"})
    return path


def test_eval_seeds_are_the_test_seeds():
    assert EvalSettings(seed=3).env_seed == EVAL_SEED_OFFSET + 3


# --------------------------------------------------------------------------- metrics

def _record(outcome: str, path_len: float, straight: float, duration: float, episode: int = 0, uav: int = 0):
    return UAVRecord(episode=episode, uav=uav, start_ned=[0.0, 0.0, -10.0], goal_ned=[straight, 0.0, -10.0],
                     outcome=outcome, path_length_m=path_len, straight_distance_m=straight, duration_s=duration)


def test_metrics_and_table_on_scripted_records():
    records = [_record("arrived", 12.0, 10.0, 6.0, uav=0), _record("collision_uav", 3.0, 10.0, 2.0, uav=1),
               _record("collision_ground", 4.0, 10.0, 4.0, uav=2), _record("timeout", 10.0, 10.0, 40.0, uav=3)]
    summary = summarize(records)
    assert summary["success_rate"] == 0.25
    assert summary["spl"] == pytest.approx((10.0 / 12.0) / 4)
    assert summary["extra_distance_m"]["mean"] == pytest.approx(2.0)
    assert summary["average_speed_m_s"]["mean"] == pytest.approx(np.mean([2.0, 1.5, 1.0, 0.25]))
    assert collision_rate(summary) == pytest.approx(0.75)
    table = markdown_table(["method"], [(["scripted"], summary), (["cnn"], None)])
    lines = table.splitlines()
    assert len(lines) == 4 and lines[0].startswith("| method | success (± 95% CI) | collision")
    assert "| scripted | 0.250 | 0.750 / 0.250 / 0.250 / 0.250 | 0.208 | 2.00 ± 0.00 | 1.19 ± 0.65 |" == lines[2]
    assert lines[3].startswith("| cnn | not trained |")


def test_success_interval_is_clustered_by_episode():
    """1 of 4 arrive in one episode, 3 of 4 in the other: SE = sqrt(2 * ((1-2)^2 + (3-2)^2)) / 8 = 0.25."""
    records = [_record("arrived" if u < arrivals else "collision_uav", 10.0, 10.0, 5.0, episode=e, uav=u)
               for e, arrivals in ((0, 1), (1, 3)) for u in range(4)]
    summary = summarize(records)
    assert summary["success_rate"] == 0.5
    assert summary["success_ci95_half_width"] == pytest.approx(1.96 * 0.25)
    assert "| two | 0.500 ± 0.490 |" in markdown_table(["method"], [(["two"], summary)])
    # Episodes that all end alike leave no spread between episodes; one episode has no interval.
    same = [_record("arrived" if u < 2 else "timeout", 10.0, 10.0, 5.0, episode=e, uav=u)
            for e in range(3) for u in range(4)]
    assert summarize(same)["success_ci95_half_width"] == pytest.approx(0.0)
    assert math.isnan(summarize(same[:4])["success_ci95_half_width"])


def test_metrics_of_a_flown_trajectory_match_its_recorded_path():
    """One UAV flying straight in the random scene: the record's length, SPL and speed follow its path."""
    settings = EvalSettings(scenario=ScenarioConfig(name="random"), num_uavs=1, episodes=3, seed=5)
    result = evaluate_method(resolve_method("straight"), settings, progress=False)
    assert len(result.records) == 3 and result.summary["success_rate"] == 1.0
    for rec in result.records:
        xyz = np.asarray(rec.path_ned)
        assert len(xyz) == round(rec.duration_s / 0.1) + 1  # start + one point per control step
        assert rec.path_length_m == pytest.approx(np.linalg.norm(np.diff(xyz, axis=0), axis=1).sum(), abs=0.02)
        assert np.linalg.norm(xyz[-1] - rec.goal_ned) < 0.5  # arrived within the arrival radius
    expected_spl = np.mean([r.straight_distance_m / max(r.path_length_m, r.straight_distance_m)
                            for r in result.records])
    assert result.summary["spl"] == pytest.approx(expected_spl)


def test_episodes_do_not_depend_on_how_many_fly_at_once():
    """More episodes than parallel worlds: finished worlds start the next ones, same episodes either way."""
    method = resolve_method("straight")
    results = [evaluate_method(method, EvalSettings(scenario=ScenarioConfig(name="random"), num_uavs=3, episodes=5,
                                                    batch_worlds=batch), progress=False) for batch in (2, 5)]
    keys = [sorted((r.episode, r.uav, r.outcome, round(r.path_length_m, 9)) for r in res.records) for res in results]
    assert len(keys[0]) == 15 and {k[0] for k in keys[0]} == set(range(5))
    assert keys[0] == keys[1]


# --------------------------------------------------------------------------- ORCA

def test_orca_velocity_maps_onto_the_command_limits():
    params = OrcaParams()
    yaw = np.zeros(4)  # facing north
    vel = np.array([[1.5, 0.0, 0.0],  # ahead
                    [0.0, 1.0, 0.0],  # to the right (east)
                    [-2.0, 0.0, 0.0],  # behind
                    [1.0, 0.0, -2.0]])  # ahead and climbing fast
    action = velocity_to_action(vel, yaw, params)
    np.testing.assert_allclose(action[0], [1.5, 0.0, 0.0], atol=1e-6)
    assert action[1, 0] == pytest.approx(0.0, abs=1e-6) and action[1, 2] == pytest.approx(0.5)  # turn right
    assert action[2, 0] == 0.0 and abs(action[2, 2]) == pytest.approx(0.5)  # never backwards: turn
    np.testing.assert_allclose(action[3], [1.0, -0.5, 0.0], atol=1e-6)  # climb clipped to 0.5 m/s
    assert np.all(action >= DEFAULT_ACTION_SPEC.low_array()) and np.all(action <= DEFAULT_ACTION_SPEC.high_array())


@needs_rvo
def test_orca_fov_avoids_only_the_uavs_its_camera_covers():
    """Head-on the two UAVs see each other and both give way; one closing in from behind is
    invisible to the UAV ahead, which then keeps its preferred velocity (full ORCA does not)."""
    from companion.spec import REALSENSE_D435
    from sitl.eval.orca import OrcaController

    # UAV 0 flies north at 1.5 m/s towards its goal 1 m ahead (preferred: 1 m/s, slowing down for
    # it); UAV 1 comes south at it from 3 m ahead
    # (0.1 m aside: an exactly head-on pair is degenerate for RVO2-3D, which then does nothing);
    # UAV 2 closes in from 2 m behind at 2 m/s. All at 5 m altitude (NED down = -5).
    pos = np.array([[0.0, 0.0, -5.0], [3.0, 0.1, -5.0], [-2.0, 0.05, -5.0]])
    vel = np.array([[1.5, 0.0, 0.0], [-1.5, 0.0, 0.0], [2.0, 0.0, 0.0]])
    goal = np.array([[1.0, 0.0, -5.0], [-20.0, 0.1, -5.0], [20.0, 0.05, -5.0]])
    yaw = np.array([0.0, math.pi, 0.0])

    def solve(camera, rows):
        ctl = OrcaController(1, 3, 0.3, 0.1, camera=camera)
        known = np.zeros(3, dtype=bool)
        known[rows] = True  # the others are removed from the world
        return ctl.new_velocities(pos, vel, goal, known, known, yaw)

    pref = np.array([[1.0, 0.0, 0.0], [-2.0, 0.0, 0.0], [2.0, 0.0, 0.0]])  # at the goal, cruise, cruise
    ahead = solve(REALSENSE_D435, [0, 1])
    assert np.linalg.norm(ahead[0] - pref[0]) > 0.1 and np.linalg.norm(ahead[1] - pref[1]) > 0.1  # both give way
    behind_fov, behind_all = solve(REALSENSE_D435, [0, 2]), solve(None, [0, 2])
    np.testing.assert_allclose(behind_fov[0], pref[0], atol=1e-3)  # UAV 2 is behind UAV 0's camera
    assert np.linalg.norm(behind_all[0] - pref[0]) > 0.1  # privileged ORCA makes room for it
    assert np.linalg.norm(behind_fov[2] - pref[2]) > 0.01  # UAV 2 sees UAV 0 ahead and (expecting help) slows a little


@needs_rvo
def test_orca_fov_memory_keeps_what_it_saw_and_look_around_adds_the_ring_at_the_start():
    """UAV 0 looks north. UAV 1 starts in view ahead and then passes behind it; UAV 2 is behind it from the
    start; UAV 3 is straight above (outside the D435's +-29 deg even all around). orca-fov knows only what is
    in view now, orca-fov-memory keeps UAV 1 once seen, orca-fov-look-around also knows UAV 2 from the first
    step; nobody knows UAV 3; a new episode forgets everything."""
    from types import SimpleNamespace

    from companion.spec import REALSENSE_D435
    from sitl.eval.orca import LOOK_AROUND_PARAMS, MEMORY_PARAMS, OrcaController, OrcaParams

    def env_at(uav1_north_m: float, step: int):
        pos = np.array([[0.0, 0.0, -5.0], [uav1_north_m, 0.0, -5.0], [-3.0, 0.0, -5.0], [0.0, 0.0, -7.0]])
        return SimpleNamespace(num_worlds=1, world_steps=np.array([step]),
                               dynamics=SimpleNamespace(pos_ned=pos, yaw_rad=np.zeros(4)))

    def knowledge(params: OrcaParams) -> list[list[bool]]:
        ctl = OrcaController(1, 4, 0.3, 0.1, params=params, camera=REALSENSE_D435)
        return [ctl._remembered(env_at(north, step))[0, 1:].tolist()
                for north, step in ((3.0, 0), (-2.0, 1), (-2.0, 2), (-2.0, 0))]  # UAV 1 ahead, behind x2, new episode

    assert knowledge(OrcaParams()) == [[True, False, False], [False, False, False], [False, False, False],
                                       [False, False, False]]
    assert knowledge(MEMORY_PARAMS) == [[True, False, False], [True, False, False], [True, False, False],
                                        [False, False, False]]
    assert knowledge(LOOK_AROUND_PARAMS) == [[True, True, False], [True, True, False], [True, True, False],
                                             [True, True, False]]  # the new episode's first step looks around again
    assert knowledge(OrcaParams(memory_s=0.15)) == [[True, False, False], [True, False, False],
                                                    [False, False, False], [False, False, False]]  # 0.1 s yes, 0.2 s no
    with pytest.raises(ValueError, match="memory_s"):
        OrcaParams(memory_s=-1.0)


@needs_rvo
def test_orca_fov_memory_runs_as_a_reference_and_reports_its_settings():
    """``--policy orca-fov-memory`` and ``orca-fov-look-around`` fly episodes like any reference; the infinite
    memory is written as null (JSON has no infinity)."""
    settings = EvalSettings(scenario=ScenarioConfig(name="random", density=0.06), num_uavs=8, episodes=4,
                            camera="realsense_d435")
    for name, look in (("orca-fov-memory", False), ("orca-fov-look-around", True)):
        method = resolve_method(name)
        info = json.loads(json.dumps(method.info(), allow_nan=False))
        assert info["orca"]["memory_s"] is None and info["orca"]["look_around"] is look
        summary = evaluate_method(method, settings, progress=False).summary
        assert summary["episodes"] == 4 and 0.0 <= summary["success_rate"] <= 1.0


def test_keep_right_turns_only_towards_uavs_ahead_that_close_in():
    """The right-of-way rule turns the preferred velocity right (NED: north -> east) for a UAV closing in
    ahead, and leaves it alone for one ahead that flies away, one behind, or one not known."""
    from sitl.eval.orca import keep_right

    pos = np.array([[0.0, 0.0, -5.0], [5.0, 0.0, -5.0]])
    pref = np.array([[2.0, 0.0, 0.0], [-2.0, 0.0, 0.0]])
    known = np.ones((2, 2), dtype=bool)
    angle = math.radians(40.0)
    head_on = keep_right(pref, pos, np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]), known, angle)
    np.testing.assert_allclose(head_on[0], [2 * math.cos(angle), 2 * math.sin(angle), 0.0], atol=1e-9)  # veers east
    np.testing.assert_allclose(head_on[1], [-2 * math.cos(angle), -2 * math.sin(angle), 0.0], atol=1e-9)  # its right: west
    apart = keep_right(pref, pos, np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), known, angle)
    np.testing.assert_allclose(apart, pref)  # opening: no conflict
    unknown = keep_right(pref, pos, np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]), ~known, angle)
    np.testing.assert_allclose(unknown, pref)  # out of view: no conflict
    same_way = keep_right(np.array([[2.0, 0.0, 0.0], [2.0, 0.0, 0.0]]), pos,
                          np.array([[2.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), known, angle)
    assert same_way[0, 1] > 0 and same_way[1, 1] == 0  # UAV 0 closes on UAV 1 ahead; UAV 1 has it behind


@needs_rvo
def test_orca_fov_right_flies_the_circle_that_orca_fov_does_not():
    """Eight UAVs on a 10 m circle, each camera-limited: plain orca-fov collides in the centre in some
    episodes, the right-of-way rule makes them all arrive (a roundabout)."""
    settings = EvalSettings(scenario=ScenarioConfig(name="circle", circle_radius_m=10.0, circle_jitter_m=0.5),
                            num_uavs=8, episodes=6, camera="realsense_d435")
    plain = evaluate_method(resolve_method("orca-fov"), settings, progress=False).summary
    right = evaluate_method(resolve_method("orca-fov-right"), settings, progress=False).summary
    assert right["success_rate"] == 1.0
    assert plain["success_rate"] < 0.9


@needs_rvo
def test_the_wider_roundabout_holds_where_starts_scatter():
    """Eight camera-limited UAVs on a 12 m circle whose starts are scattered within 3 m of the ring: pairs meet
    one at a time and neighbours close in from outside the view; turning 80 deg (orca-fov-right80) keeps more of
    them apart than 40 deg (orca-fov-right) on the same episodes."""
    settings = EvalSettings(scenario=ScenarioConfig(name="circle", circle_radius_m=12.0, circle_scatter_m=3.0),
                            num_uavs=8, episodes=20, camera="realsense_d435")
    narrow = evaluate_method(resolve_method("orca-fov-right"), settings, progress=False).summary
    wide = evaluate_method(resolve_method("orca-fov-right80"), settings, progress=False).summary
    assert wide["success_rate"] >= narrow["success_rate"] + 0.05


def _orca_pole_run(see_obstacles: bool, camera_limited: bool = False) -> tuple[str, float]:
    """One UAV flying ORCA to its goal 10 m north, through a 0.2 m pole: its outcome and closest approach."""
    from sitl.eval.orca import orca_actor
    from tests.sim_helpers import pole_world

    env, obs = pole_world(pole_east_m=0.05)  # exactly head-on is degenerate for RVO2-3D
    act = orca_actor(env, camera_limited=camera_limited, see_obstacles=see_obstacles)
    closest = math.inf
    for _ in range(300):
        obs, _, term, trunc, _ = env.step(act(obs))
        closest = min(closest, float(np.hypot(env.dynamics.pos_ned[0, 0], env.dynamics.pos_ned[0, 1] - 0.05)))
        if term[0] or trunc[0]:
            break
    return env.finish()[0].outcome, closest


@needs_rvo
def test_orca_that_sees_obstacles_flies_round_a_pole_the_plain_one_hits():
    """The distill method's teacher: the UAV's nearest obstacle point stands in RVO2-3D as a static agent."""
    assert _orca_pole_run(see_obstacles=False)[0] == "collision_obstacle"
    outcome, closest = _orca_pole_run(see_obstacles=True)
    assert outcome == "arrived" and closest > 0.2 + 0.3  # never touched: the pole's radius plus R


@needs_rvo
def test_camera_limited_orca_that_sees_obstacles_flies_round_a_pole_too():
    """``--teacher-camera-limited``'s teacher: orca-fov (each UAV solved alone, knowing the UAVs in view)
    with its own nearest obstacle point loaded."""
    assert _orca_pole_run(see_obstacles=False, camera_limited=True)[0] == "collision_obstacle"
    outcome, closest = _orca_pole_run(see_obstacles=True, camera_limited=True)
    assert outcome == "arrived" and closest > 0.2 + 0.3


@needs_rvo
def test_orca_solves_the_circle_of_eight_without_collision():
    settings = EvalSettings(scenario=ScenarioConfig(name="circle"), num_uavs=8, episodes=4, seed=1)
    orca = evaluate_method(resolve_method("orca"), settings, progress=False)
    assert orca.summary["success_rate"] == 1.0
    assert orca.summary["collision_uav_rate"] == 0.0 and orca.summary["timeout_rate"] == 0.0
    for episode in range(settings.episodes):
        paths = [np.asarray(r.path_ned) for r in orca.records if r.episode == episode]
        steps = min(len(p) for p in paths)
        xyz = np.stack([p[:steps] for p in paths], axis=1)  # [T, N, 3]
        gaps = np.linalg.norm(xyz[:, :, None] - xyz[:, None], axis=3) + np.eye(8) * 1e9
        assert gaps.min() > 2 * 0.3  # centres never within 2R
    # The same episodes flown without avoidance collide: the test exercises avoidance.
    straight = evaluate_method(resolve_method("straight"), settings, progress=False)
    assert straight.summary["collision_uav_rate"] > 0.5


# --------------------------------------------------------------------------- the command

def test_command_writes_figures_and_json(tmp_path):
    out, extra = tmp_path / "run", tmp_path / "metrics_copy.json"
    code = main(["--policy", "straight", "--n", "4", "--episodes", "2", "--out", str(out), "--json", str(extra),
                 "--plot-episodes", "2", "--no-progress"])
    assert code == 0
    import matplotlib.image as mpimg

    for name in ("trajectories.png", "trajectories_ep1.png"):
        png = out / name
        assert png.is_file() and png.stat().st_size > 20_000
        assert mpimg.imread(png)[..., :3].std() > 0.05  # not a blank canvas
    data = json.loads((out / "metrics.json").read_text())
    assert data == json.loads(extra.read_text())
    assert data["method"]["label"] == "straight" and data["references"] == {}  # straight is its own reference
    assert data["settings"]["eval_seed"] == EVAL_SEED_OFFSET
    assert set(data["summary"]) >= {"success_rate", "spl", "extra_distance_m", "average_speed_m_s",
                                    "collision_uav_rate", "collision_ground_rate", "timeout_rate"}
    assert data["collision_rate"] == pytest.approx(1 - data["summary"]["success_rate"])
    assert len(data["records"]) == 8 and all(len(r["path_ned"]) > 10 for r in data["records"])


def test_policy_file_flies_with_its_own_camera_and_the_reference_beside_it(tmp_path, contract_policy, capsys):
    out = tmp_path / "run"
    code = main(["--policy", str(contract_policy), "--n", "3", "--episodes", "2", "--out", str(out),
                 "--max-steps", "30", "--threads", "1", "--no-progress", "--plot-episodes", "0"])
    assert code == 0
    data = json.loads((out / "metrics.json").read_text())
    assert data["config"]["camera"]["width"] == 16 and data["config"]["camera"]["height"] == 16
    assert data["method"]["kind"] == "policy" and data["method"]["label"] == "sac_ae"
    assert list(data["references"]) == ["straight"]
    assert data["references"]["straight"]["summary"]["uav_episodes"] == 6
    printed = capsys.readouterr().out
    assert "| sac_ae |" in printed and "| straight |" in printed


def test_circle_heading_flies_the_swarm_on_one_heading(tmp_path, capsys):
    """``--circle-heading common``: the first episode's layout is the default's, the swarm starting on one heading,
    which the settings and the printed description name."""
    code = main(["--policy", "straight", "--circle-heading", "common", "--episodes", "3", "--out", str(tmp_path / "c"),
                 "--plot-episodes", "0", "--no-progress"])
    assert code == 0
    data = json.loads((tmp_path / "c" / "metrics.json").read_text())
    assert data["settings"]["scenario"]["circle_heading"] == "common"
    assert "circle r=12 m at 10 m, facing common" in capsys.readouterr().out
    assert main(["--policy", "straight", "--episodes", "3", "--out", str(tmp_path / "g"), "--plot-episodes", "0",
                 "--no-progress"]) == 0
    goal = json.loads((tmp_path / "g" / "metrics.json").read_text())
    first = [(a, b) for a, b in zip(data["records"], goal["records"]) if a["episode"] == 0]  # later ones: new draws
    assert len(first) == 8
    for a, b in first:
        assert a["start_ned"] == b["start_ned"] and a["goal_ned"] == b["goal_ned"]
    assert any(a["path_ned"][5] != b["path_ned"][5] for a, b in first)  # the same layout, flown from other headings


@pytest.mark.parametrize("argv, message", [
    (["--n", "0"], "must be >= 1"),
    (["--circle-heading", "north"], "invalid choice"),
    (["--episodes", "many"], "expected an integer"),
    (["--scenario", "square"], "invalid choice"),
    (["--policy", "straight", "--density", "huge"], "unknown density 'huge'"),
    (["--policy", "straight", "--radius", "-3"], "must be a finite number > 0"),
    (["--dynamics", "warp"], "invalid choice"),
    (["paper", "--policies", "dqn=x.pt"], "unknown method 'dqn'"),
    (["paper", "--ns", "8,zero"], "comma-separated integers"),
])
def test_bad_arguments_give_clear_errors(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_missing_or_invalid_policy_files_are_named(tmp_path, monkeypatch, capsys):
    missing = tmp_path / "models" / "policy.pt"
    monkeypatch.setattr(swarm_test, "DEFAULT_POLICY", missing)
    with pytest.raises(SystemExit):
        main([])  # the default policy file
    err = capsys.readouterr().err
    assert str(missing) in err and "--policy straight" in err and "--policy orca" in err and "--policy PATH" in err
    junk = tmp_path / "junk.pt"
    junk.write_text("not a model")
    with pytest.raises(SystemExit):
        main(["--policy", str(junk)])
    err = capsys.readouterr().err
    assert str(junk) in err and "not a TorchScript" in err


def test_impossible_scenario_is_reported(capsys):
    code = main(["--policy", "straight", "--scenario", "random", "--density", "5", "--episodes", "1", "--no-progress"])
    assert code == 2
    assert "cannot build the scenario" in capsys.readouterr().err


# --------------------------------------------------------------------------- paper

@needs_rvo
def test_paper_run_is_resumable_and_reports_untrained_methods(tmp_path, contract_policy, capsys):
    policies = {"sac_ae": contract_policy, "cnn": tmp_path / "no_cnn.pt", "vae": tmp_path / "no_vae.pt"}
    table, fig6 = paper_cells(episodes=1, seed=0, dynamics="kinematic", camera_noise=False, max_steps=40, batch=1,
                              policy_paths=policies, table_n=3, densities=["medium"], ns=[3, 4], radius=6.0,
                              table_episodes=2)
    assert [c.method for c in table] == ["sac_ae", "cnn", "vae", "orca", "straight"]
    assert {c.settings.episodes for c in table} == {2} and {c.settings.episodes for c in fig6} == {1}
    assert [(c.settings.num_uavs, c.method) for c in fig6][:4] == [(3, "sac_ae"), (3, "vae"), (3, "orca"),
                                                                    (3, "straight")]
    out = tmp_path / "paper"
    first = run_paper(out, table, fig6, progress=False, policy_paths=policies)
    assert first["status"]["table2-medium-cnn"] == "not trained"
    assert first["status"]["table2-medium-orca"] == "computed"
    assert sum(s == "computed" for s in first["status"].values()) == 3 + 6
    cell = json.loads((out / "cells" / "fig6-n4-orca.json").read_text())
    assert cell["summary"]["uav_episodes"] == 4 and cell["key"]["num_uavs"] == 4
    assert json.loads((out / "cells" / "table2-medium-orca.json").read_text())["summary"]["uav_episodes"] == 6
    assert (out / "fig6_scaling.png").stat().st_size > 10_000
    assert (out / "trajectories" / "fig6-n3-sac_ae.png").is_file()
    md = (out / "paper.md").read_text()
    assert "## Table II" in md and "| medium | cnn | not trained |" in md and "## Fig. 6" in md
    mtime = (out / "cells" / "fig6-n4-orca.json").stat().st_mtime_ns

    # The command line with the same settings reuses every stored cell.
    code = main(["paper", "--out", str(out), "--episodes", "1", "--table-episodes", "2", "--max-steps", "40",
                 "--batch", "1",
                 "--policies", ",".join(f"{m}={p}" for m, p in policies.items()), "--table-n", "3",
                 "--densities", "medium", "--ns", "3,4", "--radius", "6", "--threads", "1", "--no-progress"])
    assert code == 0
    assert "0 computed, 9 reused, 4 not trained" in capsys.readouterr().out
    assert (out / "cells" / "fig6-n4-orca.json").stat().st_mtime_ns == mtime
    # Other settings are a different cell: it is computed again, not reused.
    changed = [c for c in fig6 if c.name == "fig6-n4-orca"][0]
    changed.settings = EvalSettings(**{**changed.settings.__dict__, "seed": 1})
    assert run_cell(changed, out, progress=False)[1] == "computed"
    assert not math.isnan(json.loads((out / "cells" / "fig6-n4-orca.json").read_text())["summary"]["spl"])


def test_episode_defaults_differ_for_mavlink_and_paper():
    """In-process runs and Fig. 6 fly 100 episodes by default, Table II 500; a real-time MAVLink run 10."""
    assert swarm_test.parse_args([]).episodes == 100
    assert swarm_test.parse_args(["--mavlink"]).episodes == 10
    assert swarm_test.parse_paper_args([]).episodes == 100
    assert swarm_test.parse_paper_args([]).table_episodes == 500  # Table II's random scenes need the precision
    assert swarm_test.parse_paper_args(["--episodes", "800"]).table_episodes == 800
    assert swarm_test.parse_args(["--mavlink", "--episodes", "3"]).episodes == 3
