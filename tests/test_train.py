"""The trainer's parts: replay buffer, baselines' updates, command line, checkpoint and resume."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from companion.observation import DepthFrameStack
from companion.spec import CAMERA_PRESETS, DEFAULT_ACTION_SPEC, CameraSpec
from sitl.learn.agent import AgentConfig, SacAeAgent
from sitl.learn.buffer import FrameReplayBuffer
from sitl.learn.vae import train_vae
from sitl.learn.cli import parse_args
from sitl.learn.config import training_camera
from sitl.learn.trainer import snapshot_counters

REPO = Path(__file__).resolve().parent.parent


def test_buffer_rebuilds_stacks_from_frames_stored_once():
    buf = FrameReplayBuffer(capacity=50, num_agents=2, frames=3, height=2, width=2, state_dim=6, action_dim=3)
    frame = lambda v: np.full((1, 2, 2), v, dtype=np.float32)  # noqa: E731
    buf.start_episodes(np.array([0, 1]), np.concatenate([frame(1), frame(101)]))
    for t in range(2, 6):
        buf.add(np.array([0, 1]), np.zeros((2, 6)), np.zeros((2, 3)), np.full(2, t), np.concatenate([frame(t), frame(100 + t)]),
                np.zeros((2, 6)), np.array([False, t == 5]))
    batch = buf.sample(200, torch.device("cpu"))
    for depth, next_depth, reward, not_done in zip(batch["depth"], batch["next_depth"], batch["reward"], batch["not_done"]):
        t = int(reward)
        offset = 0 if depth[0, 0, 0] < 100 else 100
        # obs = frames t-3..t-1 (the first frame repeated at the start), next = t-2..t
        expected = [max(1, s) + offset for s in (t - 3, t - 2, t - 1)]
        assert depth[:, 0, 0].tolist() == expected
        assert next_depth[:, 0, 0].tolist() == expected[1:] + [t + offset]
        assert not_done.item() == (0.0 if (offset == 100 and t == 5) else 1.0)
    # One frame per transition plus one per episode start: 10 frames, not 10 x 6.
    assert buf._next_frame == 10


@pytest.mark.parametrize("stride, ages", [(1, ()), (3, ()), (1, (6, 1, 0))])
def test_buffer_gives_back_the_observations_the_frame_stack_gave_the_policy(stride, ages):
    """The replay buffer rebuilds each transition's stacks (n-step included) exactly as the
    environment's DepthFrameStack built them, episode starts included, for any frame stride or
    unevenly spaced stack."""
    camera = CameraSpec(width=1, height=1, frames=3, frame_stride=stride, frame_ages=ages)
    stack = DepthFrameStack(2, camera)
    buf = FrameReplayBuffer(capacity=500, num_agents=2, frames=3, height=1, width=1, state_dim=6, action_dim=3,
                            frame_ages=camera.stack_ages)
    rng = np.random.default_rng(0)
    seen: dict[int, tuple[list, list]] = {}  # transition id -> (obs, next obs) as the policy saw them
    value = 0.0
    fresh = lambda: np.array([[[value]]], dtype=np.float32)  # noqa: E731
    for agent in (0, 1):
        value += 1
        stack.reset(fresh(), np.array([agent]))
        buf.start_episodes(np.array([agent]), fresh())
    for step in range(120):
        for agent in (0, 1):  # one agent at a time, so each row is one transition with its own id
            obs = stack.frames[agent, :, 0, 0].tolist()
            value += 1
            stack.push(fresh(), np.array([agent]))
            ends = bool(rng.random() < 0.08)
            tid = 1000 * step + agent
            seen[tid] = (obs, stack.frames[agent, :, 0, 0].tolist())
            buf.add(np.array([agent]), np.zeros((1, 6)), np.zeros((1, 3)), np.array([tid]), fresh()[0][None],
                    np.zeros((1, 6)), np.array([ends]))
            if ends:
                value += 1
                stack.reset(fresh(), np.array([agent]))
                buf.start_episodes(np.array([agent]), fresh())
    batch = buf.sample(300, torch.device("cpu"))
    for depth, next_depth, tid in zip(batch["depth"], batch["next_depth"], batch["reward"][:, 0]):
        obs, next_obs = seen[int(tid)]
        assert depth[:, 0, 0].tolist() == obs and next_depth[:, 0, 0].tolist() == next_obs


def test_the_approach_to_a_collision_is_marked_and_oversampled():
    """Agent 1 collides at its 8th step: its last 3 transitions are marked (not agent 0's, not the
    earlier ones); a batch with precollision_fraction 0.5 draws half its rows from them."""
    buf = FrameReplayBuffer(capacity=100, num_agents=2, frames=3, height=1, width=1, state_dim=6, action_dim=3,
                            precollision_steps=3)
    frame = np.zeros((2, 1, 1), dtype=np.float32)
    buf.start_episodes(np.array([0, 1]), frame)
    for t in range(8):
        hit = np.array([False, t == 7])
        buf.add(np.array([0, 1]), np.zeros((2, 6)), np.zeros((2, 3)), np.array([t, 100 + t]), frame, np.zeros((2, 6)),
                hit, collided=hit)
    buf.start_episodes(np.array([1]), frame[:1])
    buf.add(np.array([0, 1]), np.zeros((2, 6)), np.zeros((2, 3)), np.array([8, 200]), frame, np.zeros((2, 6)),
            np.array([False, False]), collided=np.array([False, False]))
    marked = sorted(buf.reward[: buf.size][buf.precollision[: buf.size], 0].tolist())
    assert marked == [105.0, 106.0, 107.0]
    rewards = buf.sample(200, torch.device("cpu"), precollision_fraction=0.5)["reward"][:, 0]
    assert set(rewards[:100].tolist()) == {105.0, 106.0, 107.0}
    assert 30 < (rewards[100:] < 100).sum() < 70  # the rest uniform over all 18 rows (9 of agent 0)
    uniform = buf.sample(200, torch.device("cpu"))["reward"][:, 0]
    assert np.isin(uniform.numpy(), [105.0, 106.0, 107.0]).mean() < 0.35


def test_a_checkpoint_holds_only_the_filled_part_of_a_big_buffer_and_resumes(tmp_path):
    """Issue 16: capacity 200,000 holding 176 transitions wrote 905 MB; now the checkpoint is the 176 transitions."""
    def make():
        return FrameReplayBuffer(capacity=200_000, num_agents=8, frames=3, height=32, width=32, state_dim=6,
                                 action_dim=3, seed=3)

    rng = np.random.default_rng(0)
    agents = np.arange(8)
    buf = make()
    assert buf.nbytes > 800 * 2**20  # preallocated (lazily: untouched pages cost no memory)
    buf.start_episodes(agents, rng.uniform(0, 20, (8, 32, 32)).astype(np.float32))
    for t in range(22):  # 22 steps x 8 agents = 176 transitions
        buf.add(agents, rng.normal(size=(8, 6)), rng.normal(size=(8, 3)), rng.normal(size=8),
                rng.uniform(0, 20, (8, 32, 32)).astype(np.float32), rng.normal(size=(8, 6)), np.array([t == 21] * 8))
    assert buf.size == 176
    path = tmp_path / "buffer.pt"
    torch.save(buf.state_dict(), path)
    assert path.stat().st_size < 2 * 2**20, path.stat().st_size  # 184 frames of 2 KiB + rows: < 1 MiB

    restored = make()
    restored.load_state_dict(torch.load(path, weights_only=False))
    assert restored.size == 176 and restored._next_frame == buf._next_frame
    a = buf.sample(64, torch.device("cpu"), n_step=5)
    b = restored.sample(64, torch.device("cpu"), n_step=5)
    for key in a:
        assert torch.equal(a[key], b[key]), key
    # It keeps filling where the saved one left off, links between transitions included.
    for target in (buf, restored):
        target.start_episodes(agents, np.ones((8, 32, 32), np.float32))
        target.add(agents, np.zeros((8, 6)), np.zeros((8, 3)), np.ones(8), np.ones((8, 32, 32), np.float32),
                   np.zeros((8, 6)), np.zeros(8, bool))
    for name in ("frame_index", "state", "reward", "stamp", "successor", "successor_stamp", "frame_store"):
        assert np.array_equal(getattr(buf, name)[:400], getattr(restored, name)[:400]), name
    with pytest.raises(ValueError, match="capacity"):
        FrameReplayBuffer(1000, 8, 3, 32, 32, 6, 3).load_state_dict(buf.state_dict())


def test_buffer_memory_is_small_for_the_default_run():
    buf = FrameReplayBuffer(20_000, 128, 3, 32, 32, 6, 3)
    assert buf.nbytes < 90 * 2**20


@pytest.mark.parametrize("method", ["sac_ae", "cnn", "drq"])
def test_every_method_updates_its_networks(method):
    torch.manual_seed(0)
    cam = CameraSpec(width=16, height=16)
    agent = SacAeAgent(AgentConfig(method=method, hidden_dim=32), cam, DEFAULT_ACTION_SPEC)
    buf = FrameReplayBuffer(200, 4, 3, 16, 16, 6, 3)
    rng = np.random.default_rng(0)
    buf.start_episodes(np.arange(4), rng.uniform(0, 20, (4, 16, 16)))
    for _ in range(20):
        buf.add(np.arange(4), rng.normal(size=(4, 6)), rng.uniform(-1, 1, (4, 3)), rng.normal(size=4),
                rng.uniform(0, 20, (4, 16, 16)), rng.normal(size=(4, 6)), np.zeros(4, bool))
    conv_before = agent.critic.encoder.convs[0].weight.detach().clone()
    actor_before = agent.actor.trunk[0].weight.detach().clone()
    for _ in range(4):
        info = agent.update(buf.sample(16, agent.device))
    assert all(np.isfinite(v) for v in info.values())
    assert not torch.equal(conv_before, agent.critic.encoder.convs[0].weight)
    assert not torch.equal(actor_before, agent.actor.trunk[0].weight)
    # The actor's convolutions are the critic's (tied), the target's are a lagging copy.
    assert agent.actor.encoder.convs[0].weight is agent.critic.encoder.convs[0].weight
    assert not torch.equal(agent.critic_target.encoder.convs[0].weight, agent.critic.encoder.convs[0].weight)
    assert ("losses/reconstruction" in info) == (method == "sac_ae")


def test_vae_learns_and_freezes():
    rng = np.random.default_rng(0)
    images = np.full((256, 3, 16, 16), 20.0, dtype=np.float32)
    for img in images:  # a box of random depth at a random place
        r, c = rng.integers(0, 12, 2)
        img[:, r:r + 4, c:c + 4] = rng.uniform(2, 10)
    encoder, losses = train_vae(images, 20.0, latent_dim=8, epochs=6, batch_size=64)
    assert losses[-1] < 0.7 * losses[0]
    assert not any(p.requires_grad for p in encoder.parameters())
    agent = SacAeAgent(AgentConfig(method="vae", hidden_dim=32, latent_dim=8), CameraSpec(width=16, height=16),
                       DEFAULT_ACTION_SPEC, vae_encoder=encoder)
    assert agent.act(images[:2], np.zeros((2, 6)), explore=False).shape == (2, 3)


def test_presets_and_flags():
    cfg, agent_cfg, resume, _ = parse_args([])
    assert cfg.preset == "fast" and cfg.method == "sac_ae" and cfg.scenario == "random" and cfg.num_uavs == 8
    assert agent_cfg.critic_tau == 0.01 and agent_cfg.encoder_tau == 0.05
    assert (agent_cfg.hidden_dim, agent_cfg.init_temperature, agent_cfg.n_step) == (1024, 0.01, 5)
    paper, paper_agent, _, _ = parse_args(["--preset", "paper"])
    assert (paper_agent.hidden_dim, paper_agent.init_temperature, paper_agent.n_step) == (1024, 0.1, 1)
    assert (paper.replay_capacity, paper.max_episodes, paper.updates_per_episode, paper.batch_size) == (20000, 200, 400, 128)
    assert paper.num_worlds == 1 and paper.total_updates == 0
    override, _, _, _ = parse_args(["--preset", "paper", "--max-episodes", "3"])
    assert override.max_episodes == 3 and override.updates_per_episode == 400
    _, cnn, _, _ = parse_args(["--method", "cnn", "--critic-lr", "3e-4"])
    assert cnn.method == "cnn" and cnn.critic_lr == 3e-4


def test_camera_grid_changes_the_pixels_not_the_field_of_view():
    cfg, _, _, _ = parse_args(["--preset", "flown-fast", "--camera-grid", "48x32"])
    camera, preset = training_camera(cfg), CAMERA_PRESETS["realsense_d435"]
    assert (camera.width, camera.height) == (48, 32) and (preset.width, preset.height) == (32, 20)
    assert dataclasses.replace(camera, width=preset.width, height=preset.height) == preset  # only the grid moved
    default, _, _, _ = parse_args(["--preset", "flown-fast"])
    assert training_camera(default) == preset
    # The agent's encoder is built for the grid: a 48x32 stack goes through it.
    agent = SacAeAgent(AgentConfig(hidden_dim=32), camera, DEFAULT_ACTION_SPEC)
    depth = torch.zeros(2, camera.frames, camera.height, camera.width)
    assert agent.actor.encoder(depth).shape[0] == 2


def _train_cmd(run_dir, *extra):
    return [sys.executable, "-m", "sitl.train", "--run-dir", str(run_dir), "--num-uavs", "2", "--num-worlds", "2",
            "--image-size", "16", "--hidden-dim", "32", "--batch-size", "16", "--init-steps", "20",
            "--eval-every-updates", "0", "--final-eval-episodes", "2", "--max-episode-steps", "40", *extra]


def _env():
    return {**os.environ, "PYTHONPATH": str(REPO)}


@pytest.mark.parametrize("args, message", [
    (["--num-uavs", "0"], "num_uavs must be an integer in 1..1000, got 0"),
    (["--method", "ppo"], "unknown method 'ppo'"),
    (["--density", "-2"], "density must be > 0"),
    (["--batch-size", "many"], "argument --batch-size: expected an integer, got 'many'"),
    (["--camera", "realsense_d435", "--camera-grid", "48"], "camera_grid must be WIDTHxHEIGHT in pixels"),
    (["--camera", "realsense_d435", "--camera-grid", "48x8"], "camera_grid sides must be 16..256 pixels"),
    (["--camera-grid", "48x32"], "the paper camera's grid is image_size"),
    (["--preset", "flown-fast", "--stage-scale", "1.5,1.5"], "2 stage scale(s) for a recipe of 4 stages (preset flown-fast)"),
    (["--preset", "flown-fast", "--stage-scale", "1.5,0,1,1"], "expected comma-separated numbers > 0"),
    (["--stage-scale", "2"], "preset fast is not a recipe"),
    (["--obstacle-density", "dense"], "obstacle_density: unknown density 'dense'"),
    (["--obstacle-density", "0"], "obstacle_density: density must be > 0"),
    (["--frame-ages", "3,1"], "frame_ages [3, 1] must give one age per stacked frame"),
    (["--frame-ages", "6,1,0", "--frame-stride", "2"], "frame_ages '6,1,0' replace frame_stride"),
])
def test_bad_command_line_values(tmp_path, args, message):
    out = subprocess.run([sys.executable, "-m", "sitl.train", "--run-dir", str(tmp_path / "r"), *args],
                         capture_output=True, text=True, env=_env(), cwd=tmp_path)
    assert out.returncode == 2 and message in out.stderr


def test_run_directory_is_never_overwritten_and_sigkill_resumes(tmp_path):
    run_dir = tmp_path / "run"
    proc = subprocess.Popen(_train_cmd(run_dir, "--total-updates", "100000", "--checkpoint-every-s", "2"),
                            env=_env(), cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    ckpt = run_dir / "checkpoint.pt"
    deadline = time.time() + 120
    while not ckpt.exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.5)
    time.sleep(3)  # let it write at least one more checkpoint
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert ckpt.exists(), proc.stderr.read()
    saved = torch.load(ckpt, weights_only=False)["counters"]
    assert saved["updates"] > 0

    again = subprocess.run(_train_cmd(run_dir, "--total-updates", "10"), capture_output=True, text=True,
                           env=_env(), cwd=tmp_path)
    assert again.returncode == 2 and "already exists" in again.stderr

    # Resume with a finite budget: edit the saved config's budget to end soon after the checkpoint.
    config = json.loads((run_dir / "config.json").read_text())
    config["train"]["total_updates"] = saved["updates"] + 20
    moved = not torch.cuda.is_available()  # then pretend the run was started on a GPU machine
    if moved:
        config["train"]["device"] = "cuda"
    (run_dir / "config.json").write_text(json.dumps(config))
    resume = [sys.executable, "-m", "sitl.train", "--resume", str(run_dir)]
    if moved:
        refused = subprocess.run(resume, capture_output=True, text=True, env=_env(), cwd=tmp_path, timeout=120)
        assert refused.returncode == 2 and "Traceback" not in refused.stderr
        assert "give --device cpu to continue it here" in refused.stderr.strip().splitlines()[-1]
        other = subprocess.run([*resume, "--seed", "3"], capture_output=True, text=True, env=_env(), cwd=tmp_path)
        assert other.returncode == 2 and "not --seed" in other.stderr
        resume += ["--device", "cpu", "--threads", "1"]
    resumed = subprocess.run(resume, capture_output=True, text=True, env=_env(), cwd=tmp_path, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    if moved:  # where it computes is kept for later resumes too
        train = json.loads((run_dir / "config.json").read_text())["train"]
        assert (train["device"], train["threads"]) == ("cpu", 1)
    assert f"resumed from {ckpt}: {saved['updates']} updates" in resumed.stderr
    final = json.loads((run_dir / "final_eval.json").read_text())
    assert final["updates"] == saved["updates"] + 20
    assert (run_dir / "policy.pt").stat().st_size > 0 and (run_dir / "learning_curve.png").exists()


def test_n_step_returns_follow_each_agent_and_stop_at_episode_ends():
    buf = FrameReplayBuffer(capacity=64, num_agents=2, frames=3, height=1, width=1, state_dim=6, action_dim=3, seed=1)
    frame = lambda *v: np.asarray(v, dtype=np.float32).reshape(-1, 1, 1)  # noqa: E731
    buf.start_episodes(np.array([0, 1]), frame(0, 100))
    for t in range(1, 6):  # agent 1 terminates at t = 3, agent 0 runs on (a time-out is not terminal)
        agents = np.array([0, 1]) if t <= 3 else np.array([0])
        rewards = np.array([t, 100 + t][: len(agents)], dtype=float)
        terminated = np.array([False, t == 3][: len(agents)])
        buf.add(agents, np.zeros((len(agents), 6)), np.zeros((len(agents), 3)), rewards,
                frame(*[t, 100 + t][: len(agents)]), np.full((len(agents), 6), t, dtype=float), terminated)
    batch = buf.sample(400, torch.device("cpu"), n_step=3, gamma=0.5)
    for r, disc, nxt_state, nxt_depth in zip(batch["reward"][:, 0], batch["discount"][:, 0], batch["next_state"][:, 0],
                                             batch["next_depth"][:, -1, 0, 0]):
        if r < 100:  # agent 0, transition t0: rewards t0, t0+1, t0+2 while they exist (up to t = 5)
            t0 = next(t for t in range(1, 6) if abs(r - sum(0.5**k * (t + k) for k in range(min(3, 6 - t)))) < 1e-4)
            steps = min(3, 6 - t0)
            assert disc == pytest.approx(0.5**steps) and nxt_state == t0 + steps - 1 and nxt_depth == t0 + steps - 1
        else:  # agent 1 stops at its terminal transition t = 3: no bootstrap after it
            t0 = next(t for t in range(1, 4) if abs(r - sum(0.5**k * (100 + t + k) for k in range(4 - t))) < 1e-4)
            assert disc == 0.0 and nxt_state == 3 and nxt_depth == 103


def test_second_stage_starts_from_a_checkpoint_and_trains_on_mixed_scenes(tmp_path):
    """--init-from: the networks carry over, the provenance adds both stages (and a non-default obstacle
    density), mixed evaluates every scene it mixes."""
    first, second = tmp_path / "stage1", tmp_path / "stage2"
    run = lambda *a: subprocess.run(_train_cmd(*a), capture_output=True, text=True, env=_env(), cwd=tmp_path,  # noqa: E731
                                    timeout=300)
    done = run(first, "--total-updates", "15")
    assert done.returncode == 0, done.stderr
    stage1 = torch.load(first / "checkpoint.pt", weights_only=False)
    done = run(second, "--total-updates", "12", "--scenario", "mixed", "--init-from", str(first),
               "--eval-every-updates", "5", "--eval-episodes", "2", "--select-best",
               "--obstacle-fraction", "0.2", "--obstacle-density", "0.03")
    assert done.returncode == 0, done.stderr
    assert f"initialised from {first / 'checkpoint.pt'}: 15 updates" in done.stderr
    final = json.loads((second / "final_eval.json").read_text())
    assert final["updates"] == 27 and final["stages"][0]["updates"] == 15 and final["stages"][1]["updates"] == 12
    assert final["wall_time_s"] > final["stages"][1]["wall_s"]
    assert final["evaluation"]["scenario"] == "random" and final["evaluation_circle"]["scenario"] == "circle"
    assert final["evaluation_obstacles"]["scenario"] == "obstacles" and final["obstacle_density"] == "0.03"
    # --select-best: every validation was kept, the last networks (12 updates, between validations) were
    # validated too, and the exported networks are the best one's.
    validations = json.loads((second / "snapshots" / "validation.json").read_text())
    assert [v["updates"] for v in validations] == [5, 10, 12]
    assert (second / "snapshots" / "agent_12.pt").exists()
    best = max(validations, key=lambda v: (v["score"], v["updates"]))
    assert final["selected_snapshot"]["updates"] == best["updates"]
    # It really continued from stage 1's weights: 12 updates of Adam at lr 1e-3 move each weight by at most
    # ~0.012 (~0.024 for the shared encoder, which the decoder's optimiser also steps), while a fresh
    # initialisation would differ by ~0.1 everywhere.
    stage2 = torch.load(second / "checkpoint.pt", weights_only=False)
    for key, w1 in stage1["agent"]["model"].items():
        if "critic" in key and key.endswith("weight") and "target" not in key:
            assert (stage2["agent"]["model"][key] - w1).abs().max() < 0.03, key

    # A third stage from a validated snapshot, at another learning rate than the optimiser states were saved with.
    snapshot = second / "snapshots" / "agent_5.pt"
    done = run(tmp_path / "stage3", "--total-updates", "5", "--init-from", str(snapshot), "--actor-lr", "2e-4",
               "--critic-lr", "3e-4")
    assert done.returncode == 0, done.stderr
    assert f"initialised from {snapshot}: 20 updates" in done.stderr  # 15 of stage 1 + 5 of stage 2
    final3 = json.loads((tmp_path / "stage3" / "final_eval.json").read_text())
    assert final3["updates"] == 25 and final3["stages"][0]["updates"] == 20
    assert final3["stages"][0]["transitions"] == stage1["counters"]["transitions"] + validations[0]["counters"][
        "transitions"]
    optimizers = torch.load(tmp_path / "stage3" / "checkpoint.pt", weights_only=False)["agent"]["optimizers"]
    assert optimizers["actor_optimizer"]["param_groups"][0]["lr"] == pytest.approx(2e-4)
    assert optimizers["critic_optimizer"]["param_groups"][0]["lr"] == pytest.approx(3e-4)

    wrong = run(tmp_path / "stage2b", "--total-updates", "10", "--hidden-dim", "64", "--init-from", str(first))
    assert wrong.returncode == 2 and "do not match this run's agent settings" in wrong.stderr
    assert not (tmp_path / "stage2b").exists()
    missing = run(tmp_path / "stage2c", "--total-updates", "10", "--init-from", str(tmp_path / "nowhere"))
    assert missing.returncode == 2 and "no such checkpoint" in missing.stderr
    exported = run(tmp_path / "stage2d", "--total-updates", "10", "--init-from", str(first / "policy.pt"))
    assert exported.returncode == 2 and "an exported policy.pt cannot be trained further" in exported.stderr
    assert not (tmp_path / "stage2d").exists()


def test_snapshot_counters_of_older_validation_rows_are_scaled_from_the_run(tmp_path):
    """Rows written before validation.json kept counters: updates and wall time are exact, the rest scaled."""
    run_dir = tmp_path / "run"
    (run_dir / "snapshots").mkdir(parents=True)
    counters = {"updates": 8000, "env_steps": 8100, "transitions": 200_000, "episodes": 320, "wall_s": 2400.0}
    earlier = {"updates": 12_000, "env_steps": 12_100, "transitions": 250_000, "episodes": 870, "wall_s": 3000.0}
    torch.save({"counters": counters, "initial_stage": earlier}, run_dir / "checkpoint.pt")
    rows = [{"updates": 2000, "wall_s": 610.0, "score": 0.5},
            {"updates": 4000, "wall_s": 1200.0, "score": 0.7, "counters": {"env_steps": 4050, "transitions": 99_000,
                                                                          "episodes": 150}}]
    (run_dir / "snapshots" / "validation.json").write_text(json.dumps(rows))
    old = snapshot_counters(run_dir / "snapshots" / "agent_2000.pt")
    assert old == {"updates": 14_000, "wall_s": 3610.0, "env_steps": 12_100 + 2025, "transitions": 250_000 + 50_000,
                   "episodes": 870 + 80}
    new = snapshot_counters(run_dir / "snapshots" / "agent_4000.pt")
    assert new["transitions"] == 250_000 + 99_000 and new["episodes"] == 870 + 150 and new["updates"] == 16_000
    with pytest.raises(ValueError, match="not a snapshot of a run directory"):
        snapshot_counters(run_dir / "snapshots" / "agent_3000.pt")


@pytest.mark.parametrize("preset", ["fast", "paper"])
def test_help_shows_the_defaults_a_run_uses(preset, capsys):
    """--help's '(default: X)' of every flag is the value of the resolved config (the preset applied)."""
    import dataclasses

    from sitl.learn.cli import build_parser, parse_args as parse

    argv = [] if preset == "fast" else ["--preset", preset]
    with pytest.raises(SystemExit):
        parse([*argv, "--help"])
    printed = capsys.readouterr().out
    text = " ".join(printed.split())
    # argparse wraps at spaces and after hyphens, by the terminal's width: compare without whitespace.
    squeezed = "".join(printed.split())
    cfg, agent_cfg, _, _ = parse(argv)
    values = {**dataclasses.asdict(agent_cfg), **dataclasses.asdict(cfg)}
    checked = 0
    for action in build_parser(preset)._actions:  # the parser parse() builds for these arguments
        if action.dest in values:
            shown = " ".join(action.help.split())
            assert shown.endswith(f"(default: {values[action.dest]})"), (action.dest, shown)
            assert "".join(shown.split()) in squeezed  # and --help printed it
            checked += 1
    assert checked == len(values)
    assert f"(default: {agent_cfg.init_temperature})" in text and f"(default: {agent_cfg.n_step})" in text


#: The one action a test teacher always commands (unit action space).
TEACHER_TARGET = np.array([0.6, -0.4, 0.3], dtype=np.float32)


def _teacher_buffer(some_unlabelled: bool) -> FrameReplayBuffer:
    """16 steps of 4 UAVs with random 16x16 frames, each labelled with :data:`TEACHER_TARGET`
    (``some_unlabelled``: UAV 3's label missing on every other step)."""
    rng = np.random.default_rng(0)
    buf = FrameReplayBuffer(64, 4, 3, 16, 16, 6, 3)
    buf.start_episodes(np.arange(4), rng.uniform(0, 20, (4, 16, 16)))
    for step in range(16):
        valid = np.array([True, True, True, step % 2 == 0 or not some_unlabelled])
        buf.add(np.arange(4), rng.normal(size=(4, 6)), rng.uniform(-1, 1, (4, 3)), rng.normal(size=4),
                rng.uniform(0, 20, (4, 16, 16)), rng.normal(size=(4, 6)), np.zeros(4, bool),
                np.tile(TEACHER_TARGET, (4, 1)), valid)
    return buf


def test_teacher_term_pulls_the_actor_towards_the_teachers_actions_only_where_they_hold():
    """Teacher-guided SAC+AE: with the behaviour-cloning weight on, the actor's mean action moves
    to the teacher's on the rows the teacher labelled; with it off, the paper's update is unchanged."""
    cam = CameraSpec(width=16, height=16)
    buf = _teacher_buffer(some_unlabelled=True)
    target = TEACHER_TARGET
    assert buf.teacher_valid[:buf.size].mean() == pytest.approx(14 / 16)
    batch = buf.sample(64, torch.device("cpu"), with_teacher=True)

    def distance_after(weight: float) -> float:
        torch.manual_seed(0)
        agent = SacAeAgent(AgentConfig(hidden_dim=32, actor_update_freq=1), cam, DEFAULT_ACTION_SPEC)
        pixels, state = agent._inputs(batch["depth"], batch["state"])
        for _ in range(60):
            info = agent.update_actor_and_alpha(pixels, state, batch["teacher_action"], batch["teacher_valid"], weight)
        assert ("losses/teacher_bc" in info) == (weight > 0)
        with torch.no_grad():
            mean = agent.actor.deterministic(pixels, state)
        return float((mean - torch.from_numpy(target)).pow(2).sum(-1).mean())

    assert distance_after(5.0) < 0.2 * distance_after(0.0)


def test_trainer_labels_with_privileged_orca_outside_circle_worlds_and_the_weight_decays(tmp_path):
    from sitl.learn.config import PRESETS, resolve_configs
    from sitl.learn.trainer import make_trainer

    cfg, agent_cfg = resolve_configs(
        {**PRESETS["flown"]["train"], "preset": "flown", "scenario": "mixed", "circle_fraction": 0.5,
         "obstacle_fraction": 0.5, "num_worlds": 4, "total_updates": 6, "init_steps": 100, "batch_size": 16,
         "eval_every_updates": 0, "final_eval_episodes": 0, "teacher_bc_weight": 2.0, "teacher_bc_updates": 12},
        {"hidden_dim": 32})
    trainer = make_trainer(cfg, agent_cfg, tmp_path)
    assert trainer.teacher_weight() == 2.0
    trainer.run()
    assert trainer.teacher_weight() == pytest.approx(1.0)  # 6 of 12 updates done
    buf, env = trainer.buffer, trainer.env
    assert trainer.teacher.see_obstacles
    valid = buf.teacher_valid[:buf.size, 0]
    assert 0 < valid.mean() < 1  # circle worlds were left out, the obstacle worlds labelled
    circle_rows = np.repeat(env.world_is_circle, env.uavs_per_world)
    newest = (buf._next - 1 - np.arange(env.num_agents)) % buf.capacity  # the last step's rows, newest first
    assert np.array_equal(buf.teacher_valid[newest, 0] > 0, ~circle_rows[::-1])
    labels = buf.teacher_action[:buf.size][valid > 0]
    assert np.abs(labels).max() <= 1.0 and labels[:, 0].max() > 0  # unit actions; ORCA flies forward


def _small_teacher_run(tmp_path, **train):
    """Four updates of teacher-guided SAC in the flown mix (half the worlds among obstacles), ``train`` on top."""
    from sitl.learn.config import PRESETS, resolve_configs
    from sitl.learn.trainer import make_trainer

    cfg, agent_cfg = resolve_configs(
        {**PRESETS["flown"]["train"], "preset": "flown", "scenario": "mixed", "obstacle_fraction": 0.5,
         "num_worlds": 4, "total_updates": 4, "init_steps": 60, "batch_size": 16, "eval_every_updates": 0,
         "final_eval_episodes": 0, "teacher_bc_weight": 1.0, **train},
        {"hidden_dim": 32})
    trainer = make_trainer(cfg, agent_cfg, tmp_path)
    trainer.run()
    return trainer


def test_the_circle_teacher_labels_circle_worlds_with_orca_that_keeps_right_of_what_it_sees(tmp_path):
    """``circle_teacher_right``: circle worlds are labelled too, by the camera-limited right-of-way ORCA
    (its commands, not privileged ORCA's), and the other worlds keep privileged ORCA's labels."""
    from sitl.eval.orca import RIGHT_HAND_PARAMS
    from sitl.learn.config import resolve_configs

    trainer = _small_teacher_run(tmp_path, circle_fraction=0.5, circle_teacher_right=True)
    assert trainer.buffer.teacher_valid[:trainer.buffer.size].min() == 1.0  # every world labelled
    env = trainer.env
    assert trainer.circle_teacher.camera is not None and trainer.circle_teacher.params == RIGHT_HAND_PARAMS
    assert env.world_is_circle.any() and not env.world_is_circle.all()  # this seed flies both kinds now
    circle = np.repeat(env.world_is_circle, env.uavs_per_world) & env.acting
    commands = trainer.teacher_commands()
    np.testing.assert_allclose(commands[circle], trainer.circle_teacher.act_env(env, acting=circle)[circle])
    np.testing.assert_allclose(commands[~circle], trainer.teacher.act_env(env)[~circle])
    with pytest.raises(ValueError, match="circle_teacher_right needs a teacher"):
        resolve_configs({"circle_teacher_right": True}, {})


def test_the_circle_teachers_turn_is_a_setting(tmp_path):
    """``circle_teacher_right_deg``: the circle worlds' teacher turns that far (the ``orca-fov-right80`` reference's
    80 deg here) and the run's provenance says so; a turn outside [0, 90] deg is refused."""
    from sitl.eval.orca import WIDE_RIGHT_HAND_PARAMS, baseline_orca
    from sitl.learn.config import resolve_configs

    trainer = _small_teacher_run(tmp_path, circle_fraction=0.5, circle_teacher_right=True, circle_teacher_right_deg=80.0)
    assert trainer.circle_teacher.params == WIDE_RIGHT_HAND_PARAMS == baseline_orca("orca-fov-right80")[0]
    assert trainer.circle_teacher.camera is not None
    provenance = json.loads((trainer.finish().parent / "final_eval.json").read_text())
    assert provenance["teacher"]["circle_worlds"]["orca"]["right_hand_deg"] == 80.0
    assert provenance["teacher"]["circle_worlds"]["kind"].startswith("orca-fov-right80 ")  # the reference flown alone
    with pytest.raises(ValueError, match="circle_teacher_right_deg"):
        resolve_configs({"method": "distill", "circle_teacher_right": True, "circle_teacher_right_deg": 91.0}, {})
    with pytest.raises(ValueError, match="needs circle_teacher_right"):
        resolve_configs({"circle_teacher_right_deg": 80.0}, {})  # a turn for a teacher the run does not have


def test_a_camera_limited_teacher_labels_the_other_worlds_with_what_each_uav_sees(tmp_path):
    """``teacher_camera_limited``: the worlds other than circles are labelled by orca-fov that sees the
    obstacles (each UAV knows only the UAVs in its camera's view), and the provenance says so."""
    from sitl.learn.config import resolve_configs

    trainer = _small_teacher_run(tmp_path, circle_fraction=0.0, teacher_camera_limited=True)
    teacher, env = trainer.teacher, trainer.env
    assert teacher.camera is not None and teacher.see_obstacles
    assert trainer.buffer.teacher_valid[:trainer.buffer.size].min() == 1.0  # no circle worlds: every row labelled
    np.testing.assert_allclose(trainer.teacher_commands(), teacher.act_env(env))  # this step's labels
    labels = trainer.buffer.teacher_action[:trainer.buffer.size]
    assert np.abs(labels).max() <= 1.0 and labels[:, 0].max() > 0  # unit actions; ORCA flies forward
    with pytest.raises(ValueError, match="teacher_camera_limited needs a teacher"):
        resolve_configs({"teacher_camera_limited": True}, {})


def test_the_teachers_look_ahead_and_margin_are_options_recorded_in_the_provenance(tmp_path):
    """``teacher_time_horizon_s`` / ``teacher_radius_margin_m``: the ORCA that labels the worlds other than circles
    has them (its labels are that ORCA's), policy.json's provenance names them, and a bad value is refused."""
    from sitl.eval.orca import OrcaController, OrcaParams
    from sitl.learn.config import resolve_configs

    trainer = _small_teacher_run(tmp_path, circle_fraction=0.0, teacher_time_horizon_s=5.0,
                                 teacher_radius_margin_m=0.3)
    params = OrcaParams(time_horizon_s=5.0, radius_margin_m=0.3)
    assert trainer.teacher.params == params and trainer.teacher.see_obstacles
    same = OrcaController.for_env(trainer.env, params, see_obstacles=True)  # stateless: the same labels now
    np.testing.assert_allclose(trainer.teacher_commands(), same.act_env(trainer.env))
    provenance = json.loads((trainer.finish().parent / "final_eval.json").read_text())
    assert provenance["teacher"]["orca"]["time_horizon_s"] == 5.0
    assert provenance["teacher"]["orca"]["radius_margin_m"] == 0.3
    for field, bad in (("teacher_time_horizon_s", 0.1), ("teacher_time_horizon_s", math.nan),
                       ("teacher_radius_margin_m", -0.1)):
        with pytest.raises(ValueError, match=f"{field} must be in"):
            resolve_configs({field: bad}, {})


def test_validations_fly_their_own_time_limit_and_record_it(tmp_path):
    """``validation_steps``: the training episodes keep theirs; each validation row says which it flew."""
    from sitl.learn.config import resolve_configs
    from sitl.learn.trainer import make_trainer

    rows = {}
    for steps in (0, 3):
        cfg, agent_cfg = resolve_configs(
            {"num_uavs": 2, "num_worlds": 2, "image_size": 16, "batch_size": 16, "init_steps": 20, "total_updates": 4,
             "eval_every_updates": 4, "eval_episodes": 4, "select_best": True, "final_eval_episodes": 0,
             "max_episode_steps": 40, "validation_steps": steps}, {"hidden_dim": 32})
        trainer = make_trainer(cfg, agent_cfg, tmp_path / f"v{steps}")
        trainer.run()
        [rows[steps]] = json.loads((tmp_path / f"v{steps}" / "snapshots" / "validation.json").read_text())
    assert rows[0]["max_episode_steps"] == 40 and rows[3]["max_episode_steps"] == 3
    # 0.3 s is too short to reach a goal: every UAV that did not collide timed out, so none succeeded
    assert rows[3]["random"]["success_rate"] == 0.0


def test_training_flies_the_harsher_noise_and_records_it_evaluations_fly_the_occlusion_shadow(tmp_path):
    """Training and the trainer's validations keep the noise every recipe was trained with (holes on both
    sides of depth edges, TRAINING_STEREO_NOISE), and the policy file records it; the protocols fly
    the sensor's occlusion shadow (StereoNoise's default). The file records the response ranges its training
    worlds drew too (here with a command delay)."""
    import dataclasses

    from companion.policy import load_policy
    from sitl.eval.flown import flown_cells
    from sitl.learn.config import TRAINING_STEREO_NOISE, make_sim_config, resolve_configs
    from sitl.learn.trainer import make_trainer
    from sitl.sim.camera import StereoNoise

    assert TRAINING_STEREO_NOISE == dataclasses.replace(StereoNoise(), edge_holes="both")
    assert all(cell.settings.noise_model.edge_holes == "shadow" for cell in flown_cells(1))
    cfg, agent_cfg = resolve_configs(
        {"camera": "realsense_d435", "camera_noise": True, "num_uavs": 2, "num_worlds": 2, "batch_size": 16,
         "init_steps": 20, "total_updates": 2, "eval_every_updates": 2, "eval_episodes": 2,
         "final_eval_episodes": 0, "max_episode_steps": 20, "randomize_dynamics": True,
         "response": "command_delay_s=0:0.2"}, {"hidden_dim": 32})
    for scenario in (None, "random"):  # training worlds and the trainer's validations
        assert make_sim_config(cfg, 1, scenario_name=scenario).camera_noise.edge_holes == "both"
    make_trainer(cfg, agent_cfg, tmp_path / "run").run()
    provenance = load_policy(tmp_path / "run" / "policy.pt").metadata["provenance"]
    assert provenance["camera_noise_model"] == dataclasses.asdict(dataclasses.replace(TRAINING_STEREO_NOISE,
                                                                                      min_range_m=0.2))
    assert provenance["dynamics_randomization"]["command_delay_s"] == [0.0, 0.2]
    assert provenance["dynamics_randomization"]["tau_horizontal_s"] == [0.15, 0.5]


def test_camera_noise_edges_trains_and_validates_with_the_occlusion_shadow_and_refuses_an_unknown_model():
    """``--camera-noise-edges shadow``: training worlds and validations fly the evaluations' edge holes,
    the rest of the training noise unchanged; an unknown model is a one-line error, not a run."""
    import dataclasses

    from sitl.learn.config import TRAINING_STEREO_NOISE, make_sim_config, resolve_configs

    values = {"camera": "realsense_d435", "camera_noise": True, "total_updates": 2}
    cfg, _ = resolve_configs({**values, "camera_noise_edges": "shadow"}, {})
    for scenario in (None, "random", "obstacles"):
        noise = make_sim_config(cfg, 1, scenario_name=scenario).camera_noise
        assert noise == dataclasses.replace(TRAINING_STEREO_NOISE, edge_holes="shadow", min_range_m=0.2)
    with pytest.raises(ValueError, match="camera_noise_edges"):
        resolve_configs({**values, "camera_noise_edges": "left"}, {})


def test_imitation_update_moves_the_actors_mean_and_its_convolutions_towards_the_teacher():
    """The distill method's update: the actor's mean action converges on the teacher's labels, and
    the convolutions (for SAC+AE the critic's alone) learn from that loss."""
    cam = CameraSpec(width=16, height=16)
    target = TEACHER_TARGET
    batch = _teacher_buffer(some_unlabelled=False).sample(64, torch.device("cpu"), with_teacher=True)
    torch.manual_seed(0)
    agent = SacAeAgent(AgentConfig(method="distill", hidden_dim=32), cam, DEFAULT_ACTION_SPEC)
    convs = [p.detach().clone() for p in agent.actor.encoder.convs.parameters()]
    critic_q = [p.detach().clone() for p in agent.critic.q1.parameters()]
    pixels, state = agent._inputs(batch["depth"], batch["state"])

    def distance() -> float:
        with torch.no_grad():
            return float((agent.actor.deterministic(pixels, state) - torch.from_numpy(target)).pow(2).sum(-1).mean())

    before = distance()
    for _ in range(60):
        info = agent.update(batch)
    assert set(info) == {"losses/imitation"} and distance() < 0.05 * before
    assert any(not torch.equal(a, b) for a, b in zip(convs, agent.actor.encoder.convs.parameters()))
    assert all(torch.equal(a, b) for a, b in zip(critic_q, agent.critic.q1.parameters()))  # no critic is trained


def _whole_pixel_offset(out: torch.Tensor, x: torch.Tensor, pad: int) -> tuple[int, int] | None:
    """The (dy, dx) crop of the replicate-padded ``x`` that ``out`` is, if any (one sample, [C, H, W])."""
    h, w = x.shape[-2:]
    padded = torch.nn.functional.pad(x.unsqueeze(0), (pad, pad, pad, pad), mode="replicate")[0]
    for dy in range(2 * pad + 1):
        for dx in range(2 * pad + 1):
            if torch.allclose(out, padded[:, dy:dy + h, dx:dx + w], atol=1e-5):
                return dy, dx
    return None


def test_random_shift_moves_each_depth_stack_by_whole_pixels_within_the_pad():
    """DrQ's shift on the D435's non-square 32x20 grid: every sample is an exact crop of the replicate-padded
    stack (no interpolation blur), at its own offset."""
    from sitl.learn.agent import random_shift

    torch.manual_seed(0)
    x = torch.rand(16, 3, 20, 32)
    out = random_shift(x, 2)
    offsets = [_whole_pixel_offset(out[i], x[i], 2) for i in range(len(x))]
    assert None not in offsets
    assert len(set(offsets)) > 2  # each sample draws its own offset


def test_distill_shift_px_trains_the_student_on_shifted_stacks():
    """``distill_shift_px``: the imitation loss sees each stack shifted by up to that many pixels; 0 (the
    default) sees it as rendered; negative values are refused."""
    cam = CameraSpec(width=16, height=16)
    batch = _teacher_buffer(some_unlabelled=False).sample(32, torch.device("cpu"), with_teacher=True)
    for px in (0, 1):
        torch.manual_seed(0)
        agent = SacAeAgent(AgentConfig(method="distill", hidden_dim=32, distill_shift_px=px), cam, DEFAULT_ACTION_SPEC)
        seen = []
        imitate = agent.update_imitation

        def recording_imitation(pixels, *rest):  # the real update, with its input kept for the check
            seen.append(pixels)
            return imitate(pixels, *rest)

        agent.update_imitation = recording_imitation
        agent.update(batch)
        rendered, _ = agent._inputs(batch["depth"], batch["state"])
        offsets = {_whole_pixel_offset(seen[0][i], rendered[i], px) for i in range(len(rendered))}
        if px == 0:
            assert offsets == {(0, 0)}  # as rendered
        else:
            assert None not in offsets and len(offsets) > 1  # whole-pixel shifts, drawn per sample
    with pytest.raises(ValueError, match="distill_shift_px"):
        AgentConfig(method="distill", distill_shift_px=-1)


def test_distill_trainer_labels_every_world_and_hands_over_from_teacher_to_student(tmp_path):
    """DAgger: obstacle worlds are labelled too (the teacher sees the poles), and beta falls from 1 to
    0 over dagger_beta_updates, after which the UAVs fly the student's deterministic commands."""
    from sitl.learn.config import PRESETS, resolve_configs
    from sitl.learn.trainer import make_trainer

    cfg, agent_cfg = resolve_configs(
        {**PRESETS["flown"]["train"], "preset": "flown", "method": "distill", "scenario": "mixed",
         "circle_fraction": 0.0, "obstacle_fraction": 1.0, "num_worlds": 4, "total_updates": 40, "init_steps": 64,
         "batch_size": 16, "eval_every_updates": 0, "final_eval_episodes": 0, "dagger_beta_updates": 20},
        {"hidden_dim": 32})
    trainer = make_trainer(cfg, agent_cfg, tmp_path)
    assert trainer.dagger_beta() == 1.0 and trainer.teacher_weight() == 1.0
    trainer.run()
    assert trainer.dagger_beta() == 0.0
    buf, env = trainer.buffer, trainer.env
    assert env.world_has_obstacles.all()  # every episode among obstacles...
    assert buf.teacher_valid[:buf.size].min() == 1.0  # ...and every transition labelled
    labels = buf.teacher_action[:buf.size]
    assert np.abs(labels).max() <= 1.0 and labels[:, 0].max() > 0  # unit actions; ORCA flies forward
    # With beta at 0 the replay's newest actions are the student's own, not the teacher's.
    newest = (buf._next - 1 - np.arange(env.num_agents)) % buf.capacity
    assert not np.allclose(buf.action[newest], buf.teacher_action[newest], atol=1e-3)
    assert trainer.teacher.see_obstacles


def test_distill_data_scale_collects_more_labelled_transitions_per_update_for_the_student_only(tmp_path):
    """``distill_data_scale`` F: a distill run makes the same updates from F times the transitions, in a buffer
    F times larger; other methods ignore it (a recipe's SAC stages keep their own ratio)."""
    from sitl.learn.config import PRESETS, resolve_configs
    from sitl.learn.trainer import data_scale, make_trainer

    base = {**PRESETS["flown"]["train"], "preset": "flown", "method": "distill", "scenario": "random",
            "num_worlds": 2, "total_updates": 24, "init_steps": 32, "batch_size": 16, "eval_every_updates": 0,
            "final_eval_episodes": 0, "updates_per_env_step": 0.5, "replay_capacity": 5_000}
    collected = {}
    for scale in (1.0, 2.0):
        cfg, agent_cfg = resolve_configs({**base, "distill_data_scale": scale}, {"hidden_dim": 32})
        trainer = make_trainer(cfg, agent_cfg, tmp_path / f"x{scale:g}")
        trainer.run()
        assert trainer.agent.updates == 24 and trainer.buffer.capacity == round(5_000 * scale)
        collected[scale] = trainer.counters["env_steps"]
    # 24 updates at 0.5 per step need 48 environment steps after the random start; at F = 2, 96.
    assert collected[2.0] - collected[1.0] == pytest.approx(48, abs=2)
    cfg, _ = resolve_configs({**base, "method": "cnn", "distill_data_scale": 4.0}, {})
    assert data_scale(cfg) == 1.0
    with pytest.raises(ValueError, match="distill_data_scale"):
        resolve_configs({**base, "distill_data_scale": 0.5}, {})


def test_frozen_convolutions_stay_put_and_a_delayed_actor_waits_for_its_critic():
    """SAC on fixed features (``freeze_convs``, the cnn method only): the critic learns, the convolutions
    do not; with ``actor_delay_updates`` the actor and temperature stay put for that many updates."""
    torch.manual_seed(0)
    cam = CameraSpec(width=16, height=16)
    agent = SacAeAgent(AgentConfig(method="cnn", hidden_dim=32, freeze_convs=True, actor_delay_updates=4,
                                   actor_update_freq=1), cam, DEFAULT_ACTION_SPEC)
    batch = _teacher_buffer(some_unlabelled=False).sample(16, agent.device)
    convs = [p.detach().clone() for p in agent.critic.encoder.convs.parameters()]
    actor = agent.actor.trunk[0].weight.detach().clone()
    critic = agent.critic.q1[0].weight.detach().clone()
    for _ in range(4):
        info = agent.update(batch)
    assert "losses/actor" not in info and torch.equal(actor, agent.actor.trunk[0].weight)
    assert agent.alpha.item() == pytest.approx(AgentConfig().init_temperature)
    assert not torch.equal(critic, agent.critic.q1[0].weight)
    info = agent.update(batch)
    assert "losses/actor" in info and not torch.equal(actor, agent.actor.trunk[0].weight)
    assert all(torch.equal(a, b) for a, b in zip(convs, agent.critic.encoder.convs.parameters()))
    with pytest.raises(ValueError, match="freeze_convs is for the cnn method"):
        AgentConfig(method="sac_ae", freeze_convs=True)


def test_a_distilled_student_hands_over_to_sac_with_its_convolutions_and_a_fresh_target_critic(tmp_path):
    """The flown-distill recipe's hand-over: a cnn run started from a distill run's checkpoint takes the
    student's networks (not its optimisers), its target critic starts as its critic, and with frozen
    convolutions the student's features are what the actor keeps seeing."""
    from sitl.learn.config import PRESETS, resolve_configs
    from sitl.learn.trainer import make_trainer

    common = {**PRESETS["flown"]["train"], "preset": "flown", "scenario": "random", "num_worlds": 2,
              "init_steps": 32, "batch_size": 16, "eval_every_updates": 0, "final_eval_episodes": 0}
    cfg, agent_cfg = resolve_configs({**common, "method": "distill", "total_updates": 6}, {"hidden_dim": 32})
    student = make_trainer(cfg, agent_cfg, tmp_path / "student")
    student.run()
    cfg, agent_cfg = resolve_configs({**common, "method": "cnn", "total_updates": 6,
                                      "init_from": str(tmp_path / "student")},
                                     {"hidden_dim": 32, "freeze_convs": True, "actor_delay_updates": 3})
    sac = make_trainer(cfg, agent_cfg, tmp_path / "sac")
    convs = [p.detach().clone() for p in student.agent.critic.encoder.convs.parameters()]
    assert all(torch.equal(a, b) for a, b in zip(convs, sac.agent.actor.encoder.convs.parameters()))
    assert all(torch.equal(a, b) for a, b in zip(sac.agent.critic.parameters(), sac.agent.critic_target.parameters()))
    assert not all(torch.equal(a, b) for a, b in zip(student.agent.critic_target.encoder.parameters(),
                                                     sac.agent.critic_target.encoder.parameters()))
    sac.run()
    assert sac.initial_stage["updates"] == 6 and sac.agent.updates == 6
    assert all(torch.equal(a, b) for a, b in zip(convs, sac.agent.critic.encoder.convs.parameters()))
