"""The policy file contract: export from the trainer, validate and load for flight."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from companion.policy import FORMAT_VERSION, PolicyFileError, build_metadata, load_policy, save_policy
from companion.spec import DEFAULT_ACTION_SPEC, CameraSpec
from sitl.rl.agent import AgentConfig, SacAeAgent
from sitl.rl.export import export_policy

CAMERA = CameraSpec(width=16, height=16)


@pytest.fixture(scope="module")
def agent():
    torch.manual_seed(0)
    return SacAeAgent(AgentConfig(hidden_dim=64), CAMERA, DEFAULT_ACTION_SPEC)


def test_exported_policy_matches_the_agent_and_carries_metadata(agent, tmp_path):
    path = tmp_path / "policy.pt"
    export_policy(agent, path, 0.1, {"method": "sac_ae", "scenario": "random", "updates": 0})
    policy = load_policy(path)
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 25.0, (5, 3, 16, 16)).astype(np.float32)  # beyond max range too
    state = rng.normal(0, 5, (5, 6)).astype(np.float32)
    np.testing.assert_allclose(policy.act(depth, state), agent.act(depth, state, explore=False), atol=1e-5)
    meta = policy.metadata
    assert meta["format_version"] == FORMAT_VERSION
    assert meta["depth"] == {"height": 16, "width": 16, "frames": 3, "hfov_deg": 90.0, "max_range_m": 20.0,
                             "units": "m", "kind": "planar", "order": "oldest_first"}
    assert meta["action"]["low"] == [0.0, -0.5, -0.5] and meta["action"]["high"] == [2.0, 0.5, 0.5]
    assert meta["provenance"]["method"] == "sac_ae" and "git_commit" in meta["provenance"]
    assert policy.camera == CAMERA and policy.control_period_s == 0.1
    # Plain torch.jit.load works too, as the contract promises.
    extra = {"policy.json": ""}
    module = torch.jit.load(str(path), _extra_files=extra)
    out = module(torch.from_numpy(depth), torch.from_numpy(state))
    assert out.dtype == torch.float32 and out.shape == (5, 3) and json.loads(extra["policy.json"])
    assert torch.all(out >= torch.tensor([0.0, -0.5, -0.5])) and torch.all(out <= torch.tensor([2.0, 0.5, 0.5]))


def test_wrong_files_are_refused_with_a_reason(agent, tmp_path):
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"\x00not a model" * 100)
    with pytest.raises(PolicyFileError, match="not a zip archive"):
        load_policy(garbage)
    with pytest.raises(PolicyFileError, match="no such policy file"):
        load_policy(tmp_path / "missing.pt")

    good = tmp_path / "good.pt"
    export_policy(agent, good, 0.1, {})
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(PolicyFileError):
        load_policy(truncated)

    bare = tmp_path / "bare.pt"
    torch.jit.save(torch.jit.script(torch.nn.Linear(6, 3)), str(bare))
    with pytest.raises(PolicyFileError, match="no policy.json"):
        load_policy(bare)


class _Const(torch.nn.Module):
    def __init__(self, value: float) -> None:
        super().__init__()
        self.value = value

    def forward(self, depth: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        return torch.full((depth.shape[0], 3), self.value)


def test_metadata_and_behaviour_are_checked(tmp_path):
    meta = build_metadata(CAMERA, DEFAULT_ACTION_SPEC, 0.1, {})
    bad_version = dict(meta, format_version=99)
    with pytest.raises(PolicyFileError, match="format_version 99"):
        save_policy(_Const(0.0), bad_version, tmp_path / "v.pt")
    bad_layout = dict(meta, state_names=["a", "b"])
    path = tmp_path / "layout.pt"
    torch.jit.save(torch.jit.script(_Const(0.0)), str(path), _extra_files={"policy.json": json.dumps(bad_layout)})
    with pytest.raises(PolicyFileError, match="state layout"):
        load_policy(path)
    nan_policy = tmp_path / "nan.pt"
    save_policy(_Const(float("nan")), meta, nan_policy)
    with pytest.raises(PolicyFileError, match="non-finite"):
        load_policy(nan_policy)
    assert load_policy(nan_policy, check_forward=False).act(np.zeros((1, 3, 16, 16)), np.zeros((1, 6))).shape == (1, 3)
    too_fast = tmp_path / "fast.pt"
    save_policy(_Const(5.0), meta, too_fast)
    with pytest.raises(PolicyFileError, match="outside the action bounds"):
        load_policy(too_fast)
    broken_json = tmp_path / "json.pt"
    torch.jit.save(torch.jit.script(_Const(0.0)), str(broken_json), _extra_files={"policy.json": "{oops"})
    with pytest.raises(PolicyFileError, match="not valid JSON"):
        load_policy(broken_json)
