"""Reward terms (paper eqs. 2-4) and metrics (eq. 9) on hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sitl.sim.config import RewardConfig, ScenarioConfig, SimConfig
from sitl.sim.env import SwarmEnv
from sitl.sim.metrics import UAVRecord, spl, summarize
from sitl.sim.reward import avoid_reward, goal_reward, nearest_depth_m, step_reward

CFG = RewardConfig()


def test_goal_reward_is_scaled_progress_or_arrival_bonus():
    prev, now = np.array([10.0, 10.0, 0.6]), np.array([9.8, 10.1, 0.4])
    r = goal_reward(prev, now, arrived=np.array([False, False, True]), cfg=CFG)
    np.testing.assert_allclose(r, [3.0 * 0.2, 3.0 * -0.1, 50.0])


def test_avoid_reward_penalises_near_surfaces_and_collisions():
    d_min = np.array([8.0, 5.0, 1.0, 1.0])
    r = avoid_reward(np.array([False, False, False, True]), d_min, CFG)
    np.testing.assert_allclose(r, [0.0, 0.0, -0.05 * 4.0, -10.0])


def test_total_reward_and_collision_cancels_arrival():
    r = step_reward(np.array([1.0, 1.0]), np.array([0.3, 0.3]), np.array([True, True]),
                    np.array([False, True]), np.array([10.0, 10.0]), CFG)
    np.testing.assert_allclose(r, [50.0, 3.0 * 0.7 - 10.0])


def test_d_min_is_taken_from_the_depth_image():
    depth = np.full((2, 4, 4), 20.0, dtype=np.float32)
    depth[1, 2, 3] = 1.5
    np.testing.assert_array_equal(nearest_depth_m(depth), [20.0, 1.5])


def _head_on_env(**overrides):
    cfg = SimConfig(num_uavs=2, scenario=ScenarioConfig(name="circle", circle_radius_m=3.0, circle_jitter_m=0.0),
                    **overrides)
    env = SwarmEnv(cfg, seed=1)
    env.reset()
    return env


def test_env_head_on_collision_gives_collision_reward_and_removes_both():
    env = _head_on_env()
    rewards = []
    while not env.world_done.all():
        obs, r, term, trunc, info = env.step(np.tile([2.0, 0.0, 0.0], (2, 1)))
        rewards.append(r)
    assert rewards[-1].tolist() == pytest.approx([rewards[-1][0]] * 2)
    assert rewards[-1][0] < -9.0  # -10 plus a little progress
    # On the way in, they saw each other within d_safe and were penalised (eq. 4).
    assert any(-9 < r[0] < 3.0 * 0.2 - 1e-3 for r in rewards[:-1])
    records = env.finish()
    assert [rec.outcome for rec in records] == ["collision_uav", "collision_uav"]
    assert not env.present.any()


def test_crashed_uavs_can_be_kept_frozen():
    env = _head_on_env(crashed="freeze")
    while not env.world_done.all():
        env.step(np.tile([2.0, 0.0, 0.0], (2, 1)))
    frozen = env.dynamics.pos_ned.copy()
    assert env.present.all()
    env.step(np.tile([2.0, 0.0, 0.0], (2, 1)))
    np.testing.assert_array_equal(env.dynamics.pos_ned, frozen)


def test_arrived_uav_hovers_near_goal_and_stays_visible():
    cfg = SimConfig(num_uavs=1, scenario=ScenarioConfig(name="circle", circle_radius_m=3.0, circle_jitter_m=0.0))
    env = SwarmEnv(cfg, seed=0)
    obs = env.reset()
    from sitl.sim.baselines import straight_to_goal
    total = 0.0
    while not env.world_done.all():
        obs, r, term, trunc, info = env.step(straight_to_goal(obs.state))
        total += r[0]
    assert info["outcome"][0] == 1 and term[0] and r[0] >= 50.0
    assert total == pytest.approx(50.0 + 3.0 * (6.0 - np.linalg.norm(env.goal_ned[0] - env._paths[0][-1])), abs=1.0)
    for _ in range(30):
        env.step(np.zeros((1, 3)))
    assert np.linalg.norm(env.dynamics.pos_ned[0] - env.goal_ned[0]) < 1.0
    assert np.linalg.norm(env.dynamics.vel_ned[0]) < 0.05 and env.present[0]


def _record(outcome, path, straight, episode=0):
    return UAVRecord(episode=episode, uav=0, start_ned=[0, 0, 0], goal_ned=[straight, 0, 0], outcome=outcome,
                     path_length_m=path, straight_distance_m=straight, duration_s=path / 1.0 if path else 1.0)


def test_spl_matches_equation_9_by_hand():
    records = [
        _record("arrived", 12.0, 10.0),  # 10 / 12
        _record("arrived", 9.6, 10.0),  # reached within 0.5 m: l / max(p, l) = 1
        _record("collision_uav", 3.0, 10.0),  # S = 0
        _record("timeout", 30.0, 5.0, episode=1),  # S = 0
    ]
    assert spl(records) == pytest.approx((10 / 12 + 1.0) / 4)
    s = summarize(records)
    assert s["success_rate"] == 0.5 and s["episodes"] == 2 and s["uav_episodes"] == 4
    assert s["extra_distance_m"]["mean"] == pytest.approx((2.0 - 0.4) / 2)
    assert s["collision_uav_rate"] == 0.25 and s["timeout_rate"] == 0.25 and s["collision_ground_rate"] == 0.0
    assert math.isnan(spl([]))


def _hover_reward(altitude_m: float, counts_ground: bool, other_ahead_m: float | None = None,
                  reward: RewardConfig | None = None) -> float:
    """The reward of UAV 0 hovering level at ``altitude_m`` in an empty scene (UAV 1 far behind or ahead)."""
    cfg = SimConfig(num_uavs=2, scenario=ScenarioConfig(name="circle", circle_radius_m=30.0, circle_jitter_m=0.0),
                    reward=reward or RewardConfig(avoid_counts_ground=counts_ground))
    env = SwarmEnv(cfg, seed=0)
    env.reset()
    other = [other_ahead_m, 0.0, -altitude_m] if other_ahead_m is not None else [-50.0, 0.0, -altitude_m]
    env.dynamics.reset(np.arange(2), np.array([[0.0, 0.0, -altitude_m], other]), np.zeros(2))
    env.goal_ned[:] = env.dynamics.pos_ned  # no progress term while hovering
    env.goal_ned[:, 0] += 20.0
    _, reward, *_ = env.step(np.zeros((2, 3)))
    return float(reward[0])


def test_the_ground_counts_in_d_min_only_when_the_reward_config_says_so():
    """Paper eq. 4 with the ground: hovering at 2 m costs w_avoid * (5 - ~2) per step; without it, nothing."""
    with_ground = _hover_reward(2.0, counts_ground=True)
    assert with_ground == pytest.approx(-0.05 * (5.0 - 2.016), abs=2e-3)
    assert _hover_reward(2.0, counts_ground=False) == 0.0
    assert _hover_reward(8.0, counts_ground=True) == 0.0  # the ground beyond d_safe costs nothing either way
    # Another UAV 3 m ahead counts in both: its surface is 2.7 m away (R = 0.3 m).
    near_uav = _hover_reward(8.0, counts_ground=False, other_ahead_m=3.0)
    assert near_uav == pytest.approx(-0.05 * (5.0 - 2.7), abs=2e-3)
    assert _hover_reward(8.0, counts_ground=True, other_ahead_m=3.0) == pytest.approx(near_uav, abs=1e-6)


def test_the_training_config_sets_the_collision_reward_the_environment_pays():
    """``sitl.train --collision-reward`` reaches eq. 4 in the simulator (paper -10 by default); a reward
    above 0 is refused."""
    from sitl.learn.config import TrainConfig, make_sim_config

    assert make_sim_config(TrainConfig(), num_worlds=1).reward.r_collision == RewardConfig().r_collision == -10.0
    cfg = make_sim_config(TrainConfig(collision_reward=-50.0), num_worlds=1)
    env = SwarmEnv(SimConfig(num_uavs=2, reward=cfg.reward,
                             scenario=ScenarioConfig(name="circle", circle_radius_m=3.0, circle_jitter_m=0.0)), seed=1)
    env.reset()
    while not env.world_done.all():
        _, r, *_ = env.step(np.tile([2.0, 0.0, 0.0], (2, 1)))
    assert -50.0 < r[0] < -49.0  # -50 plus a little progress
    with pytest.raises(ValueError, match="collision_reward"):
        TrainConfig(collision_reward=5.0)


def _first_collision_reward(reward: RewardConfig, obstacle: bool) -> float:
    """The reward of the step in which UAV 0, flying straight north at 2 m/s, hits UAV 1 flying the other
    way (or, with ``obstacle``, a 0.2 m pole half-way to its goal, with UAV 1 far away)."""
    cfg = SimConfig(num_uavs=2, reward=reward, scenario=ScenarioConfig(name="random", density=0.01, min_goal_distance_m=0.0))
    env = SwarmEnv(cfg, seed=0, cylinders=np.array([[[0.0, 0.0, 0.2, -30.0, 0.0]]]) if obstacle else None)
    env.reset()
    other_start = [40.0, 40.0, -8.0] if obstacle else [5.0, 0.0, -8.0]
    env.dynamics.reset(np.array([0, 1]), np.array([[-5.0, 0.0, -8.0], other_start]), np.array([0.0, math.pi]))
    env.goal_ned[0], env.goal_ned[1] = [5.0, 0.0, -8.0], [other_start[0] - 10.0, other_start[1], -8.0]
    for _ in range(100):
        _, r, term, *_ = env.step(np.tile([2.0, 0.0, 0.0], (2, 1)))
        if term[0]:
            return float(r[0])
    raise AssertionError("UAV 0 never collided")


def test_an_extra_price_on_uav_collisions_leaves_other_collisions_at_r_collision():
    """``--uav-collision-extra-reward -40``: a UAV-UAV collision costs -50, a pole still the paper's -10."""
    from sitl.learn.config import TrainConfig, make_sim_config

    reward = make_sim_config(TrainConfig(uav_collision_extra_reward=-40.0), num_worlds=1).reward
    assert (reward.r_collision, reward.r_collision_uav_extra) == (-10.0, -40.0)
    assert -50.0 < _first_collision_reward(reward, obstacle=False) < -49.0  # -50 plus a little progress
    assert -10.0 < _first_collision_reward(reward, obstacle=True) < -9.0
    assert -10.0 < _first_collision_reward(RewardConfig(), obstacle=False) < -9.0  # the paper: no extra price
    with pytest.raises(ValueError, match="uav_collision_extra_reward"):
        TrainConfig(uav_collision_extra_reward=1.0)


def test_in_frustum_follows_the_camera_field_of_view_and_mount_pitch():
    """A D435 (87 x 58 deg): ahead is seen, straight up and 45 deg to the side are not; a climb at
    26.6 deg is inside the level camera's +-29 deg, outside once the camera is pitched 5 deg down."""
    from companion.spec import REALSENSE_D435
    from sitl.sim.camera import in_frustum

    h, v = REALSENSE_D435.tan_half_hfov, REALSENSE_D435.tan_half_vfov
    directions = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [1.0, 1.0, 0.0], [1.0, 0.9, 0.0],
                           [1.0, 0.0, -0.5], [0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    assert in_frustum(directions, h, v).tolist() == [True, False, False, True, True, False, False]
    assert in_frustum(directions[4], h, v, math.radians(-5.0)).item() is False
    assert in_frustum(directions[4], h, v, math.radians(5.0)).item() is True
    # A direction 33 deg up is seen only by a camera pitched up by more than 4 deg.
    up33 = np.array([math.cos(math.radians(33)), 0.0, -math.sin(math.radians(33))])
    assert in_frustum(np.stack([up33] * 3), h, v, np.radians([0.0, 3.0, 5.0])).tolist() == [False, False, True]


def test_the_blind_motion_reward_prices_speed_outside_the_camera_view_only():
    """``--blind-motion-reward W``: a UAV climbing straight up pays W per m/s of its speed on top of eq. 2;
    one flying level towards its goal pays nothing; W = 0 (the paper) changes nothing."""
    from sitl.learn.config import TrainConfig, make_sim_config

    def rewards(w_blind: float, action: list[float]) -> np.ndarray:
        reward = make_sim_config(TrainConfig(blind_motion_reward=w_blind), num_worlds=1).reward
        cfg = SimConfig(num_uavs=1, reward=reward, scenario=ScenarioConfig(name="random", density=0.01))
        env = SwarmEnv(cfg, seed=0)
        env.reset()
        env.dynamics.reset(np.array([0]), np.array([[0.0, 0.0, -8.0]]), np.array([0.0]))
        env.goal_ned[0] = [30.0, 0.0, -38.0]  # far ahead and far above: neither step arrives
        out = []
        for _ in range(20):
            _, r, *_ = env.step(np.array([action]))
            out.append((r[0], np.linalg.norm(env.dynamics.vel_ned[0])))
        return np.array(out)

    climb, level = [0.0, -0.5, 0.0], [2.0, 0.0, 0.0]
    paper, priced = rewards(0.0, climb), rewards(-0.2, climb)
    assert priced[-1, 1] > 0.4  # climbing at (almost) the full 0.5 m/s
    np.testing.assert_allclose(priced[:, 0], paper[:, 0] - 0.2 * paper[:, 1], atol=1e-5)
    np.testing.assert_allclose(rewards(-0.2, level)[:, 0], rewards(0.0, level)[:, 0], atol=1e-6)
    assert make_sim_config(TrainConfig(), num_worlds=1).reward.w_blind == 0.0
    with pytest.raises(ValueError, match="blind_motion_reward"):
        TrainConfig(blind_motion_reward=0.5)


def test_the_corridor_price_charges_forward_speed_the_governor_would_not_allow():
    """``--corridor-speed-reward W``: flying at full speed at a pole pays W per m/s above the speed
    governor's cap on the new frame, more the nearer it gets; flying at the same speed in open air
    pays nothing; W = 0 (the paper) changes nothing."""
    from companion.governor import SpeedGovernor
    from companion.spec import REALSENSE_D435
    from sitl.learn.config import TrainConfig, make_sim_config

    def run(w: float, pole: bool) -> tuple[np.ndarray, np.ndarray]:
        reward = make_sim_config(TrainConfig(corridor_speed_reward=w), num_worlds=1).reward
        cfg = SimConfig(num_uavs=1, reward=reward, camera=REALSENSE_D435,
                        scenario=ScenarioConfig(name="random", density=0.01, min_goal_distance_m=0.0))
        cylinders = np.array([[[0.0, 0.0, 0.2, -30.0, 0.0]]]) if pole else None
        env = SwarmEnv(cfg, seed=0, cylinders=cylinders)
        env.reset()
        env.dynamics.reset(np.array([0]), np.array([[-4.0, 0.0, -8.0]]), np.array([0.0]))
        env.goal_ned[0] = [6.0, 0.0, -8.0]
        rewards, excess = [], []
        for _ in range(12):
            obs, r, term, *_ = env.step(np.array([[2.0, 0.0, 0.0]], dtype=np.float32))
            if term[0]:
                break
            rewards.append(r[0])
            excess.append(max(2.0 - SpeedGovernor(REALSENSE_D435).forward_limit(obs.depth[:, -1])[1][0], 0.0))
        return np.array(rewards), np.array(excess)

    paper, excess = run(0.0, pole=True)
    priced, _ = run(-1.0, pole=True)
    assert excess[-1] > 0.3 and np.all(np.diff(excess[excess > 0]) >= 0)  # the pole comes closer
    np.testing.assert_allclose(priced, paper - excess[:len(priced)], atol=1e-5)
    np.testing.assert_allclose(run(-1.0, pole=False)[0], run(0.0, pole=False)[0], atol=1e-6)
    assert make_sim_config(TrainConfig(), num_worlds=1).reward.w_corridor == 0.0
    with pytest.raises(ValueError, match="corridor_speed_reward"):
        TrainConfig(corridor_speed_reward=0.5)


def test_the_training_config_sets_eq4s_avoid_weight():
    """``--avoid-weight W``: a UAV 2.7 m from another's surface pays W * (5 - 2.7) per step (paper W = -0.05)."""
    from sitl.learn.config import TrainConfig, make_sim_config

    reward = make_sim_config(TrainConfig(avoid_weight=-0.15), num_worlds=1).reward
    assert _hover_reward(8.0, False, other_ahead_m=3.0, reward=reward) == pytest.approx(-0.15 * (5.0 - 2.7), abs=5e-3)
    assert make_sim_config(TrainConfig(), num_worlds=1).reward.w_avoid == RewardConfig().w_avoid == -0.05
    with pytest.raises(ValueError, match="avoid_weight"):
        TrainConfig(avoid_weight=0.1)
