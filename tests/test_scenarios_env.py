"""Scenarios (paper IV.B), determinism, the batched interface and bad input."""

from __future__ import annotations

import math
from itertools import combinations

import numpy as np
import pytest

from sitl.sim.baselines import straight_to_goal
from sitl.sim.config import DENSITIES, ScenarioConfig, SimConfig, density_from_name
from sitl.sim.env import SwarmEnv
from sitl.sim.scenarios import random_box_size, sample_circle, sample_random


@pytest.mark.parametrize("name", ["small", "medium", "large"])
def test_random_scenario_density_and_separations(name):
    cfg = ScenarioConfig(name="random", density=DENSITIES[name])
    side, height = random_box_size(8, cfg.density, cfg.box_aspect)
    assert 8 / (side * side * height) == pytest.approx(DENSITIES[name])
    rng = np.random.default_rng(0)
    for _ in range(20):
        s = sample_random(8, cfg, rng)
        for pts in (s.start_ned, s.goal_ned):
            assert np.all(np.abs(pts[:, :2]) <= side / 2 + 1e-9)
            assert np.all((-pts[:, 2] >= cfg.box_floor_alt_m - 1e-9) & (-pts[:, 2] <= cfg.box_floor_alt_m + height + 1e-9))
            assert min(np.linalg.norm(a - b) for a, b in combinations(pts, 2)) >= cfg.min_separation_m
        assert np.all(np.linalg.norm(s.goal_ned - s.start_ned, axis=1) >= cfg.min_goal_distance_m)


def test_circle_scenario_is_antipodal_and_varies_between_episodes():
    cfg = ScenarioConfig(name="circle", circle_radius_m=12.0)
    rng = np.random.default_rng(0)
    a, b = sample_circle(8, cfg, rng), sample_circle(8, cfg, rng)
    for s in (a, b):
        np.testing.assert_allclose(np.linalg.norm(s.goal_ned[:, :2], axis=1), 12.0)
        assert np.all(s.goal_ned[:, 2] == -cfg.circle_alt_m)
        nominal = s.goal_ned * [-1, -1, 1]
        assert np.all(np.abs(s.start_ned - nominal) <= cfg.circle_jitter_m)
        # evenly spaced
        angles = np.sort(np.arctan2(s.goal_ned[:, 1], s.goal_ned[:, 0]))
        np.testing.assert_allclose(np.diff(angles), 2 * math.pi / 8, atol=1e-9)
    assert not np.allclose(a.start_ned, b.start_ned)  # rotated and jittered anew


def test_same_seed_same_episode_and_different_seed_differs():
    def rollout(seed):
        env = SwarmEnv(SimConfig(num_uavs=4, num_worlds=3), seed=seed)
        obs = env.reset()
        for _ in range(20):
            obs, *_ = env.step(straight_to_goal(obs.state))
        return obs.depth.copy(), obs.state.copy()

    d1, s1 = rollout(5)
    d2, s2 = rollout(5)
    d3, s3 = rollout(6)
    np.testing.assert_array_equal(d1, d2)
    np.testing.assert_array_equal(s1, s2)
    assert not np.array_equal(s1, s3)


def test_batched_interface_shapes_and_world_reset():
    cfg = SimConfig(num_uavs=3, num_worlds=4, max_episode_steps=5)
    env = SwarmEnv(cfg, seed=0)
    obs = env.reset()
    assert obs.depth.shape == (12, 3, 32, 32) and obs.depth.dtype == np.float32
    assert obs.state.shape == (12, 6) and obs.state.dtype == np.float32
    for _ in range(5):
        obs, reward, term, trunc, info = env.step(np.zeros((12, 3)))
    assert reward.shape == (12,) and info["acting"].all()
    assert trunc.all() and env.world_done.all()  # hovering in place until the time limit
    obs = env.reset_worlds(np.array([True, False, False, False]))
    assert env.acting[:3].all() and not env.acting[3:].any()
    records = env.finish()
    assert len(records) == 12 and {r.outcome for r in records} == {"timeout"}
    assert {r.episode for r in records} == {0, 1, 2, 3}


def test_straight_reference_in_the_open_reaches_every_goal():
    env = SwarmEnv(SimConfig(num_uavs=1, num_worlds=20), seed=0)
    obs = env.reset()
    while not env.world_done.all():
        obs, *_ = env.step(straight_to_goal(obs.state))
    records = env.finish()
    assert all(r.success for r in records) and len(records) == 20


def test_bad_configuration_is_rejected_with_a_clear_message():
    with pytest.raises(ValueError, match="unknown scenario 'spiral'"):
        ScenarioConfig(name="spiral")
    with pytest.raises(ValueError, match="num_uavs must be >= 1"):
        SimConfig(num_uavs=0)
    with pytest.raises(ValueError, match="density must be > 0"):
        ScenarioConfig(density=0.0)
    with pytest.raises(ValueError, match="density must be > 0"):
        density_from_name("-1")
    with pytest.raises(ValueError, match="unknown density 'huge'"):
        density_from_name("huge")
    assert density_from_name("small") == 0.1 and density_from_name("0.02") == 0.02
    with pytest.raises(ValueError, match="real quadrotor"):
        SimConfig(collision_radius_m=0.1)
    with pytest.raises(ValueError, match="unknown dynamics"):
        SimConfig(dynamics="warp")
    with pytest.raises(ValueError, match="too high"):
        sample_random(8, ScenarioConfig(density=50.0), np.random.default_rng(0))


def test_bad_actions_raise_or_clip():
    env = SwarmEnv(SimConfig(num_uavs=2), seed=0)
    env.reset()
    with pytest.raises(ValueError, match="non-finite"):
        env.step(np.array([[np.nan, 0, 0], [1, 0, 0]]))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros((3, 3)))
    # Out-of-bounds commands are clipped: 5 m/s forward flies like 2 m/s.
    clipped = SwarmEnv(SimConfig(num_uavs=2), seed=0)
    clipped.reset()
    env.reset(seed=0)
    for _ in range(10):
        env.step(np.tile([5.0, 2.0, 3.0], (2, 1)))
        clipped.step(np.tile([2.0, 0.5, 0.5], (2, 1)))
    np.testing.assert_allclose(env.dynamics.pos_ned, clipped.dynamics.pos_ned)


def test_mixed_scenario_draws_circles_with_the_given_fraction():
    from sitl.sim.scenarios import sample_scenario

    rng = np.random.default_rng(3)
    cfg = ScenarioConfig(name="mixed", circle_fraction=0.5)
    altitudes = [sample_scenario(8, cfg, rng).goal_ned[:, 2] for _ in range(200)]
    # A circle episode has every goal at the circle's altitude; a random one does not.
    circles = sum(bool(np.allclose(z, -cfg.circle_alt_m)) for z in altitudes)
    assert 70 <= circles <= 130
    only_random = ScenarioConfig(name="mixed", circle_fraction=0.0)
    assert not any(np.allclose(sample_scenario(8, only_random, rng).goal_ned[:, 2], -10.0) for _ in range(20))
    with pytest.raises(ValueError, match="circle_fraction"):
        ScenarioConfig(name="mixed", circle_fraction=1.5)


def test_mount_pitch_is_drawn_per_episode_within_the_jitter():
    import math

    from companion.spec import REALSENSE_D435
    from sitl.sim.config import SimConfig
    from sitl.sim.env import SwarmEnv

    env = SwarmEnv(SimConfig(num_uavs=4, num_worlds=50, camera=REALSENSE_D435, mount_pitch_jitter_deg=5.0), seed=3)
    env.reset()
    first = env.mount_pitch_rad.copy()
    assert np.abs(first).max() <= math.radians(5.0) and np.abs(first).max() > math.radians(4.0)
    assert len(np.unique(first)) == first.size  # every camera its own
    env.reset()
    assert not np.array_equal(first, env.mount_pitch_rad)
    level = SwarmEnv(SimConfig(num_uavs=4, camera=REALSENSE_D435), seed=3)
    level.reset()
    assert np.all(level.mount_pitch_rad == 0.0)
    with pytest.raises(ValueError, match="mount_pitch_jitter_deg"):
        SimConfig(mount_pitch_jitter_deg=45.0)


def test_a_noisy_real_camera_reaches_the_policy_through_the_companion_conversion():
    from companion.spec import REALSENSE_D435
    from sitl.sim.camera import StereoNoise
    from sitl.sim.config import SimConfig
    from sitl.sim.env import SwarmEnv

    env = SwarmEnv(SimConfig(num_uavs=8, num_worlds=4, camera=REALSENSE_D435, camera_noise=StereoNoise()), seed=0)
    obs = env.reset()
    for _ in range(5):
        obs, *_ = env.step(straight_to_goal(obs.state))
    depth = obs.depth
    assert depth.shape == (32, 3, REALSENSE_D435.height, REALSENSE_D435.width)
    assert depth.min() > 0 and depth.max() == REALSENSE_D435.max_range_m  # no zeros: holes read max range
    assert 0.3 < np.mean(depth[:, -1] == REALSENSE_D435.max_range_m) < 1.0  # holes and sky, but not only


def test_remembered_depth_in_the_state_is_built_from_the_frames_and_poses_the_companion_would_have():
    """With ``SimConfig.memory`` every UAV's state carries the sector ranges after its 6 entries, built by
    companion.observation.RememberedDepth from each rendered frame and the pose it was seen from: the same
    frames and odometry fed to a separate instance (as the companion is fed) give the same state."""
    from companion.observation import RememberedDepth
    from companion.spec import REALSENSE_D435, MemorySpec

    memory = MemorySpec(steps=6, every_steps=2)
    config = SimConfig(num_uavs=8, num_worlds=2, camera=REALSENSE_D435, memory=memory,
                       scenario=ScenarioConfig(name="random", density=density_from_name("small")))
    env = SwarmEnv(config, seed=3)
    obs = env.reset()
    companion_side = RememberedDepth(env.num_agents, REALSENSE_D435, memory)
    d = env.dynamics
    companion_side.reset(env.frames.latest, d.pos_ned, d.yaw_rad)
    nearest = []
    for _ in range(8):
        assert obs.state.shape == (env.num_agents, 6 + memory.num_sectors)
        np.testing.assert_array_equal(obs.state[:, 6:], companion_side.sector_ranges(d.pos_ned, d.yaw_rad))
        nearest.append(obs.state[:, 6:].min())
        obs, *_ = env.step(straight_to_goal(obs.state, env.action_spec))
        companion_side.push(env.frames.latest, d.pos_ned, d.yaw_rad)
    assert min(nearest) < memory.range_m  # a crowded start: some UAV remembers a neighbour within range
