"""Running a policy file in ONNX form with onnxruntime (``companion --model policy.onnx``).

``policy.onnx`` is the same policy as ``policy.pt`` (docs/policy_file.md): inputs ``depth``
float32 [B, frames, H, W] (planar metres, oldest first) and ``state`` float32 [B, 6] (longer with
remembered depth), output ``action`` float32 [B, 3] in physical units, and the same ``policy.json`` metadata, stored in
the model's ``metadata_props`` under the key ``policy.json``. onnxruntime runs it without
torch on the companion computers people fly (a Raspberry Pi, a Jetson with the CUDA and
TensorRT execution providers). :func:`companion.policy.load_policy` dispatches here for a
``.onnx`` file, so the metadata checks are the TorchScript file's.

Reading a file needs ``onnxruntime`` only (``pip install 'swarmnav[onnx]'``, or the
``onnxruntime-gpu`` build on a GPU computer); writing one (:mod:`sitl.learn.export`) needs
``onnx`` too.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: Names of the graph's inputs and output (the arguments and result of ``forward(depth, state)``).
INPUT_DEPTH, INPUT_STATE, OUTPUT_ACTION = "depth", "state", "action"
#: ``metadata_props`` key holding ``policy.json`` (the TorchScript file's extra-file name).
METADATA_KEY = "policy.json"

#: ``--onnx-provider`` choices and the onnxruntime execution providers each asks for, best first.
#: ``auto`` takes whichever of them this onnxruntime build offers (the CPU build: CPU only).
PROVIDER_CHOICES: dict[str, tuple[str, ...]] = {
    "auto": ("TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"),
    "cpu": ("CPUExecutionProvider",),
    "cuda": ("CUDAExecutionProvider", "CPUExecutionProvider"),
    "tensorrt": ("TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"),
}


class OnnxUnavailableError(RuntimeError):
    """onnxruntime is not installed, or lacks an execution provider that was asked for."""


def select_providers(choice: str = "auto") -> list[str]:
    """The execution providers for ``--onnx-provider choice`` that this onnxruntime build has.

    ``cuda`` and ``tensorrt`` are refused (:class:`OnnxUnavailableError`) when the build lacks
    them: an operator who asked for the GPU must not silently fly on the CPU.
    """
    if choice not in PROVIDER_CHOICES:
        raise ValueError(f"unknown onnx provider {choice!r}: use one of {', '.join(PROVIDER_CHOICES)}")
    ort = _onnxruntime()
    available = set(ort.get_available_providers())
    wanted = PROVIDER_CHOICES[choice]
    if choice != "auto" and wanted[0] not in available:
        raise OnnxUnavailableError(f"onnxruntime here has no {wanted[0]} (available: {', '.join(sorted(available))})")
    return [p for p in wanted if p in available]


def _onnxruntime():
    try:
        import onnxruntime  # noqa: PLC0415 - optional extra, only for .onnx files
    except ImportError as err:
        raise OnnxUnavailableError("an .onnx policy needs onnxruntime: pip install 'swarmnav[onnx]' "
                                   "(onnxruntime-gpu on a GPU computer)") from err
    return onnxruntime


class OnnxPolicyModule:
    """An onnxruntime session behind the policy's ``act``: numpy in, numpy out, no torch.

    Args:
        session: an ``onnxruntime.InferenceSession`` of a policy graph.
    """

    def __init__(self, session) -> None:
        self.session = session
        self.providers: list[str] = list(session.get_providers())

    def run_numpy(self, depth_m: np.ndarray, state: np.ndarray) -> np.ndarray:
        """Deterministic actions [B, 3] (float32) for a batch of observations."""
        feeds = {INPUT_DEPTH: np.ascontiguousarray(depth_m, dtype=np.float32),
                 INPUT_STATE: np.ascontiguousarray(state, dtype=np.float32)}
        return self.session.run([OUTPUT_ACTION], feeds)[0]

    def eval(self) -> OnnxPolicyModule:
        """Nothing to switch (a graph is always in inference mode); kept for the TorchScript interface."""
        return self


def read_onnx_policy(path: str, providers: Sequence[str] | None = None,
                     threads: int = 1) -> tuple[OnnxPolicyModule, str]:
    """Open ``path`` with onnxruntime and return (module, the ``policy.json`` text, "" if absent).

    Raises :class:`ValueError` with a one-line reason for a file that is not a policy graph
    (not ONNX, wrong inputs or output) and :class:`OnnxUnavailableError` without onnxruntime.
    ``threads``: intra-op threads (1, like the TorchScript path: predictable latency).
    """
    ort = _onnxruntime()
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.log_severity_level = 3  # errors only: provider fallbacks are reported by us, once
    try:
        session = ort.InferenceSession(path, sess_options=options,
                                       providers=list(providers) if providers else ["CPUExecutionProvider"])
    except Exception as err:  # onnxruntime raises its own Fail/InvalidProtobuf/... types
        text = str(err).strip()
        raise ValueError(f"not a loadable ONNX model ({text.splitlines()[0] if text else type(err).__name__})") from err
    inputs = {i.name: i for i in session.get_inputs()}
    outputs = [o.name for o in session.get_outputs()]
    if set(inputs) != {INPUT_DEPTH, INPUT_STATE} or OUTPUT_ACTION not in outputs:
        raise ValueError(f"ONNX graph has inputs {sorted(inputs)} and outputs {outputs}, "
                         f"expected inputs {INPUT_DEPTH!r}, {INPUT_STATE!r} and output {OUTPUT_ACTION!r}")
    for name, item in inputs.items():
        if item.type != "tensor(float)":
            raise ValueError(f"ONNX input {name!r} is {item.type}, expected tensor(float)")
    metadata = session.get_modelmeta().custom_metadata_map.get(METADATA_KEY, "")
    return OnnxPolicyModule(session), metadata


def shape_problem(module: OnnxPolicyModule, frames: int, height: int, width: int, state_dim: int) -> str | None:
    """Why the graph's declared input shapes disagree with its ``policy.json``, or None.

    Dynamic axes (declared by name, such as the batch) match anything.
    """
    expected = {INPUT_DEPTH: [None, frames, height, width], INPUT_STATE: [None, state_dim]}
    for item in module.session.get_inputs():
        declared = list(item.shape)
        want = expected[item.name]
        same = len(declared) == len(want) and all(
            w is None or not isinstance(d, int) or d == w for d, w in zip(declared, want))
        if not same:
            return f"ONNX input {item.name!r} has shape {declared}, policy.json says {['B', *want[1:]]}"
    return None
