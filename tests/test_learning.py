"""SAC+AE learns: a UAV that must learn to fly fast and straight to reach its goal in time.

The task (one UAV in open space, circle scenario of radius 3 m: the goal 6 m ahead, 4 s
to get within 1.5 m of it) is failed by the untrained policy, whose mean command is the
middle of the action box (1 m/s forward, measured: success 0), and by any policy that
wanders; it is solved by flying at the goal at >= 1.5 m/s while holding heading and
altitude. The
whole training stack runs for real: vectorised rollouts, the frame replay buffer, the
critic, actor, temperature and decoder updates, evaluation on unseen seeds and the export
to a policy file. If any of them is broken, success stays near zero.
"""

from __future__ import annotations

import json

from companion.policy import load_policy
from sitl.learn.cli import parse_args
from sitl.learn.trainer import make_trainer


def test_one_uav_learns_to_reach_its_goal(tmp_path):
    cfg, agent_cfg, _, _ = parse_args([
        "--scenario", "circle", "--circle-radius-m", "3", "--num-uavs", "1", "--num-worlds", "16",
        "--image-size", "16", "--hidden-dim", "128", "--max-episode-steps", "40", "--arrival-radius-m", "1.5",
        "--init-steps", "500", "--total-updates", "800",
        "--eval-every-updates", "0", "--final-eval-episodes", "50", "--seed", "1",
        "--run-dir", str(tmp_path),
    ])
    trainer = make_trainer(cfg, agent_cfg, tmp_path)
    before = trainer.evaluate(50)["circle"]["success_rate"]
    policy_path = trainer.run()
    after = json.loads((tmp_path / "final_eval.json").read_text())["evaluation"]["success_rate"]
    print(f"success before training {before:.2f}, after {after:.2f}")
    assert before <= 0.1
    assert after >= 0.8
    assert load_policy(policy_path).metadata["provenance"]["evaluation"]["success_rate"] == after
