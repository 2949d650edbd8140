"""sitl.learn.average: a stage's snapshots averaged into one policy file that flies."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from companion.policy import load_policy
from sitl.learn.average import average_state_dicts

REPO = Path(__file__).resolve().parent.parent


def _run(tmp_path, *args):
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, cwd=tmp_path, timeout=300,
                          env={**os.environ, "PYTHONPATH": str(REPO)})


def test_mean_of_floats_first_of_integers_and_same_networks_only():
    a = {"w": torch.tensor([1.0, 2.0]), "n": torch.tensor(3)}
    b = {"w": torch.tensor([3.0, 6.0]), "n": torch.tensor(7)}
    mean = average_state_dicts([a, b])
    assert torch.equal(mean["w"], torch.tensor([2.0, 4.0])) and mean["w"].dtype == torch.float32
    assert int(mean["n"]) == 3
    with pytest.raises(ValueError, match="different networks"):
        average_state_dicts([a, {"w": torch.zeros(2)}])
    with pytest.raises(ValueError, match="nothing"):
        average_state_dicts([])


def test_averaged_policy_holds_the_mean_weights_and_flies_an_evaluation_cell(tmp_path):
    run_dir = tmp_path / "run"
    done = _run(tmp_path, "-m", "sitl.train", "--run-dir", str(run_dir), "--num-uavs", "2", "--num-worlds", "2",
                "--image-size", "16", "--hidden-dim", "32", "--batch-size", "16", "--init-steps", "20",
                "--max-episode-steps", "40", "--total-updates", "12", "--eval-every-updates", "4",
                "--eval-episodes", "2", "--select-best", "--final-eval-episodes", "2")
    assert done.returncode == 0, done.stderr

    out = tmp_path / "avg" / "policy.pt"
    done = _run(tmp_path, "-m", "sitl.learn.average", str(run_dir), "--out", str(out), "--updates", "4,12",
                "--eval", "paper:random-medium", "--eval-episodes", "2", "--threads", "1")
    assert done.returncode == 0, done.stderr
    assert "the mean of 2 snapshots (4, 12 updates)" in done.stdout
    assert "paper:random-medium: success" in done.stdout
    assert (tmp_path / "avg" / "eval" / "cells" / "paper-random-medium.json").is_file()

    loaded = load_policy(out)
    averaged = loaded.metadata["provenance"]["averaged_snapshots"]
    assert averaged["updates"] == [4, 12]
    assert not any(key.startswith("evaluation") for key in loaded.metadata["provenance"])
    # The flown actor's weights are the snapshots' mean, tensor by tensor.
    snaps = [torch.load(run_dir / "snapshots" / f"agent_{u}.pt", weights_only=True) for u in (4, 12)]
    flown = torch.jit.load(str(out)).state_dict()
    compared = 0
    for key, value in flown.items():
        source = "actor." + key.removeprefix("policy.")
        if key.startswith("policy.") and source in snaps[0]:
            assert torch.allclose(value, (snaps[0][source] + snaps[1][source]) / 2, atol=1e-6), key
            compared += 1
    assert compared >= 10
    # The snapshots differ, so the average is neither of them.
    assert not torch.equal(snaps[0]["actor.trunk.0.weight"], snaps[1]["actor.trunk.0.weight"])


def test_bad_input_is_one_line_and_exit_2(tmp_path):
    done = _run(tmp_path, "-m", "sitl.learn.average", str(tmp_path / "nope"), "--out", str(tmp_path / "p.pt"))
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [f"error: {tmp_path / 'nope'}: not a training run directory "
                                                "(no config.json)"]
    assert not (tmp_path / "p.pt").exists()
    done = _run(tmp_path, "-m", "sitl.learn.average", str(tmp_path), "--out", str(tmp_path / "p.pt"),
                "--eval", "paper:nowhere")
    assert done.returncode == 2 and "unknown evaluation cell(s) paper:nowhere" in done.stderr
