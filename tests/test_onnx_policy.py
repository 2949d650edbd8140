"""The ONNX policy file: same actions as TorchScript on simulator observations, same metadata, same refusals.

The observations are rendered by the simulator (:class:`sitl.sim.env.SwarmEnv`: a circle of
8 UAVs flown by the bundled policy, so the depth images hold the other UAVs at every range),
not random noise alone.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

onnx = pytest.importorskip("onnx", reason="ONNX export needs the onnx package (swarmnav[train])")
pytest.importorskip("onnxruntime", reason="ONNX inference needs onnxruntime (swarmnav[onnx])")

from companion.onnx_policy import METADATA_KEY, select_providers  # noqa: E402
from companion.policy import PolicyFileError, load_policy  # noqa: E402
from sitl.learn.export import ONNX_TOLERANCE, export_onnx  # noqa: E402
from sitl.sim.config import ScenarioConfig, SimConfig  # noqa: E402
from sitl.sim.env import SwarmEnv  # noqa: E402
from tests.companion_helpers import REPO, env, make_policy  # noqa: E402

BUNDLED_PT, BUNDLED_ONNX = REPO / "models" / "policy.pt", REPO / "models" / "policy.onnx"


def _simulated_observations(policy, steps: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Depth stacks and states of 8 UAVs on a 6 m circle flying towards each other, ``steps`` control periods."""
    config = SimConfig(num_uavs=8, scenario=ScenarioConfig(name="circle", circle_radius_m=6.0), camera=policy.camera)
    sim = SwarmEnv(config, seed=3)
    obs = sim.reset()
    depths, states = [], []
    for _ in range(steps):
        depths.append(np.array(obs.depth))
        states.append(np.array(obs.state))
        obs, *_ = sim.step(policy.act(obs.depth, obs.state))
    return np.concatenate(depths), np.concatenate(states)


def test_the_bundled_onnx_file_gives_torchscripts_actions_on_simulated_observations():
    reference, exported = load_policy(BUNDLED_PT), load_policy(BUNDLED_ONNX)
    depth, state = _simulated_observations(reference)
    near = depth < reference.camera.max_range_m
    assert near.mean() > 0.01, "the rendered frames should show the other UAVs"
    expected, actual = reference.act(depth, state), exported.act(depth, state)
    assert actual.shape == expected.shape == (len(depth), 3) and actual.dtype == np.float32
    assert float(np.max(np.abs(actual - expected))) <= ONNX_TOLERANCE
    assert float(np.std(expected, axis=0).min()) > 1e-3, "the observations should produce varied actions"
    assert exported.metadata == reference.metadata
    assert (exported.camera, exported.action, exported.control_period_s, exported.task) == \
        (reference.camera, reference.action, reference.control_period_s, reference.task)


def test_export_writes_the_metadata_into_metadata_props_with_dynamic_batch(tmp_path):
    out = tmp_path / "policy.onnx"
    assert export_onnx(BUNDLED_PT, out) <= ONNX_TOLERANCE
    model = onnx.load(str(out))
    props = {p.key: p.value for p in model.metadata_props}
    assert json.loads(props[METADATA_KEY]) == load_policy(BUNDLED_PT).metadata
    assert [i.name for i in model.graph.input] == ["depth", "state"] and [o.name for o in model.graph.output] == ["action"]
    cam = load_policy(BUNDLED_PT).camera
    depth_dims = [d.dim_param or d.dim_value for d in model.graph.input[0].type.tensor_type.shape.dim]
    assert depth_dims == ["batch", cam.frames, cam.height, cam.width]
    batch = load_policy(out).act(np.full((5, cam.frames, cam.height, cam.width), 7.0, np.float32),
                                 np.zeros((5, 6), np.float32))
    assert batch.shape == (5, 3)


def test_the_export_command_converts_a_file_and_refuses_a_bad_one(tmp_path):
    source = make_policy(tmp_path / "seeker.pt")
    done = subprocess.run([sys.executable, "-m", "sitl.learn.export", str(source)], cwd=REPO, env=env(),
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stderr == ""  # TorchScript's and the exporter's deprecation warnings stay out of the user's face
    assert (tmp_path / "seeker.onnx").is_file() and "largest action difference" in done.stdout
    (tmp_path / "junk.pt").write_bytes(b"not a policy")
    bad = subprocess.run([sys.executable, "-m", "sitl.learn.export", str(tmp_path / "junk.pt")], cwd=REPO, env=env(),
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 3 and bad.stderr.count("\n") == 1 and "not a TorchScript policy file" in bad.stderr


def test_loading_refuses_non_policy_onnx_files_with_one_line_reasons(tmp_path):
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"\x08\x07garbage")
    with pytest.raises(PolicyFileError, match="not a loadable ONNX model"):
        load_policy(garbage)
    # A valid graph without policy.json, and one whose metadata disagrees with its input shape.
    model = onnx.load(str(BUNDLED_ONNX))
    del model.metadata_props[:]
    onnx.save(model, str(tmp_path / "bare.onnx"))
    with pytest.raises(PolicyFileError, match="no policy.json inside"):
        load_policy(tmp_path / "bare.onnx")
    meta = load_policy(BUNDLED_PT).metadata
    depth = meta["depth"]
    graph_shape = f"{depth['frames']}, {depth['height']}, {depth['width']}"
    depth["width"] *= 2
    entry = model.metadata_props.add()
    entry.key, entry.value = METADATA_KEY, json.dumps(meta)
    onnx.save(model, str(tmp_path / "wide.onnx"))
    expected = (rf"ONNX input 'depth' has shape \['batch', {graph_shape}\], "
                rf"policy.json says \['B', {depth['frames']}, {depth['height']}, {depth['width']}\]")
    with pytest.raises(PolicyFileError, match=expected):
        load_policy(tmp_path / "wide.onnx")


def test_providers_default_to_cpu_here_and_an_absent_gpu_provider_is_refused():
    import onnxruntime

    assert select_providers("cpu") == ["CPUExecutionProvider"]
    assert select_providers("auto")[-1] == "CPUExecutionProvider"
    if "CUDAExecutionProvider" not in onnxruntime.get_available_providers():
        done = subprocess.run([sys.executable, "-m", "companion.cli", "--connect", "udpin:127.0.0.1:9",
                               "--model", str(BUNDLED_ONNX), "--onnx-provider", "cuda", "--camera", "sitl:9"],
                              cwd=REPO, env=env(), capture_output=True, text=True, timeout=120)
        assert done.returncode == 3, done.stderr
        assert "no CUDAExecutionProvider" in done.stdout and "Traceback" not in done.stderr


def test_loading_torchscript_prints_no_deprecation_warning():
    code = "from companion.policy import load_policy; load_policy('models/policy.pt')"
    done = subprocess.run([sys.executable, "-W", "always", "-c", code], cwd=REPO, env=env(), capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0 and "Deprecat" not in done.stderr, done.stderr


def test_the_training_export_writes_both_formats_with_the_same_actions(tmp_path):
    import torch

    from companion.spec import DEFAULT_ACTION_SPEC, CameraSpec
    from sitl.learn.agent import AgentConfig, SacAeAgent
    from sitl.learn.export import check_observations, export_policy

    torch.manual_seed(0)
    agent = SacAeAgent(AgentConfig(hidden_dim=32), CameraSpec(width=16, height=16), DEFAULT_ACTION_SPEC)
    export_policy(agent, tmp_path / "policy.pt", 0.1, {"method": "sac_ae", "note": "untrained test policy"})
    reference, exported = load_policy(tmp_path / "policy.pt"), load_policy(tmp_path / "policy.onnx")
    depth, state = check_observations(3, 16, 16, reference.camera.max_range_m, seed=7)
    assert float(np.max(np.abs(exported.act(depth, state) - reference.act(depth, state)))) <= ONNX_TOLERANCE
    assert exported.metadata == reference.metadata
