"""sitl.learn.ensemble: policy files flown as one by averaging their actions."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import torch
from torch import nn

from companion.policy import build_metadata, load_policy, save_policy
from companion.spec import DEFAULT_ACTION_SPEC, STATE_DIM, CameraSpec
from sitl.learn.ensemble import build_ensemble

REPO = Path(__file__).resolve().parent.parent
CAMERA = CameraSpec(width=16, height=10, hfov_deg=87.0, vfov_deg=58.0, max_range_m=10.0)


class _Linear(nn.Module):
    """A deterministic stand-in network: tanh of a fixed linear map, scaled into the action bounds."""

    def __init__(self, seed: int) -> None:
        super().__init__()
        torch.manual_seed(seed)
        self.depth = nn.Linear(3 * CAMERA.height * CAMERA.width, 3)
        self.state = nn.Linear(STATE_DIM, 3)
        low, high = torch.tensor(DEFAULT_ACTION_SPEC.low_array()), torch.tensor(DEFAULT_ACTION_SPEC.high_array())
        self.register_buffer("action_mid", (low + high) / 2)
        self.register_buffer("action_half", (high - low) / 2)

    def forward(self, depth: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        return self.action_mid + self.action_half * torch.tanh(self.depth(depth.flatten(1) / 10.0) + self.state(state))


def _policy(path: Path, seed: int, camera: CameraSpec = CAMERA) -> Path:
    save_policy(_Linear(seed), build_metadata(camera, DEFAULT_ACTION_SPEC, 0.1, {"seed": seed,
                                                                                 "evaluation": {"x": 1}}), path)
    return path


def test_ensemble_flies_the_mean_of_its_members_actions(tmp_path):
    members = [_policy(tmp_path / f"p{i}.pt", seed) for i, seed in enumerate((1, 2, 3))]
    out = tmp_path / "ens" / "policy.pt"
    build_ensemble(members, out)

    ensemble = load_policy(out)  # a valid policy file: the contract's checks and a forward pass
    torch.manual_seed(0)
    depth = torch.rand(32, 3, CAMERA.height, CAMERA.width) * 10.0
    state = torch.randn(32, STATE_DIM)
    actions = [load_policy(p).module(depth, state) for p in members]
    assert not torch.allclose(actions[0], actions[1])  # the members differ, so the mean is none of them
    assert torch.allclose(ensemble.module(depth, state), sum(actions) / 3, atol=1e-6)
    assert ensemble.camera == load_policy(members[0]).camera
    provenance = ensemble.metadata["provenance"]
    assert [m["path"] for m in provenance["ensemble"]["members"]] == [str(p) for p in members]
    assert provenance["seed"] == 1 and "evaluation" not in provenance  # the first member's, without its test result

    # The command line writes the same file and flies it in an evaluation cell.
    done = subprocess.run([sys.executable, "-m", "sitl.learn.ensemble", *map(str, members[:2]), "--out",
                           str(tmp_path / "cli" / "e.pt"), "--eval", "paper:random-medium", "--eval-episodes", "2",
                           "--threads", "1"], capture_output=True, text=True, cwd=tmp_path, timeout=300,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    assert done.returncode == 0, done.stderr
    assert "the mean action of 2 policies" in done.stdout and "paper:random-medium: success" in done.stdout
    assert (tmp_path / "cli" / "eval" / "cells" / "paper-random-medium.json").is_file()


def test_bad_input_is_one_line_and_exit_2(tmp_path):
    def run(*args):
        return subprocess.run([sys.executable, "-m", "sitl.learn.ensemble", *map(str, args)], capture_output=True,
                              text=True, cwd=tmp_path, timeout=120, env={**os.environ, "PYTHONPATH": str(REPO)})

    a = _policy(tmp_path / "a.pt", 1)
    narrower = CameraSpec(width=16, height=10, hfov_deg=70.0, vfov_deg=58.0, max_range_m=10.0)  # same pixels
    other = _policy(tmp_path / "b.pt", 2, narrower)
    out = tmp_path / "e.pt"
    for args, message in (((a, "--out", out), "at least two policy files"),
                          ((a, tmp_path / "nope.pt", "--out", out), "no such policy file"),
                          ((a, other, "--out", out), "'depth' differs")):
        done = run(*args)
        assert done.returncode == 2, done.stderr
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], done.stderr
        assert not out.exists()
