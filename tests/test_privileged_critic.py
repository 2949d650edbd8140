"""The asymmetric critic (``--privileged-critic``): its inputs, its update and a training run with it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from companion.spec import DEFAULT_ACTION_SPEC, CameraSpec
from sitl.learn.agent import AgentConfig, SacAeAgent
from sitl.learn.buffer import FrameReplayBuffer
from sitl.learn.networks import STATE_FEATURES
from sitl.learn.privileged import PRIVILEGED_DIM, privileged_features
from sitl.sim.collision import nearest_obstacle_points
from sitl.sim.collision import DISABLED_BOX, DISABLED_CYLINDER, distance_to_obstacles_m


def test_neighbours_obstacle_and_altitude_in_the_heading_frame():
    # UAV 0 at 5 m altitude heads east and flies east at 1 m/s; UAV 1 hovers 2 m north of it
    # (on its left), UAV 2 is 20 m away (out of range), UAV 3 is gone (crashed, removed).
    pos = np.array([[0, 0, -5], [2, 0, -5], [0, 20, -5], [0, 1, -5.0]])
    vel = np.array([[0, 1, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0.0]])
    yaw = np.array([np.pi / 2, 0, 0, 0])
    present = np.array([True, True, True, False])
    cylinders = np.array([[[0.0, -3.0, 0.5, -10.0, 0.0]]])  # a pole 3 m west of UAV 0, 0.5 m radius
    f = privileged_features(pos, vel, yaw, present, 4, np.tile(DISABLED_BOX, (1, 1, 1)), cylinders)
    assert f.shape == (4, PRIVILEGED_DIM) and f.dtype == np.float32
    first = f[0, 0:7]
    np.testing.assert_allclose(first, [0.0, -0.2, 0.0, -0.5, 0.0, 0.0, 1.0], atol=1e-6)  # left 2 m, closing at 1 m/s
    np.testing.assert_array_equal(f[0, 7:21], 0.0)  # no other neighbour within 10 m (UAV 3 is not present)
    np.testing.assert_allclose(f[0, 21:25], [-0.25, 0.0, 0.0, 1.0], atol=1e-6)  # the pole's surface 2.5 m behind
    assert f[0, 25] == pytest.approx(0.5)  # 5 m altitude / 10 m
    assert f[2, 6] == 0.0 and f[2, 24] == 0.0  # UAV 2: nothing within range


def test_the_nearest_obstacle_point_lies_at_the_collision_distance():
    rng = np.random.default_rng(3)
    boxes = np.array([[[5.0, 0.0, -2.0, 1.0, 2.0, 2.0], DISABLED_BOX]])
    cylinders = np.array([[[-4.0, 3.0, 0.4, -6.0, 0.0], DISABLED_CYLINDER]])
    points = rng.uniform([-10, -10, -10], [10, 10, -0.5], (1, 200, 3))
    nearest = nearest_obstacle_points(points, boxes, cylinders)
    np.testing.assert_allclose(np.linalg.norm(nearest - points, axis=-1), distance_to_obstacles_m(points, boxes, cylinders),
                               atol=1e-9)


def _filled_buffer(privileged_dim: int) -> FrameReplayBuffer:
    rng = np.random.default_rng(0)
    buf = FrameReplayBuffer(200, 4, 3, 16, 16, 6, 3, privileged_dim=privileged_dim)
    buf.start_episodes(np.arange(4), rng.uniform(0, 10, (4, 16, 16)))
    for t in range(20):
        extra = {}
        if privileged_dim:
            extra = {"privileged": np.full((4, privileged_dim), t, np.float32),
                     "next_privileged": np.full((4, privileged_dim), t + 1, np.float32)}
        buf.add(np.arange(4), rng.normal(size=(4, 6)), rng.uniform(-1, 1, (4, 3)), rng.normal(size=4),
                rng.uniform(0, 10, (4, 16, 16)), rng.normal(size=(4, 6)), np.zeros(4, bool), **extra)
    return buf


def test_the_critic_sees_the_privileged_input_and_the_actor_does_not():
    torch.manual_seed(0)
    cam = CameraSpec(width=16, height=16)
    agent = SacAeAgent(AgentConfig(hidden_dim=32, privileged_critic=True), cam, DEFAULT_ACTION_SPEC)
    paper = SacAeAgent(AgentConfig(hidden_dim=32), cam, DEFAULT_ACTION_SPEC)
    latent = agent.config.latent_dim
    assert agent.critic.q1[0].in_features == paper.critic.q1[0].in_features + PRIVILEGED_DIM
    assert agent.actor.trunk[0].in_features == paper.actor.trunk[0].in_features == latent + STATE_FEATURES

    buf = _filled_buffer(PRIVILEGED_DIM)
    batch = buf.sample(16, agent.device, n_step=3)
    # n-step: the next privileged input is the one after the last step followed (t + 3 here, no episode ends)
    np.testing.assert_allclose(batch["next_privileged"][:, 0] - batch["privileged"][:, 0],
                               np.minimum(3, 20 - batch["privileged"][:, 0].numpy()))
    before = agent.critic.q1[0].weight.detach().clone()
    for _ in range(3):
        info = agent.update(batch)
    assert all(np.isfinite(v) for v in info.values())
    assert not torch.equal(before, agent.critic.q1[0].weight)
    # The critic's value depends on the privileged input.
    pixels, state = agent._inputs(batch["depth"], batch["state"])
    with torch.no_grad():
        q_a = agent.critic(pixels, agent.critic_state(state, batch["privileged"]), batch["action"])[0]
        q_b = agent.critic(pixels, agent.critic_state(state, batch["privileged"] + 1.0), batch["action"])[0]
    assert not torch.allclose(q_a, q_b)
    # A batch without it is refused with the reason; the paper's critic needs none.
    with pytest.raises(ValueError, match="privileged"):
        agent.update({k: v for k, v in batch.items() if "privileged" not in k})
    paper.update(_filled_buffer(0).sample(16, paper.device))
    with pytest.raises(ValueError, match="privileged"):
        FrameReplayBuffer(10, 1, 3, 2, 2, 6, 3, privileged_dim=4).add(
            np.array([0]), np.zeros((1, 6)), np.zeros((1, 3)), np.zeros(1), np.zeros((1, 2, 2)), np.zeros((1, 6)),
            np.zeros(1, bool))


def test_a_training_run_with_the_privileged_critic_stores_the_true_surroundings_and_exports_the_plain_policy(tmp_path):
    from companion.policy import load_policy
    from sitl.learn.config import PRESETS, resolve_configs
    from sitl.learn.trainer import make_trainer

    cfg, agent_cfg = resolve_configs(
        {**PRESETS["flown"]["train"], "preset": "flown", "scenario": "mixed", "circle_fraction": 0.0,
         "obstacle_fraction": 0.5, "num_worlds": 4, "total_updates": 4, "init_steps": 100, "batch_size": 16,
         "eval_every_updates": 0, "final_eval_episodes": 0},
        {"hidden_dim": 32, "privileged_critic": True})
    trainer = make_trainer(cfg, agent_cfg, tmp_path)
    trainer.run()
    buf = trainer.buffer
    rows = buf.privileged[:buf.size]
    assert rows.shape[1] == PRIVILEGED_DIM
    assert rows[:, 6].mean() > 0.5  # a nearest neighbour within 10 m is the rule in random medium
    assert 0 < rows[:, 24].mean() < 1  # an obstacle point in range in some worlds only (half have obstacles)
    assert np.all(rows[:, 25] > 0.0)  # altitude above the ground
    assert not np.array_equal(rows, buf.next_privileged[:buf.size])
    policy = load_policy(tmp_path / "policy.pt")  # the exported actor takes the plain observation
    assert policy.metadata["provenance"]["privileged_critic"]["neighbours"] == 3
