"""The task as flown: altitude ranges, circle ranges, start jitter, obstacles, dynamics randomization, the protocol."""

from __future__ import annotations

import json
from itertools import combinations

import numpy as np
import pytest

from sitl.eval.cli import main
from sitl.eval.flown import flown_cells
from sitl.sim.collision import distance_to_obstacles_m
from sitl.sim.config import (FLOWN_ALTITUDE_RANGE_M, OBSTACLE_SCENE_DENSITY, ScenarioConfig, SimConfig,
                             scenario_for)
from sitl.sim.dynamics import KinematicDynamics, KinematicRandomization
from sitl.sim.env import SwarmEnv
from sitl.sim.metrics import UAVRecord, success_by_goal_altitude
from sitl.sim.scenarios import (max_obstacles, obstacle_counts, sample_circle, sample_obstacles, sample_random,
                                sample_scenario)


def test_flown_random_scene_spans_the_altitude_range_with_bounded_jitter():
    cfg = scenario_for("flown", "random")
    rng = np.random.default_rng(0)
    lo, hi = FLOWN_ALTITUDE_RANGE_M
    floors = []
    for _ in range(200):
        s = sample_random(8, cfg, rng)
        for pts in (s.start_ned, s.goal_ned):
            assert np.all((-pts[:, 2] >= lo - 1e-9) & (-pts[:, 2] <= hi + cfg.start_jitter_m + 1e-9))
        assert min(np.linalg.norm(a - b) for a, b in combinations(s.start_ned, 2)) >= cfg.min_separation_m - 1e-9
        floors.append(-s.goal_ned[:, 2].max())
    assert min(floors) < 3.0 and max(floors) > 10.0  # the floor is drawn per episode over the whole range


def test_low_floor_fraction_oversamples_low_goals_in_training_worlds_only():
    from sitl.learn.config import TrainConfig, make_sim_config

    def goal_altitudes(cfg: ScenarioConfig, episodes: int = 400) -> np.ndarray:
        rng = np.random.default_rng(5)
        return np.concatenate([-sample_random(8, cfg, rng).goal_ned[:, 2] for _ in range(episodes)])

    uniform = goal_altitudes(scenario_for("flown", "random"))
    low = goal_altitudes(scenario_for("flown", "random", low_floor_fraction=0.25))
    assert (low < 3.0).mean() > 2.5 * (uniform < 3.0).mean()  # ~3 % -> ~11 % of goals below 3 m
    assert low.max() > 10.0  # the rest still spans the range
    # every floor in the lowest band: the box (3.2 m tall at medium density) ends below lo + 1 m + its height
    lo, _ = FLOWN_ALTITUDE_RANGE_M
    always = goal_altitudes(scenario_for("flown", "random", low_floor_fraction=1.0), 50)
    assert always.min() >= lo - 1e-9 and always.max() <= lo + 1.0 + 3.3
    # 0 draws no extra number: the episodes are those of a config without the field
    a = sample_random(8, scenario_for("flown", "random"), np.random.default_rng(9))
    b = sample_random(8, scenario_for("flown", "random", low_floor_fraction=0.0), np.random.default_rng(9))
    assert np.array_equal(a.goal_ned, b.goal_ned)
    with pytest.raises(ValueError, match="low_floor_fraction"):
        ScenarioConfig(low_floor_fraction=1.5)
    # the paper geometry's floor is fixed: asking for low floors there is an error, not a silent no-op
    with pytest.raises(ValueError, match="needs altitude_range_m"):
        scenario_for("paper", "random", low_floor_fraction=0.25)
    with pytest.raises(ValueError, match="needs altitude_range_m"):
        TrainConfig(low_floor_fraction=0.25)
    # training worlds get it, evaluation worlds (validation, rescoring, tests) fly the uniform draw
    cfg = TrainConfig(preset="flown-fast", geometry="flown", low_floor_fraction=0.25)
    assert make_sim_config(cfg, 1).scenario.low_floor_fraction == 0.25
    assert make_sim_config(cfg, 1, scenario_name="random").scenario.low_floor_fraction == 0.0


def test_density_range_draws_each_random_training_episode_at_its_own_crowding():
    from sitl.learn.config import TrainConfig, make_sim_config, parse_density_range
    from sitl.sim.config import DENSITIES
    from sitl.sim.scenarios import random_box_size

    assert parse_density_range("small,large") == (DENSITIES["large"], DENSITIES["small"])  # sorted
    assert parse_density_range("0.05, medium") == (0.05, DENSITIES["medium"])
    assert parse_density_range("") is None
    for bad, message in (("small", "two densities"), ("small,crowded", "unknown density"), ("0,small", "> 0")):
        with pytest.raises(ValueError, match=message):
            parse_density_range(bad)
    with pytest.raises(ValueError, match="density_range"):
        TrainConfig(density_range="small,crowded")  # a bad flag fails before the run starts
    with pytest.raises(ValueError, match="density_range: at 0.0001 UAV/m.3 the random box .* does not fit"):
        TrainConfig(geometry="flown", density_range="0.0001,small")  # a box taller than 1.5-15 m
    with pytest.raises(ValueError, match="density_range: at 10 UAV/m.3 cannot place"):
        TrainConfig(density_range="small,10")  # UAVs 1 m apart cannot be this crowded
    # the box of each random episode: between the sparse and the dense box, both ends reached
    cfg = scenario_for("flown", "mixed", circle_fraction=0.0, obstacle_fraction=0.0, density_range=(0.04, 0.1))
    rng = np.random.default_rng(0)
    spans = np.array([np.ptp(sample_scenario(8, cfg, rng).goal_ned[:, :2]) for _ in range(300)])
    dense, sparse = random_box_size(8, 0.1, cfg.box_aspect)[0], random_box_size(8, 0.04, cfg.box_aspect)[0]
    assert spans.max() <= sparse + 1e-9 and spans.max() > dense + 0.5  # sparser boxes than the densest
    fixed = scenario_for("flown", "random", density=0.1)
    assert max(np.ptp(sample_random(8, fixed, rng).goal_ned[:, :2]) for _ in range(300)) <= dense + 1e-9
    # without it no extra number is drawn: the episodes are those of a config without the field
    a = sample_scenario(8, scenario_for("flown", "random"), np.random.default_rng(9))
    b = sample_scenario(8, scenario_for("flown", "random", density_range=None), np.random.default_rng(9))
    assert np.array_equal(a.goal_ned, b.goal_ned)
    # training worlds get it; validation, rescoring and tests fly their own density
    train = TrainConfig(preset="flown-fast", density_range="large,small")
    assert make_sim_config(train, 1).scenario.density_range == (0.04, 0.1)
    assert make_sim_config(train, 1, scenario_name="random").scenario.density_range is None


def test_paper_geometry_is_the_default_and_draws_the_same_episodes():
    assert scenario_for("paper", "random") == ScenarioConfig(name="random")
    a = sample_random(8, ScenarioConfig(), np.random.default_rng(3))
    assert np.all(-a.start_ned[:, 2] >= 6.0)  # the paper's 6 m floor, unchanged
    with pytest.raises(ValueError, match="does not fit"):
        sample_random(8, ScenarioConfig(altitude_range_m=(1.5, 3.0)), np.random.default_rng(0))


def test_flown_circle_draws_radius_and_altitude_per_episode():
    cfg = scenario_for("flown", "circle")
    rng = np.random.default_rng(0)
    radii, alts = [], []
    for _ in range(100):
        s = sample_circle(8, cfg, rng)
        r = np.linalg.norm(s.goal_ned[:, :2], axis=1)
        np.testing.assert_allclose(r, r[0])
        radii.append(r[0])
        alts.append(-s.goal_ned[0, 2])
        assert np.all(np.abs(s.start_ned - s.goal_ned * [-1, -1, 1]) <= cfg.circle_jitter_m + 1e-9)
    assert 8.0 <= min(radii) < 10.0 and 18.0 < max(radii) <= 20.0
    assert 2.0 <= min(alts) < 4.0 and 13.0 < max(alts) <= 15.0


def test_circle_start_headings_goal_common_any_and_mixed():
    """``goal`` faces each UAV's goal and draws nothing more (the paper's circle keeps its episodes); ``common``
    gives the swarm one heading per episode, ``any`` each UAV its own, ``mixed`` one of the three per episode;
    the layout itself is the same draw in every case."""
    from sitl.sim.scenarios import _bearing_rad

    draws = {h: [sample_circle(8, scenario_for("flown", "circle", circle_heading=h), np.random.default_rng(k))
                 for k in range(60)] for h in ("goal", "common", "any", "mixed")}
    for k, s in enumerate(draws["goal"]):
        np.testing.assert_allclose(s.yaw_rad, _bearing_rad(s.start_ned, s.goal_ned))
        for h in ("common", "any", "mixed"):
            np.testing.assert_array_equal(draws[h][k].start_ned, s.start_ned)
    common = np.array([s.yaw_rad for s in draws["common"]])
    assert np.all(common == common[:, :1]) and np.ptp(common[:, 0]) > 5.0  # one per episode, spread over the circle
    many = np.array([s.yaw_rad for s in draws["any"]])
    assert np.all(np.ptp(many, axis=1) > 0.5) and many.min() < -2.5 and many.max() > 2.5
    kinds = set()
    for s in draws["mixed"]:
        facing_goal = np.allclose(s.yaw_rad, _bearing_rad(s.start_ned, s.goal_ned))
        kinds.add("goal" if facing_goal else "common" if np.all(s.yaw_rad == s.yaw_rad[0]) else "any")
    assert kinds == {"goal", "common", "any"}
    with pytest.raises(ValueError, match="unknown circle_heading 'north'"):
        scenario_for("flown", "circle", circle_heading="north")


def test_circle_heading_reaches_training_worlds_only():
    from sitl.learn.config import TrainConfig, make_sim_config

    cfg = TrainConfig(preset="flown-fast", geometry="flown", scenario="mixed", circle_heading="common")
    assert make_sim_config(cfg, 1).scenario.circle_heading == "common"
    assert make_sim_config(cfg, 1, scenario_name="circle").scenario.circle_heading == "goal"
    with pytest.raises(ValueError, match="unknown circle_heading"):
        TrainConfig(circle_heading="sideways")


def test_obstacles_keep_clear_of_starts_and_goals():
    cfg = scenario_for("flown", "obstacles", density=OBSTACLE_SCENE_DENSITY)
    rng = np.random.default_rng(1)
    boxes, cylinders = obstacle_counts(8, cfg)
    assert boxes >= 1 and cylinders >= 4
    for _ in range(30):
        s = sample_obstacles(8, cfg, rng)
        assert len(s.boxes) + len(s.cylinders) >= 1
        d = distance_to_obstacles_m(np.concatenate([s.start_ned, s.goal_ned]), s.boxes, s.cylinders)
        assert d.min() >= cfg.obstacle_clearance_m
        assert np.all(s.cylinders[:, 4] == 0.0) and np.all(s.boxes[:, 2] + s.boxes[:, 5] == pytest.approx(0.0))


def test_a_mixed_scenario_draws_its_obstacles_episodes_at_their_own_density():
    """``obstacle_density`` makes training's obstacles episodes the obstacle scene that validation flies:
    its box (line lengths) and its obstacle count; random episodes keep ``density``."""
    scene = scenario_for("flown", "obstacles", density=OBSTACLE_SCENE_DENSITY)
    mixed = scenario_for("flown", "mixed", circle_fraction=0.0, obstacle_fraction=0.5,
                         obstacle_density=OBSTACLE_SCENE_DENSITY)
    plain = scenario_for("flown", "mixed", circle_fraction=0.0, obstacle_fraction=0.5)
    assert max_obstacles(8, mixed) == obstacle_counts(8, scene) != max_obstacles(8, plain)

    def spans(cfg, want_obstacles):
        rng, out = np.random.default_rng(2), []
        while len(out) < 200:
            s = sample_scenario(8, cfg, rng)
            if (len(s.boxes) + len(s.cylinders) > 0) == want_obstacles:
                out.append(np.ptp(s.start_ned[:, :2], axis=0).max())
        return np.mean(out)
    # The box of 8 UAVs is ~8.1 m wide at 0.03 UAV/m^3 and ~6.4 m at medium (0.06).
    assert spans(mixed, True) > 1.15 * spans(plain, True)
    assert spans(mixed, False) == pytest.approx(spans(plain, False), rel=0.05)
    with pytest.raises(ValueError, match="obstacle_density must be > 0"):
        scenario_for("flown", "mixed", obstacle_fraction=0.2, obstacle_density=0.0)


def test_flying_into_a_pole_ends_the_episode_as_an_obstacle_collision():
    # One UAV flies straight at its goal 10 m north; a 0.2 m pole stands half-way.
    cfg = SimConfig(num_uavs=1, scenario=ScenarioConfig(name="random", density=0.01, min_goal_distance_m=0.0))
    pole = np.array([[[0.0, 0.0, 0.2, -30.0, 0.0]]])
    env = SwarmEnv(cfg, seed=0, cylinders=pole)
    env.reset()
    env.dynamics.reset(np.array([0]), np.array([[-5.0, 0.0, -8.0]]), np.array([0.0]))
    env.goal_ned[0] = [5.0, 0.0, -8.0]
    for _ in range(100):
        _, reward, term, _, info = env.step(np.array([[2.0, 0.0, 0.0]]))
        if term[0]:
            break
    assert env.outcome[0] == 5 and reward[0] < cfg.reward.r_collision + 1.0  # the collision penalty (plus progress)
    assert abs(env.dynamics.pos_ned[0, 0]) < 0.6  # stopped at the pole, not behind it
    records = env.finish()
    assert records[0].outcome == "collision_obstacle"
    # Obstacles drawn per episode are rendered: the camera sees something nearer than the range.
    env = SwarmEnv(SimConfig(num_uavs=8, scenario=scenario_for("flown", "obstacles", density=OBSTACLE_SCENE_DENSITY)),
                   seed=0)
    env.reset()
    assert np.any(env.cylinders[0, :, 2] > 0.0) and env.cylinders.shape[1] == obstacle_counts(8, env.config.scenario)[1]


def test_dynamics_randomization_draws_per_uav_and_episode():
    ranges = KinematicRandomization()
    env = SwarmEnv(SimConfig(num_uavs=8, num_worlds=2, dynamics_randomization=ranges), seed=0)
    env.reset()
    tau = env.dynamics.response["tau_horizontal_s"].copy()
    assert np.all((tau >= 0.15) & (tau <= 0.5)) and len(np.unique(tau)) == 16
    acc = env.dynamics.response["max_acc_horizontal_m_s2"]
    assert np.all((acc >= 2.0) & (acc <= 5.0))
    env.reset_worlds(np.array([True, False]))
    assert not np.allclose(env.dynamics.response["tau_horizontal_s"][:8], tau[:8])
    np.testing.assert_array_equal(env.dynamics.response["tau_horizontal_s"][8:], tau[8:])
    nominal = SwarmEnv(SimConfig(num_uavs=8), seed=0)
    nominal.reset()
    assert np.all(nominal.dynamics.response["tau_horizontal_s"] == 0.25)
    # The drawn response is what the UAV flies: a 0.5 s lag is slower to reach speed than 0.15 s.
    d = KinematicDynamics(2)
    d.reset(np.arange(2), np.array([[0.0, 0.0, -10.0], [0.0, 50.0, -10.0]]), np.zeros(2))
    rng = np.random.default_rng(0)
    d.randomize(np.array([0]), KinematicRandomization(tau_horizontal_s=(0.5, 0.5)), rng)
    d.randomize(np.array([1]), KinematicRandomization(tau_horizontal_s=(0.15, 0.15)), rng)
    d.response["max_acc_horizontal_m_s2"][:] = 5.0
    for _ in range(3):
        d.step(np.tile([2.0, 0.0, 0.0], (2, 1)), 0.1, np.ones(2, dtype=bool))
    assert d.vel_ned[0, 0] < d.vel_ned[1, 0] - 0.3
    with pytest.raises(ValueError, match="kinematic backend only"):
        SimConfig(dynamics="jsbsim", dynamics_randomization=ranges)
    with pytest.raises(ValueError, match="0 < low <= high"):
        KinematicRandomization(tau_vertical_s=(0.5, 0.1))


def test_circle_scatter_moves_starts_horizontally_within_its_disc_and_keeps_them_apart():
    """``circle-n8-scatter``: each start lies within the scatter disc (plus the usual jitter) of its point on the ring,
    at the ring's altitude, no two closer than the minimum separation, the goals at the nominal antipodes; without
    scatter the circle draws exactly what it drew before."""
    from sitl.sim.config import FLOWN_CIRCLE_SCATTER_M

    cfg = scenario_for("flown", "circle", circle_scatter_m=FLOWN_CIRCLE_SCATTER_M)
    plain = scenario_for("flown", "circle")
    offsets = []
    for seed in range(200):
        s, p = sample_circle(8, cfg, np.random.default_rng(seed)), sample_circle(8, plain, np.random.default_rng(seed))
        np.testing.assert_allclose(s.goal_ned, p.goal_ned)  # the same ring and goals
        off = np.linalg.norm((s.start_ned - p.start_ned)[:, :2], axis=1)
        assert np.all(off <= FLOWN_CIRCLE_SCATTER_M + 1e-9) and np.allclose(s.start_ned[:, 2], p.start_ned[:, 2])
        assert min(np.linalg.norm(a - b) for a, b in combinations(s.start_ned, 2)) >= cfg.min_separation_m - 1e-9
        offsets += off.tolist()
    assert 1.7 < np.mean(offsets) < 2.3  # a uniform disc of 3 m: mean offset 2 m
    cells = {c.name: c for c in flown_cells(episodes=1, jsbsim=False)}
    assert cells["circle-n8-scatter"].settings.scenario.circle_scatter_m == FLOWN_CIRCLE_SCATTER_M
    assert cells["circle-n8"].settings.scenario.circle_scatter_m == 0.0


def test_pi_loop_against_drag_falls_short_then_catches_up():
    """The optional PX4-like response: a PI velocity loop against linear drag gets only 1 / (1 + kd tau) of a step
    quickly, then its integrator brings the rest; without the integrator the shortfall stays; kd = ki = 0 is the
    plain lag. The integrator starts from zero at every reset."""
    from sitl.sim.dynamics import KinematicParams

    def speeds(**response) -> dict[float, float]:
        d = KinematicDynamics(1, KinematicParams(tau_horizontal_s=1 / 1.2, **response))
        d.reset(np.arange(1), np.array([[0.0, 0.0, -10.0]]), np.zeros(1))
        out = {}
        for k in range(1, 201):
            d.step(np.array([[2.0, 0.0, 0.0]]), 0.1, np.ones(1, dtype=bool))
            out[round(k * 0.1, 1)] = float(d.vel_ned[0, 0])
        d.reset(np.arange(1), np.zeros((1, 3)), np.zeros(1))
        assert np.all(d.vel_error_int_ne == 0.0)
        return out

    plain, drag_only = speeds(), speeds(drag_horizontal_per_s=0.5)
    px4_sih = speeds(drag_horizontal_per_s=0.5, integral_horizontal_per_s2=0.2)  # docs/real_autopilots.md's fit
    assert plain[3.0] > 1.9 and plain[20.0] == pytest.approx(2.0, abs=1e-6)
    assert drag_only[20.0] == pytest.approx(2.0 / (1 + 0.5 / 1.2), abs=0.01)  # the shortfall stays
    assert 1.1 < px4_sih[1.0] < 1.4 and px4_sih[3.0] < 1.7 and px4_sih[20.0] > 1.9
    assert KinematicRandomization(drag_horizontal_per_s=(0.0, 0.0)).drag_horizontal_per_s == (0.0, 0.0)
    # Off (the default), the option draws nothing: a run consumes its generator as before the option existed.
    d, rng, ref = KinematicDynamics(8), np.random.default_rng(3), np.random.default_rng(3)
    d.randomize(np.arange(8), KinematicRandomization(), rng)
    for _ in range(6):  # the six response fields that were there before
        ref.uniform(0.0, 1.0, 8)
    assert rng.random() == ref.random() and np.all(d.response["drag_horizontal_per_s"] == 0.0)
    with pytest.raises(ValueError, match="0 <= low <= high"):
        KinematicRandomization(integral_horizontal_per_s2=(-0.1, 0.2))


def test_success_by_goal_altitude_bins():
    def rec(ep, alt, outcome):
        return UAVRecord(ep, 0, [0, 0, -5], [3, 0, -alt], outcome, 3.0, 3.0, 2.0)

    split = success_by_goal_altitude([rec(0, 2.0, "arrived"), rec(1, 2.5, "timeout"), rec(2, 4.0, "arrived"),
                                      rec(3, 9.0, "collision_uav")])
    assert split["below 3 m"]["uav_episodes"] == 2 and split["below 3 m"]["success_rate"] == 0.5
    assert split["below 3 m"]["timeout_rate"] == 0.5
    assert split["3-6 m"]["success_rate"] == 1.0 and split["above 6 m"]["success_rate"] == 0.0
    from sitl.eval.flown import _altitude_cells  # the table shows each bin's interval: a small bin is a wide one

    two_episodes = success_by_goal_altitude([rec(0, 2.0, "arrived"), rec(1, 2.5, "timeout")])
    assert _altitude_cells(two_episodes)[0] == f"0.500 ± {two_episodes['below 3 m']['success_ci95_half_width']:.3f} (2)"
    assert _altitude_cells(two_episodes)[1:] == ["-", "-"]


def test_flown_protocol_writes_cells_table_and_plot_and_resumes(tmp_path, capsys):
    out = tmp_path / "flown"
    argv = ["flown", "--policy", "straight", "--episodes", "1", "--no-jsbsim", "--out", str(out), "--no-progress",
            "--batch", "1"]
    assert main(argv) == 0
    text = (out / "flown.md").read_text()
    for cell in ("random-small", "random-medium", "random-large", "circle-n8", "circle-n8-common", "circle-n8-scatter",
                 "obstacles", "random-medium-delay"):
        assert f"| {cell} | straight |" in text
    assert "below 3 m" in text and (out / "flown_success.png").stat().st_size > 1000
    data = json.loads((out / "flown.json").read_text())
    assert set(data["cells"]["obstacles"]["results"]["straight"]["by_goal_altitude"]) == {"below 3 m", "3-6 m",
                                                                                         "above 6 m"}
    assert main(argv) == 0
    assert "0 computed, 9 reused" in capsys.readouterr().out
    assert main([*argv, "--cells", "obstacles,random-small"]) == 0  # a subset: only those cells, still reused
    printed = capsys.readouterr().out
    assert "0 computed, 2 reused" in printed and "| random-medium |" not in printed
    assert "| obstacles | straight |" in printed
    for bad in (["--episodes", "0"], ["--cells", "random-huge"], ["--cells", "random-medium-jsbsim", "--no-jsbsim"]):
        with pytest.raises(SystemExit) as exc:
            main(["flown", *bad])
        assert exc.value.code == 2


def test_circle_scatter_reaches_training_and_validation_circles():
    """``--circle-scatter-m``: training circles start scattered, and so do the run's validation circles (symmetric
    ones fly at 1.000 for every snapshot); its other validation scenes do not; without it nothing is scattered; a
    value outside [0, 10] m is refused."""
    from sitl.learn.config import TrainConfig, make_sim_config

    cfg = TrainConfig(preset="flown-fast", geometry="flown", scenario="mixed", circle_scatter_m=3.0)
    assert make_sim_config(cfg, 1).scenario.circle_scatter_m == 3.0
    assert make_sim_config(cfg, 1, scenario_name="circle").scenario.circle_scatter_m == 3.0
    for other in ("random", "obstacles"):
        assert make_sim_config(cfg, 1, scenario_name=other).scenario.circle_scatter_m == 0.0
    plain = TrainConfig(preset="flown-fast", geometry="flown", scenario="mixed")
    assert make_sim_config(plain, 1, scenario_name="circle").scenario.circle_scatter_m == 0.0
    with pytest.raises(ValueError, match="circle_scatter_m"):
        TrainConfig(circle_scatter_m=-1.0)


def test_velocity_lag_max_widens_training_dynamics_only():
    """``--velocity-lag-max-s``: training worlds draw horizontal and vertical velocity lags up to it (PX4 SIH's slower
    response); validation and tests fly the nominal vehicle; a value outside (0.15, 5] s is refused."""
    import dataclasses

    from sitl.learn.config import TrainConfig, make_sim_config

    cfg = TrainConfig(preset="flown-fast", geometry="flown", scenario="mixed", randomize_dynamics=True,
                      velocity_lag_max_s=1.6)
    train = make_sim_config(cfg, 1).dynamics_randomization
    assert train.tau_horizontal_s == train.tau_vertical_s == (KinematicRandomization().tau_horizontal_s[0], 1.6)
    assert train.tau_yaw_s == KinematicRandomization().tau_yaw_s  # the yaw response is left as it was
    assert make_sim_config(cfg, 1, scenario_name="circle").dynamics_randomization is None
    default = make_sim_config(dataclasses.replace(cfg, velocity_lag_max_s=0.0), 1).dynamics_randomization
    assert default == KinematicRandomization()
    for bad in (0.1, 9.0):
        with pytest.raises(ValueError, match="velocity_lag_max_s must be 0"):
            TrainConfig(velocity_lag_max_s=bad)


def test_the_delay_cell_flies_random_medium_with_a_command_delay_drawn_per_uav():
    """``random-medium-delay``: random medium's scene, every response field nominal but the command delay, drawn per
    UAV within FLOWN_COMMAND_DELAY_S in the simulator the evaluation builds."""
    from sitl.eval.evaluate import sim_config_for
    from sitl.eval.flown import FLOWN_COMMAND_DELAY_S, flown_cells
    from sitl.eval.methods import resolve_method
    from sitl.sim.dynamics import describe_response, nominal_ranges
    from sitl.sim.env import SwarmEnv

    cells = {cell.name: cell for cell in flown_cells(episodes=2, jsbsim=False)}
    delayed, plain = cells["random-medium-delay"].settings, cells["random-medium"].settings
    assert delayed.scenario == plain.scenario and plain.response is None
    lo, hi = FLOWN_COMMAND_DELAY_S
    assert describe_response(delayed.response, nominal_ranges()) == f"command_delay_s={lo:g}:{hi:g}"
    env = SwarmEnv(sim_config_for(resolve_method("straight"), delayed, num_worlds=4), seed=delayed.env_seed)
    env.reset()
    delays = env.dynamics.response["command_delay_s"]
    assert lo <= delays.min() and delays.max() <= hi and np.ptp(delays) > (hi - lo) / 2


def test_flown_response_layers_over_every_kinematic_cell_and_is_named(tmp_path, capsys):
    """``swarm_test flown --response SPEC``: each kinematic cell flies SPEC over its own response (the PX4 cell keeps
    its ranges, the delay cell takes the named delay), the JSBSim cell is left as it is; flown.md names it; a bad
    spec is one line and exit 2."""
    from sitl.sim.dynamics import RESPONSE_PRESETS, nominal_ranges, parse_response

    late = parse_response("command_delay_s=0.1", nominal_ranges())
    cells = {cell.name: cell.settings for cell in flown_cells(episodes=1, response=late)}
    assert cells["random-medium"].response.command_delay_s == (0.1, 0.1)
    assert cells["random-medium"].response.tau_horizontal_s == nominal_ranges().tau_horizontal_s
    assert cells["circle-n8-px4-sih"].response.command_delay_s == (0.1, 0.1)
    assert cells["circle-n8-px4-sih"].response.tau_horizontal_s == RESPONSE_PRESETS["px4-sih"]["tau_horizontal_s"]
    assert cells["random-medium-delay"].response.command_delay_s == (0.1, 0.1)
    assert cells["random-medium-jsbsim"].response is None
    out = tmp_path / "flown"
    assert main(["flown", "--policy", "straight", "--episodes", "1", "--cells", "random-small", "--response",
                 "command_delay_s=0.1", "--out", str(out), "--no-progress", "--batch", "1"]) == 0
    assert "also flies the response `command_delay_s=0.1`" in (out / "flown.md").read_text()
    with pytest.raises(SystemExit) as exc:
        main(["flown", "--response", "command_delay_s=9"])
    assert exc.value.code == 2
    assert "command_delay_s must be" in capsys.readouterr().err
