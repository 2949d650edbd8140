"""Export a trained actor as ``policy.pt`` (TorchScript) and ``policy.onnx``, both following :mod:`companion.policy`.

``python -m sitl.learn.export POLICY.pt [--output POLICY.onnx]`` converts an existing
TorchScript policy file (the bundled ``models/policy.pt``, say) to ONNX with the same
inputs, output and ``policy.json`` metadata (in the graph's ``metadata_props``), and checks
that both give the same actions on test observations. Training writes both files.
"""

from __future__ import annotations

import argparse
import copy
import io
import json
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

from companion.checked_policy import unwrap_checked
from companion.governor import GovernorSpec
from companion.onnx_policy import INPUT_DEPTH, INPUT_STATE, METADATA_KEY, OUTPUT_ACTION
from companion.policy import PolicyFileError, build_metadata, load_policy, save_policy
from companion.spec import DEFAULT_TASK_SPEC, MemorySpec, TaskSpec

#: ONNX opset of the exported graph: onnxruntime >= 1.12 runs it (JetPack 5's builds included).
ONNX_OPSET = 17
#: Largest |ONNX - TorchScript| action difference the export accepts (the issue's tolerance).
ONNX_TOLERANCE = 1e-4


class ExportedPolicy(nn.Module):
    """Deterministic actor: raw depth (m) and state in, physical actions within the bounds out."""

    def __init__(self, agent) -> None:
        super().__init__()
        self.encoder = copy.deepcopy(agent.actor.encoder).cpu()  # own copy of the tied convolutions
        self.trunk = copy.deepcopy(agent.actor.trunk).cpu()
        self.max_range_m = float(agent.camera.max_range_m)
        self.state_features = copy.deepcopy(agent.state_features).cpu()
        self.register_buffer("action_mid", agent.actor.action_mid.detach().cpu().clone())
        self.register_buffer("action_half", agent.actor.action_half.detach().cpu().clone())
        self.action_dim = int(self.action_mid.numel())

    def forward(self, depth: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        pixels = torch.clamp(depth, 0.0, self.max_range_m) / self.max_range_m - 0.5
        latent = self.encoder(pixels)
        mu = self.trunk(torch.cat([latent, self.state_features(state)], dim=1))[:, : self.action_dim]
        return self.action_mid + self.action_half * torch.tanh(mu)


def git_commit() -> str:
    """The current commit of the repository, or 'unknown' outside a git checkout."""
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=5,
                             cwd=Path(__file__).resolve().parent)
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def export_policy(agent, path: str | Path, control_period_s: float, provenance: dict,
                  task: TaskSpec = DEFAULT_TASK_SPEC, onnx: bool = True, governor: GovernorSpec | None = None) -> None:
    """Write ``path`` as a TorchScript policy with ``policy.json`` metadata (``task``: what it was trained for;
    ``governor``: the speed governor it flies with, usually the one it was trained with).

    With ``onnx`` the same policy is also written beside it as ``<stem>.onnx`` (:func:`export_onnx`);
    without the ``onnx`` package that step is skipped with a note on stderr (a finished training run
    is never lost to a missing export dependency: ``python -m sitl.learn.export`` converts it later).
    """
    module = ExportedPolicy(agent).eval()
    metadata = build_metadata(agent.camera, agent.action_spec, control_period_s,
                              {"git_commit": git_commit(), **provenance}, task, governor, agent.memory)
    save_policy(module, metadata, path)
    if onnx:
        try:
            import onnx as _onnx  # noqa: F401, PLC0415 - only to know whether the export can run
        except ImportError:
            print(f"note: {path} written; no ONNX twin (the onnx package is missing: pip install "
                  "'swarmnav[train]', then python -m sitl.learn.export)", file=sys.stderr)
            return
        export_onnx(path, Path(path).with_suffix(".onnx"))


def export_onnx(torchscript_path: str | Path, onnx_path: str | Path) -> float:
    """Convert a TorchScript policy file to ONNX; return the largest action difference on test observations.

    The graph has inputs ``depth`` [B, frames, H, W] and ``state`` [B, 6] (longer with remembered depth) and output ``action``
    [B, 3] (B dynamic), and carries the TorchScript file's ``policy.json`` unchanged in its
    ``metadata_props``. Raises :class:`PolicyFileError` if the source is not a valid policy
    or the two formats disagree by more than :data:`ONNX_TOLERANCE`.
    """
    import onnx  # noqa: PLC0415 - export-time only (swarmnav[train])

    policy = load_policy(torchscript_path)
    cam = policy.camera
    example = (torch.full((1, cam.frames, cam.height, cam.width), cam.max_range_m), torch.zeros(1, policy.state_dim))
    # The network without the TorchScript input check (companion/checked_policy.py): the ONNX
    # graph declares its input shapes instead, and the exporter would otherwise have to trace the check.
    module = unwrap_checked(policy.module)
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        # The TorchScript-based exporter is the one that takes a TorchScript module (the file we
        # fly); torch >= 2.9 marks it deprecated and warns about the scripted method's signature.
        for message in (r"You are using the legacy TorchScript-based ONNX export", r".*torch\.jit",
                        r"The feature will be removed"):  # the last: the legacy exporter's own logging helper
            warnings.filterwarnings("ignore", category=DeprecationWarning, message=message)
        warnings.filterwarnings("ignore", category=UserWarning, message=r"no signature found")
        torch.onnx.export(module, example, buffer, input_names=[INPUT_DEPTH, INPUT_STATE],
                          output_names=[OUTPUT_ACTION], opset_version=ONNX_OPSET, dynamo=False,
                          dynamic_axes={INPUT_DEPTH: {0: "batch"}, INPUT_STATE: {0: "batch"},
                                        OUTPUT_ACTION: {0: "batch"}})
    model = onnx.load_from_string(buffer.getvalue())
    # The exporter drops an input the module never reads (a test policy that ignores depth);
    # the contract says both are there, so put it back as an unused input.
    declared = {i.name for i in model.graph.input}
    for name, shape in ((INPUT_DEPTH, ["batch", cam.frames, cam.height, cam.width]), (INPUT_STATE, ["batch", policy.state_dim])):
        if name not in declared:
            model.graph.input.append(onnx.helper.make_tensor_value_info(name, onnx.TensorProto.FLOAT, shape))
    model.graph.input.sort(key=lambda i: (i.name != INPUT_DEPTH, i.name != INPUT_STATE))  # depth, state
    model.doc_string = "swarmnav policy: depth (m) and state in, physical actions out (docs/policy_file.md)"
    entry = model.metadata_props.add()
    entry.key, entry.value = METADATA_KEY, json.dumps(policy.metadata, indent=2)
    onnx.checker.check_model(model)
    Path(onnx_path).parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(onnx_path))
    exported = load_policy(onnx_path)
    depth, state = check_observations(cam.frames, cam.height, cam.width, cam.max_range_m, memory=policy.memory)
    difference = float(np.max(np.abs(exported.act(depth, state) - policy.act(depth, state))))
    if not difference <= ONNX_TOLERANCE:
        raise PolicyFileError(f"{onnx_path}: ONNX actions differ from TorchScript's by {difference:.3g} "
                              f"(tolerance {ONNX_TOLERANCE:g})")
    return difference


def check_observations(frames: int, height: int, width: int, max_range_m: float, count: int = 64,
                       seed: int = 0, memory: MemorySpec | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A batch of varied observations for comparing formats: depth with near, far and missing returns
    (and, with ``memory``, remembered sector ranges from touching to nothing remembered)."""
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.2, max_range_m, (count, frames, height, width)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.1] = max_range_m  # nothing in range
    depth[: count // 4] = np.linspace(0.5, max_range_m, width, dtype=np.float32)  # a slanted wall
    state = np.column_stack([rng.uniform(-30, 30, count), rng.uniform(-30, 30, count), rng.uniform(-5, 5, count),
                             rng.uniform(0, 2, count), rng.uniform(-0.5, 0.5, count),
                             rng.uniform(-0.5, 0.5, count)]).astype(np.float32)
    if memory is not None:
        ranges = rng.uniform(0.0, 1.2 * memory.range_m, (count, memory.num_sectors)).astype(np.float32)
        state = np.concatenate([state, np.minimum(ranges, memory.range_m)], axis=1)
    return depth, state


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sitl.learn.export",
                                     description="Convert a TorchScript policy file to ONNX (same inputs, "
                                                 "outputs and policy.json metadata).")
    parser.add_argument("policy", type=Path, help="TorchScript policy file, e.g. models/policy.pt")
    parser.add_argument("--output", "-o", type=Path, help="ONNX file to write (default: the policy's name, .onnx)")
    args = parser.parse_args(argv)
    output = args.output or args.policy.with_suffix(".onnx")
    if output.suffix.lower() != ".onnx":
        parser.error(f"the output must end in .onnx (companion --model dispatches on it), got {output}")
    try:
        difference = export_onnx(args.policy, output)
    except PolicyFileError as err:
        print(f"error: {err}", file=sys.stderr)
        return 3
    except ImportError as err:
        print(f"error: ONNX export needs the onnx package: pip install 'swarmnav[train]' ({err})", file=sys.stderr)
        return 1
    print(f"wrote {output} (largest action difference to {args.policy}: {difference:.2g})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
