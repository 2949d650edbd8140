"""The policy file contract: export from the trainer, validate and load for flight."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from companion.policy import (FORMAT_VERSION, PolicyFileError, build_metadata, load_policy, save_policy,
                             torchscript_error_line)
from companion.spec import DEFAULT_ACTION_SPEC, REALSENSE_D435, CameraSpec, MemorySpec, state_names_for
from sitl.learn.agent import AgentConfig, SacAeAgent
from sitl.learn.export import export_policy

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
    assert meta["depth"] == {"height": 16, "width": 16, "frames": 3, "frame_stride": 1, "hfov_deg": 90.0, "vfov_deg": 90.0,
                             "mount_pitch_deg": 0.0, "min_range_m": 0.0, "max_range_m": 20.0,
                             "invalid_value_m": 0.0, "invalid_reads_as": "max_range_m",
                             "units": "m", "kind": "planar", "order": "oldest_first"}
    assert meta["action"]["low"] == [0.0, -0.5, -0.5] and meta["action"]["high"] == [2.0, 0.5, 0.5]
    assert meta["provenance"]["method"] == "sac_ae" and "git_commit" in meta["provenance"]
    assert policy.camera == dataclasses.replace(CAMERA, vfov_deg=90.0) and policy.control_period_s == 0.1
    assert policy.format_version == 2 and policy.notes == ()
    # Plain torch.jit.load works too, as the contract promises.
    extra = {"policy.json": ""}
    module = torch.jit.load(str(path), _extra_files=extra)
    out = module(torch.from_numpy(depth), torch.from_numpy(state))
    assert out.dtype == torch.float32 and out.shape == (5, 3) and json.loads(extra["policy.json"])
    assert torch.all(out >= torch.tensor([0.0, -0.5, -0.5])) and torch.all(out <= torch.tensor([2.0, 0.5, 0.5]))


def test_a_bare_torch_jit_load_user_gets_a_clear_error_for_a_wrong_input_shape(agent, tmp_path):
    """The file checks its inputs against policy.json itself (companion.checked_policy), so someone who
    runs it without this package learns the expected shape, not torch's 'mat1 and mat2 shapes ...'."""
    path = tmp_path / "policy.pt"
    export_policy(agent, path, 0.1, {"method": "sac_ae"}, onnx=False)
    module = torch.jit.load(str(path))
    state = torch.zeros(1, 6)
    with pytest.raises(Exception, match=r"depth must be \[batch, 3, 16, 16\].*got \[1, 3, 20, 32\]"):
        module(torch.zeros(1, 3, 20, 32), state)
    with pytest.raises(Exception, match=r"depth must be \[batch, 3, 16, 16\]"):
        module(torch.zeros(3, 16, 16), state)  # no batch axis
    with pytest.raises(Exception, match=r"state must be \[batch, 6\] with depth's batch 2"):
        module(torch.zeros(2, 3, 16, 16), state)
    assert module(torch.zeros(2, 3, 16, 16), torch.zeros(2, 6)).shape == (2, 3)
    # Saving a loaded file again does not wrap it twice; the actions stay the same.
    resaved = tmp_path / "again.pt"
    save_policy(module, load_policy(path).metadata, resaved)
    assert "policy.policy" not in dict(torch.jit.load(str(resaved)).named_modules())
    depth = torch.rand(4, 3, 16, 16) * 20
    assert torch.equal(torch.jit.load(str(resaved))(depth, torch.ones(4, 6)), module(depth, torch.ones(4, 6)))
    # A policy.json edited after saving (another camera) is refused at load, in the check's own words.
    meta = load_policy(path).metadata
    meta["depth"]["width"] = 24
    edited = _write_raw(tmp_path / "edited.pt", meta, module)
    with pytest.raises(PolicyFileError, match=r"blank observation \(depth must be \[batch, 3, 16, 16\]"):
        load_policy(edited)
    # save_policy wraps the check anew for the metadata it writes (here 16x24, which the network
    # cannot take: its own error, at load).
    save_policy(module, meta, tmp_path / "resaved24.pt")
    with pytest.raises(PolicyFileError, match="mat1 and mat2"):
        load_policy(tmp_path / "resaved24.pt")


def test_torchscript_errors_are_cut_to_the_line_that_says_why():
    """The companion's hold reason and load errors quote the raised error, not the interpreter's preamble."""
    scripted = torch.jit.script(torch.nn.Sequential(torch.nn.Flatten(), torch.nn.Linear(4, 2)))
    with pytest.raises(Exception) as caught:
        scripted(torch.zeros(1, 5))
    assert str(caught.value).startswith("The following operation failed")
    assert torchscript_error_line(caught.value) == "mat1 and mat2 shapes cannot be multiplied (1x5 and 4x2)"
    assert torchscript_error_line(ValueError("plain\nsecond line")) == "plain"
    assert torchscript_error_line(RuntimeError("")) == "RuntimeError"


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


# --------------------------------------------------------------------------- hostile policy.json (issue 16: 6, 8, 9)


class _Width(torch.nn.Module):
    """Returns ``width`` zeros per row: a model whose output is not the 3 actions."""

    def __init__(self, width: int) -> None:
        super().__init__()
        self.width = width

    def forward(self, depth: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        return torch.zeros((depth.shape[0], self.width))


def _write_raw(path, metadata, module: torch.nn.Module | None = None):
    """Save ``module`` with ``metadata`` as policy.json *without* the exporter's checks (a hostile file)."""
    text = metadata if isinstance(metadata, str) else json.dumps(metadata)  # allow_nan: writes Infinity/NaN
    torch.jit.save(torch.jit.script(module or _Const(0.0)), str(path), _extra_files={"policy.json": text})
    return path


def _meta(**changes) -> dict:
    """A valid policy.json with ``changes`` applied; keys like ``depth.hfov_deg`` reach into a sub-object."""
    meta = json.loads(json.dumps(build_metadata(CAMERA, DEFAULT_ACTION_SPEC, 0.1, {})))
    for key, value in changes.items():
        target, _, leaf = key.rpartition(".")
        (meta[target] if target else meta)[leaf] = value
    return meta


INF = float("inf")
HOSTILE = {
    # 6: bounds and names checked against companion.spec (the paper's box is the widest allowed)
    "bounds_inf": (_meta(**{"action.low": [-INF] * 3, "action.high": [INF] * 3}), "action low[0] must be finite"),
    "bounds_100": (_meta(**{"action.low": [-100.0] * 3, "action.high": [100.0] * 3}),
                   "vel_fwd_m_s bounds [-100, 100] exceed the onboard limits [0, 2]"),
    "task_not_object": (_meta(task="0.5"), "task must be a JSON object"),
    "task_radius_nan": (_meta(**{"task.arrival_radius_m": float("nan")}), "task arrival_radius_m must be finite"),
    "task_radius_huge": (_meta(**{"task.collision_radius_m": 50.0}), "task radii must be in (0, 10] m"),
    "task_steps_fraction": (_meta(**{"task.max_episode_steps": 2.5}), "task max_episode_steps must be an integer"),
    "fwd_too_fast": (_meta(**{"action.high": [50.0, 0.5, 0.5]}), "vel_fwd_m_s bounds [0, 50] exceed"),
    "yaw_too_fast": (_meta(**{"action.low": [0.0, -0.5, -5.0]}), "yaw_rate_rad_s bounds [-5, 0.5] exceed"),
    "bounds_nan": (_meta(**{"action.high": [2.0, float("nan"), 0.5]}), "action high[1] must be finite"),
    "low_not_below_high": (_meta(**{"action.low": [0.0, 0.2, -0.5], "action.high": [2.0, 0.2, 0.5]}),
                           "vel_down_m_s: low 0.2 must be below high 0.2"),
    "bounds_strings": (_meta(**{"action.low": ["0", "-0.5", "-0.5"]}), "action low[0] must be a number"),
    "bounds_two": (_meta(**{"action.high": [2.0, 0.5]}), "action high must be a list of 3 numbers"),
    "bounds_null": (_meta(**{"action.low": None}), "action low must be a list of 3 numbers"),
    "names_swapped": (_meta(**{"action.names": ["vel_down_m_s", "vel_fwd_m_s", "yaw_rate_rad_s"]}), "action names"),
    "names_missing": (_meta(action={"low": [0, -0.5, -0.5], "high": [2, 0.5, 0.5]}), "action names None differ"),
    "action_string": (_meta(action="fast"), "action must be a JSON object"),
    # 8: control period in a sane range
    "period_inf": (_meta(control_period_s=INF), "control_period_s must be in 0.02..1 s, file says inf"),
    "period_tiny": (_meta(control_period_s=1e-4), "control_period_s must be in 0.02..1 s, file says 0.0001"),
    "period_zero": (_meta(control_period_s=0), "control_period_s must be in 0.02..1 s"),
    "period_negative": (_meta(control_period_s=-0.1), "control_period_s must be in 0.02..1 s"),
    "period_nan": (_meta(control_period_s=float("nan")), "control_period_s must be in 0.02..1 s"),
    "period_huge_int": (_meta(control_period_s=10 ** 400), "control_period_s must be in 0.02..1 s, file says inf"),
    # 9: every field type-checked before use
    "period_string": (_meta(control_period_s="abc"), "control_period_s must be a number of seconds, file says 'abc'"),
    "period_null": (_meta(control_period_s=None), "control_period_s must be a number of seconds"),
    "period_bool": (_meta(control_period_s=True), "control_period_s must be a number of seconds"),
    "hfov_null": (_meta(**{"depth.hfov_deg": None}), "depth hfov_deg must be a number, file says None"),
    "hfov_string": (_meta(**{"depth.hfov_deg": "90"}), "depth hfov_deg must be a number"),
    "hfov_180": (_meta(**{"depth.hfov_deg": 180.0}), "hfov_deg must be in [1, 179)"),
    "range_inf": (_meta(**{"depth.max_range_m": INF}), "depth max_range_m must be finite"),
    "range_negative": (_meta(**{"depth.max_range_m": -1.0}), "depth max_range_m must be in (0, 1000] m"),
    "width_fraction": (_meta(**{"depth.width": 16.5}), "depth width must be an integer"),
    "width_string": (_meta(**{"depth.width": "16"}), "depth width must be an integer"),
    "width_huge": (_meta(**{"depth.width": 10 ** 9}), "depth width must be in 1..1024"),
    "height_zero": (_meta(**{"depth.height": 0}), "depth height must be in 1..1024"),
    "frames_bool": (_meta(**{"depth.frames": True}), "depth frames must be an integer"),
    "depth_string": (_meta(depth="32x32"), "depth must be a JSON object, file says '32x32'"),
    "depth_order": (_meta(**{"depth.order": "newest_first"}), "ordered oldest_first"),
    "units_mm": (_meta(**{"depth.units": "mm"}), "depth must be planar metres"),
    "state_null": (_meta(state_names=None), "state layout None differs"),
    "version_bool": (_meta(format_version=True), "unsupported policy format_version True"),
    "provenance_string": (_meta(provenance="me"), "provenance must be a JSON object"),
    "body_frame_number": (_meta(body_frame=3), "body_frame must be a string"),
    "not_an_object": ("[1, 2, 3]", "policy.json is not a JSON object"),
    # remembered depth: every setting named and in range, and the state layout that goes with it
    "memory_string": (_meta(memory="1s"), "memory must be a JSON object"),
    "memory_missing_setting": (_meta(memory={"steps": 10, "every_steps": 2, "range_m": 5.0}),
                               "memory must have exactly the settings"),
    "memory_steps_huge": (_meta(memory={**MemorySpec().to_dict(), "steps": 10 ** 6}), "memory steps must be in 1..100"),
    "memory_range_nan": (_meta(memory={**MemorySpec().to_dict(), "range_m": float("nan")}), "memory range_m must be finite"),
    "memory_range_zero": (_meta(memory={**MemorySpec().to_dict(), "range_m": 0.0}), "memory range_m must be in (0, 100] m"),
    "memory_without_its_state": (_meta(memory=MemorySpec().to_dict()), "state layout"),
    "memory_outside_view_string": (_meta(memory={**MemorySpec().to_dict(), "outside_view": "yes"}),
                                   "memory outside_view must be true or false"),
}


@pytest.mark.parametrize("case", list(HOSTILE))
def test_hostile_metadata_is_refused_with_its_reason(case, tmp_path):
    metadata, reason = HOSTILE[case]
    path = _write_raw(tmp_path / f"{case}.pt", metadata)
    with pytest.raises(PolicyFileError) as caught:
        load_policy(path)
    assert reason in str(caught.value)
    assert "\n" not in str(caught.value) and str(caught.value).count(str(path)) == 1  # one line, named once
    with pytest.raises(PolicyFileError):  # the metadata is checked even without the forward check
        load_policy(path, check_forward=False)


@pytest.mark.parametrize("width", [1, 4])
def test_a_model_output_that_is_not_three_actions_is_refused_at_load(width, tmp_path):
    path = _write_raw(tmp_path / "wide.pt", _meta(), _Width(width))
    with pytest.raises(PolicyFileError, match=rf"policy output has shape \[1, {width}\], expected \[1, 3\]"):
        load_policy(path)


def test_a_narrower_action_box_and_the_period_limits_are_accepted(tmp_path):
    narrow = _meta(**{"action.low": [0.0, -0.2, -0.3], "action.high": [1.0, 0.2, 0.3]}, control_period_s=0.02)
    policy = load_policy(_write_raw(tmp_path / "narrow.pt", narrow, _Const(0.1)))
    assert policy.action.low == (0.0, -0.2, -0.3) and policy.action.high == (1.0, 0.2, 0.3)
    assert policy.control_period_s == 0.02
    slow = load_policy(_write_raw(tmp_path / "slow.pt", _meta(control_period_s=1), _Const(0.0)))
    assert slow.control_period_s == 1.0 and isinstance(slow.control_period_s, float)


def test_the_companion_exits_3_with_the_reason_for_hostile_files(tmp_path):
    """The real ``companion`` process: exit 3, the reason in its log, no traceback (a few cases, run in parallel)."""
    import subprocess
    import sys

    from tests.companion_helpers import REPO, env

    cases = {
        "bounds_inf": (HOSTILE["bounds_inf"][0], None, "action low[0] must be finite"),
        "period_inf": (HOSTILE["period_inf"][0], None, "control_period_s must be in 0.02..1 s"),
        "hfov_null": (HOSTILE["hfov_null"][0], None, "depth hfov_deg must be a number"),
        "four_outputs": (_meta(), _Width(4), "policy output has shape [1, 4], expected [1, 3]"),
    }
    procs = {}
    for name, (metadata, module, _) in cases.items():
        model = _write_raw(tmp_path / f"{name}.pt", metadata, module)
        procs[name] = subprocess.Popen(
            [sys.executable, "-m", "companion.cli", "--connect", "udp:127.0.0.1:9", "--model", str(model),
             "--camera", "sitl:9"], cwd=REPO, env=env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for name, proc in procs.items():
        try:
            out, err = proc.communicate(timeout=60)
        finally:
            proc.kill()
        assert proc.returncode == 3, (name, out, err)
        assert "Traceback" not in out + err
        exit_event = [json.loads(line) for line in out.splitlines() if '"exit"' in line][-1]
        assert cases[name][2] in exit_event["reason"], (name, exit_event)


def test_the_task_a_policy_was_trained_for_is_recorded_and_read(tmp_path):
    """policy.json's task (collision radius, arrival radius, time limit) is what the companion flies by;
    a file written before the field existed reads as the defaults."""
    from companion.spec import DEFAULT_TASK_SPEC, TaskSpec

    task = TaskSpec(collision_radius_m=0.35, arrival_radius_m=0.8, max_episode_steps=300)
    path = tmp_path / "task.pt"
    save_policy(_Const(0.0), build_metadata(CAMERA, DEFAULT_ACTION_SPEC, 0.1, {}, task), path)
    assert load_policy(path).task == task
    old = _meta_v1()
    del old["task"]
    assert load_policy(_write_raw(tmp_path / "old.pt", old)).task == DEFAULT_TASK_SPEC
    # Version 2 must say what it was trained for.
    no_task = _meta()
    del no_task["task"]
    with pytest.raises(PolicyFileError, match="lacks the field 'task'"):
        load_policy(_write_raw(tmp_path / "no_task.pt", no_task))


def _meta_v1(**changes) -> dict:
    """A version-1 policy.json (as the bundled policy carries): no camera geometry beyond hfov and range."""
    meta = _meta(**changes)
    meta["format_version"] = 1
    for key in ("vfov_deg", "mount_pitch_deg", "min_range_m", "invalid_value_m", "invalid_reads_as"):
        del meta["depth"][key]
    return meta


def test_version_1_files_read_as_documented_and_say_so(tmp_path):
    policy = load_policy(_write_raw(tmp_path / "v1.pt", _meta_v1()))
    cam = policy.camera
    assert policy.format_version == 1
    assert (cam.hfov_deg, cam.vertical_fov_deg, cam.mount_pitch_deg, cam.min_range_m, cam.max_range_m) == \
        pytest.approx((90.0, 90.0, 0.0, 0.0, 20.0))
    assert len(policy.notes) == 1 and policy.notes[0].startswith("policy format version 1: read as a level camera, "
                                                                 "90 x 90 deg (square pixels), range 0-20 m")


def test_version_2_camera_geometry_round_trips(tmp_path):
    from companion.spec import REALSENSE_D435

    path = tmp_path / "d435.pt"
    save_policy(_Const(0.0), build_metadata(REALSENSE_D435, DEFAULT_ACTION_SPEC, 0.1, {}), path)
    assert load_policy(path).camera == REALSENSE_D435
    pitched = dataclasses.replace(REALSENSE_D435, mount_pitch_deg=-7.5)
    save_policy(_Const(0.0), build_metadata(pitched, DEFAULT_ACTION_SPEC, 0.1, {}), path)
    assert load_policy(path).camera.mount_pitch_deg == -7.5
    strided = dataclasses.replace(REALSENSE_D435, frame_stride=3)
    save_policy(_Const(0.0), build_metadata(strided, DEFAULT_ACTION_SPEC, 0.1, {}), path)
    assert load_policy(path).camera == strided
    uneven = dataclasses.replace(REALSENSE_D435, frame_ages=(6, 1, 0))
    save_policy(_Const(0.0), build_metadata(uneven, DEFAULT_ACTION_SPEC, 0.1, {}), path)
    assert load_policy(path).camera == uneven and load_policy(path).metadata["depth"]["frame_ages"] == [6, 1, 0]
    older = _meta()  # files written before frame_stride existed stack consecutive frames
    del older["depth"]["frame_stride"]
    assert load_policy(_write_raw(tmp_path / "older.pt", older)).camera.frame_stride == 1


@pytest.mark.parametrize("changes, reason", [
    ({"depth.vfov_deg": None}, "depth vfov_deg must be a number"),
    ({"depth.vfov_deg": 180.0}, "vfov_deg must be in"),
    ({"depth.mount_pitch_deg": 60.0}, "mount_pitch_deg must be within"),
    ({"depth.min_range_m": 30.0}, "min_range_m must be in"),
    ({"depth.invalid_value_m": 65.535}, "invalid-pixel convention 65.535"),
    ({"depth.invalid_reads_as": "zero"}, "invalid-pixel convention 0 -> 'zero'"),
    ({"depth.frame_stride": 0}, "depth frame_stride must be in 1..10"),
    ({"depth.frame_stride": 2.5}, "depth frame_stride must be an integer"),
    ({"depth.frame_ages": [1, 0]}, "depth frame_ages must be a list of 3 integers"),
    ({"depth.frame_ages": [2, 1.5, 0]}, r"depth frame_ages\[1\] must be an integer"),
    ({"depth.frame_ages": [0, 1, 2]}, "must decrease strictly to 0"),
    ({"depth.frame_ages": [6, 1, 0], "depth.frame_stride": 3}, "replace frame_stride"),
])
def test_bad_version_2_camera_fields_are_refused(tmp_path, changes, reason):
    with pytest.raises(PolicyFileError, match=reason):
        load_policy(_write_raw(tmp_path / "bad.pt", _meta(**changes)))
    missing = _meta()
    del missing["depth"]["mount_pitch_deg"]
    with pytest.raises(PolicyFileError, match="lacks the field 'mount_pitch_deg'"):
        load_policy(_write_raw(tmp_path / "missing.pt", missing))


def test_a_policy_with_remembered_depth_round_trips_with_its_state_layout(tmp_path):
    """The trainer's agent with remembered depth exports a file whose policy.json declares the memory and the
    longer state; it loads with both, flies the sector ranges as the agent does, and its ONNX twin agrees.
    A file without ``memory`` (every file written before it existed) loads with the paper's state."""
    memory = MemorySpec()
    torch.manual_seed(0)
    agent = SacAeAgent(AgentConfig(hidden_dim=32), REALSENSE_D435, DEFAULT_ACTION_SPEC, memory=memory)
    path = tmp_path / "memory.pt"
    export_policy(agent, path, 0.1, {"method": "sac_ae"})
    policy = load_policy(path)
    assert policy.memory == memory and policy.state_dim == 6 + memory.num_sectors
    assert policy.metadata["memory"] == memory.to_dict()
    assert policy.metadata["state_names"] == list(state_names_for(memory))
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.2, 10.0, (4, 3, 20, 32)).astype(np.float32)
    state = np.concatenate([rng.normal(0, 5, (4, 6)), rng.uniform(0, 5, (4, memory.num_sectors))], axis=1)
    state = state.astype(np.float32)
    np.testing.assert_allclose(policy.act(depth, state), agent.act(depth, state, explore=False), atol=1e-5)
    near = state.copy()
    near[:, 6:] = 0.5  # something remembered close all round changes what it does
    assert not np.allclose(policy.act(depth, near), policy.act(depth, state))
    onnx_twin = load_policy(path.with_suffix(".onnx"))
    assert onnx_twin.memory == memory
    np.testing.assert_allclose(onnx_twin.act(depth, state), policy.act(depth, state), atol=1e-4)
    with pytest.raises(Exception, match=r"state must be \[batch, 32\]"):
        policy.act(depth, state[:, :6])
    plain = load_policy(_write_raw(tmp_path / "plain.pt", _meta()))
    assert plain.memory is None and plain.state_dim == 6
