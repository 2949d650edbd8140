"""The policy file contract: ``policy.pt`` is what training hands to flight.

A policy file is a TorchScript module saved with ``torch.jit.save`` that carries its
metadata as the extra file ``policy.json``. Its ``forward(depth, state)`` takes

* ``depth``: float32 [B, frames, H, W], planar depth in metres, oldest frame first, pixels
  with no return set to ``max_range_m`` (exactly what :mod:`companion.observation` builds);
* ``state``: float32 [B, 6] laid out as ``metadata["state_names"]`` (longer with the optional
  ``memory``: the remembered sector ranges follow, :class:`companion.spec.MemorySpec`);

and returns float32 [B, 3] deterministic actions in physical units, already inside the
action bounds. Normalisation happens inside the module, so callers pass raw metres.

``policy.json`` (format version 2; docs/policy_file.md is the full contract)::

    {
      "format_version": 2,
      "depth": {"height": 32, "width": 48, "frames": 3, "frame_stride": 1, "hfov_deg": 87.0, "vfov_deg": 58.0,
                "mount_pitch_deg": 0.0, "min_range_m": 0.2, "max_range_m": 10.0,
                "invalid_value_m": 0.0, "invalid_reads_as": "max_range_m",
                "units": "m", "kind": "planar", "order": "oldest_first"},
      "control_period_s": 0.1,
      "body_frame": "heading FRD ...",
      "state_names": ["goal_fwd_m", ...],
      "action": {"names": [...], "low": [...], "high": [...]},
      "task": {"collision_radius_m": 0.3, "arrival_radius_m": 0.5, "max_episode_steps": 400},
      "provenance": {"method": ..., "scenario": ..., "steps": ..., "wall_time_s": ...,
                     "git_commit": ..., "evaluation": {...}}
    }

:func:`load_policy` validates a file against this contract and refuses anything else with
a :class:`PolicyFileError` that says what is wrong. Version-1 files (the format before the
real camera) are read as documented: a level camera at the vehicle's centre with square
pixels (the vertical field of view from ``hfov_deg`` and the aspect), no minimum range,
no-return pixels already ``max_range_m``, and ``task`` the defaults when absent;
:attr:`LoadedPolicy.notes` says so, and the companion prints it.

The same policy exported as ONNX (``policy.onnx``: inputs ``depth`` and ``state``, output
``action``, ``policy.json`` in the graph's ``metadata_props``) loads through the same checks
and runs with onnxruntime (:mod:`companion.onnx_policy`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import warnings
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion.governor import ADDED_SETTINGS, MAY_BE_INFINITE, GovernorSpec
from companion.spec import (
    CONTROL_PERIOD_MAX_S,
    CONTROL_PERIOD_MIN_S,
    DEFAULT_ACTION_SPEC,
    POLICY_MAX_FRAMES,
    POLICY_MAX_IMAGE_SIDE_PX,
    POLICY_MAX_RANGE_M,
    DEFAULT_TASK_SPEC,
    INVALID_DEPTH_M,
    MAX_FRAME_AGE,
    MAX_FRAME_STRIDE,
    MAX_MOUNT_PITCH_DEG,
    MEMORY_MAX_STEPS,
    STATE_NAMES,
    ActionSpec,
    CameraSpec,
    MemorySpec,
    TaskSpec,
    state_dim_for,
    state_names_for,
)

FORMAT_VERSION = 2  # what export writes
READABLE_VERSIONS = (1, 2)
#: The invalid-pixel convention of a version-2 file, the only one this companion implements:
#: a raw pixel that reads this value (or is negative or non-finite) has no data, and the policy
#: sees it as ``max_range_m`` (companion.observation.clean_depth).
INVALID_VALUE_M = INVALID_DEPTH_M
INVALID_READS_AS = "max_range_m"
METADATA_FILE = "policy.json"
BODY_FRAME = ("heading frame FRD as MAV_FRAME_BODY_NED: x forward along the heading, y right, z down; "
              "yaw from north, positive turning right")


class PolicyFileError(ValueError):
    """A file that is not a valid swarmnav policy."""


def build_metadata(camera: CameraSpec, action: ActionSpec, control_period_s: float, provenance: dict,
                   task: TaskSpec = DEFAULT_TASK_SPEC, governor: GovernorSpec | None = None,
                   memory: MemorySpec | None = None) -> dict:
    """The ``policy.json`` content for a policy trained with ``camera``, ``action`` and ``task`` (and the
    speed ``governor`` after it, and the remembered-depth input ``memory``, if any)."""
    return {
        "format_version": FORMAT_VERSION,
        "depth": {
            "height": camera.height, "width": camera.width, "frames": camera.frames,
            "frame_stride": camera.frame_stride,
            "hfov_deg": camera.hfov_deg, "vfov_deg": round(camera.vertical_fov_deg, 6),
            "mount_pitch_deg": camera.mount_pitch_deg,
            "min_range_m": camera.min_range_m, "max_range_m": camera.max_range_m,
            "invalid_value_m": INVALID_VALUE_M, "invalid_reads_as": INVALID_READS_AS,
            "units": "m", "kind": "planar", "order": "oldest_first",
            # Only where the stack is not evenly spaced (older files and readers never see it).
            **({"frame_ages": list(camera.frame_ages)} if camera.frame_ages else {}),
        },
        "control_period_s": control_period_s,
        "body_frame": BODY_FRAME,
        "state_names": list(state_names_for(memory)),
        # Only for a policy with remembered depth (older files and readers never see it).
        **({"memory": memory.to_dict()} if memory is not None else {}),
        "action": {"names": list(action.names), "low": list(action.low), "high": list(action.high)},
        "task": task.to_dict(),
        **({"governor": governor.to_dict()} if governor is not None else {}),
        "provenance": provenance,
    }


def save_policy(module, metadata: dict, path: str | Path) -> None:
    """Save ``module`` as TorchScript with its metadata, wrapped in the input check.

    The wrapper (:class:`companion.checked_policy.ShapeCheckedPolicy`; a module that already has
    one is unwrapped first, so the check always matches ``metadata``) refuses depth or state of
    another shape than ``metadata`` declares with a message that names the expected shape, for
    users who run the file with a bare ``torch.jit.load``. ``module`` may be a Python module or
    TorchScript.
    """
    import torch

    from companion.checked_policy import ShapeCheckedPolicy, unwrap_checked

    camera, _, _, _, memory = _check_metadata(metadata, str(path))
    # a loaded file saved again is unwrapped first: its check follows the metadata written now
    module = ShapeCheckedPolicy(unwrap_checked(module), camera.frames, camera.height, camera.width,
                                state_dim_for(memory))
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with _QuietJitDeprecation():
        scripted = module if isinstance(module, torch.jit.ScriptModule) else torch.jit.script(module)
        torch.jit.save(scripted, str(path), _extra_files={METADATA_FILE: json.dumps(metadata, indent=2)})


class _QuietJitDeprecation(warnings.catch_warnings):
    """Silence torch's TorchScript deprecation warning inside the block.

    TorchScript is the contract: it runs on the vehicle without the model's Python code.
    torch >= 2.9 marks it deprecated in favour of torch.export, which has no such loader yet.
    """

    def __enter__(self):
        result = super().__enter__()
        warnings.filterwarnings("ignore", category=DeprecationWarning, message=r".*torch\.jit.*")
        return result


@dataclass
class LoadedPolicy:
    """A validated policy: the TorchScript module (or onnxruntime session) and what its metadata promises."""

    module: object
    metadata: dict
    camera: CameraSpec
    action: ActionSpec
    control_period_s: float
    path: str
    task: TaskSpec = DEFAULT_TASK_SPEC
    format_version: int = FORMAT_VERSION
    #: How an older file was read (empty for a current one): the companion prints these.
    notes: tuple[str, ...] = ()
    #: The speed governor the policy flies with (policy.json's optional ``governor``: the one it trained with, or
    #: its run's ``--flight-governor-setting``).
    governor: GovernorSpec | None = None
    #: The remembered-depth input appended to its state (policy.json's optional ``memory``), if any.
    memory: MemorySpec | None = None

    @property
    def state_dim(self) -> int:
        """Entries of the state this policy takes (6, plus the remembered sector ranges)."""
        return state_dim_for(self.memory)

    def blank_observation(self) -> tuple[np.ndarray, np.ndarray]:
        """``(depth [1, frames, H, W], state [1, state_dim])`` of an empty world with the goal 10 m ahead
        (nothing in range, nothing remembered): what warm-up and the load check feed the policy."""
        camera = self.camera
        depth = np.full((1, camera.frames, camera.height, camera.width), camera.max_range_m, np.float32)
        state = np.zeros((1, self.state_dim), np.float32)
        state[0, 0] = 10.0
        if self.memory is not None:
            state[0, len(STATE_NAMES):] = self.memory.range_m
        return depth, state

    def act(self, depth_m: np.ndarray, state: np.ndarray) -> np.ndarray:
        """Deterministic actions [B, 3] (float32) for a batch of observations."""
        run_numpy = getattr(self.module, "run_numpy", None)
        if run_numpy is not None:  # an onnxruntime session (companion.onnx_policy): no torch involved
            return run_numpy(depth_m, state)
        import torch

        with torch.inference_mode():
            out = self.module(torch.from_numpy(np.ascontiguousarray(depth_m, dtype=np.float32)),
                              torch.from_numpy(np.ascontiguousarray(state, dtype=np.float32)))
        return out.numpy()


def torchscript_error_line(err: BaseException) -> str:
    """The line of a (TorchScript) exception that says why. The interpreter's message starts with
    "The following operation failed ..." and a traceback, and ends with the raised error
    (``builtins.ValueError: ...`` from the input check, ``RuntimeError: mat1 and mat2 ...``): that
    last error's message, else the first line."""
    lines = [line.strip() for line in str(err).strip().splitlines() if line.strip()]
    raised = [line.split(": ", 1)[1] for line in lines
              if re.match(r"^(builtins\.)?[A-Za-z_.]*(Error|Exception): ", line)]
    return raised[-1] if raised else (lines[0] if lines else type(err).__name__)


def _require(cond: bool, path: str, message: str) -> None:
    if not cond:
        raise PolicyFileError(f"{path}: {message}")


def _is_number(value: object) -> bool:
    """A JSON number (``true``/``false`` are not numbers, although Python's bool is an int)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _as_float(value: int | float) -> float:
    """``value`` as a float; an integer too big for a float (JSON allows any) becomes inf."""
    try:
        return float(value)
    except OverflowError:
        return math.inf


def _finite_number(value: object, path: str, name: str) -> float:
    _require(_is_number(value), path, f"{name} must be a number, file says {value!r:.40}")
    number = _as_float(value)
    _require(math.isfinite(number), path, f"{name} must be finite, file says {value!r:.40}")
    return number


def _boolean(value: object, path: str, name: str) -> bool:
    _require(isinstance(value, bool), path, f"{name} must be true or false, file says {value!r:.40}")
    return value


def _integer(value: object, path: str, name: str, low: int, high: int) -> int:
    ok = _is_number(value) and math.isfinite(_as_float(value)) and _as_float(value).is_integer()
    _require(ok, path, f"{name} must be an integer, file says {value!r:.40}")
    _require(low <= value <= high, path, f"{name} must be in {low}..{high}, file says {value!r}")
    return int(value)


def _numbers(value: object, path: str, name: str, count: int) -> tuple[float, ...]:
    _require(isinstance(value, list) and len(value) == count, path,
             f"{name} must be a list of {count} numbers, file says {value!r}")
    return tuple(_finite_number(v, path, f"{name}[{i}]") for i, v in enumerate(value))


def _check_metadata(meta: object, path: str) -> tuple[CameraSpec, ActionSpec, float, TaskSpec, MemorySpec | None]:
    """Check ``policy.json`` field by field (types first) against this companion's spec.

    Returns the camera, action bounds, control period, task and remembered-depth input it declares; raises
    :class:`PolicyFileError` naming the first bad field. Nothing from the file is used
    before its type and range are known, so a hostile file gets a reason, never a traceback.
    """
    _require(isinstance(meta, dict), path, "policy.json is not a JSON object")
    version = meta.get("format_version")
    _require(_is_number(version) and version in READABLE_VERSIONS, path,
             f"unsupported policy format_version {version!r} (this companion reads versions "
             f"{', '.join(str(v) for v in READABLE_VERSIONS)})")
    for key in ("depth", "control_period_s", "state_names", "action", "body_frame", "provenance"):
        _require(key in meta, path, f"policy.json lacks the field {key!r}")

    depth = meta["depth"]
    _require(isinstance(depth, dict), path, f"depth must be a JSON object, file says {depth!r}")
    for key in ("height", "width", "frames", "hfov_deg", "max_range_m", "units", "kind"):
        _require(key in depth, path, f"policy.json depth lacks the field {key!r}")
    _require(depth["units"] == "m" and depth["kind"] == "planar", path,
             f"depth must be planar metres, file says {depth['kind']!r} in {depth['units']!r}")
    _require(depth.get("order", "oldest_first") == "oldest_first", path,
             f"depth frames must be ordered oldest_first, file says {depth.get('order')!r}")
    side = POLICY_MAX_IMAGE_SIDE_PX
    height = _integer(depth["height"], path, "depth height", 1, side)
    width = _integer(depth["width"], path, "depth width", 1, side)
    frames = _integer(depth["frames"], path, "depth frames", 1, POLICY_MAX_FRAMES)
    # Optional (files written before it existed stack consecutive frames).
    geometry = {"frame_stride": _integer(depth.get("frame_stride", 1), path, "depth frame_stride", 1,
                                         MAX_FRAME_STRIDE)}
    if "frame_ages" in depth:  # optional: unevenly spaced stacks (docs/policy_file.md)
        ages = depth["frame_ages"]
        _require(isinstance(ages, list) and len(ages) == frames, path,
                 f"depth frame_ages must be a list of {frames} integers (one per frame), file says {ages!r:.60}")
        geometry["frame_ages"] = tuple(_integer(a, path, f"depth frame_ages[{i}]", 0, MAX_FRAME_AGE)
                                       for i, a in enumerate(ages))
    hfov_deg = _finite_number(depth["hfov_deg"], path, "depth hfov_deg")
    max_range_m = _finite_number(depth["max_range_m"], path, "depth max_range_m")
    _require(0 < max_range_m <= POLICY_MAX_RANGE_M, path,
             f"depth max_range_m must be in (0, {POLICY_MAX_RANGE_M:g}] m, file says {max_range_m:g}")
    if version >= 2:
        for key in ("vfov_deg", "mount_pitch_deg", "min_range_m", "invalid_value_m", "invalid_reads_as"):
            _require(key in depth, path, f"policy.json depth lacks the field {key!r} (required by format version 2)")
        geometry["vfov_deg"] = _finite_number(depth["vfov_deg"], path, "depth vfov_deg")
        geometry["mount_pitch_deg"] = _finite_number(depth["mount_pitch_deg"], path, "depth mount_pitch_deg")
        _require(abs(geometry["mount_pitch_deg"]) <= MAX_MOUNT_PITCH_DEG, path,
                 f"depth mount_pitch_deg must be within +-{MAX_MOUNT_PITCH_DEG:g} deg, "
                 f"file says {geometry['mount_pitch_deg']:g}")
        geometry["min_range_m"] = _finite_number(depth["min_range_m"], path, "depth min_range_m")
        invalid = _finite_number(depth["invalid_value_m"], path, "depth invalid_value_m")
        _require(invalid == INVALID_VALUE_M and depth["invalid_reads_as"] == INVALID_READS_AS, path,
                 f"depth invalid-pixel convention {invalid:g} -> {depth['invalid_reads_as']!r:.40} differs from this "
                 f"companion's {INVALID_VALUE_M:g} -> {INVALID_READS_AS!r}")
    try:
        camera = CameraSpec(width=width, height=height, hfov_deg=hfov_deg, max_range_m=max_range_m, frames=frames,
                            **geometry)
    except ValueError as err:
        raise PolicyFileError(f"{path}: invalid depth specification ({err})") from None

    period = meta["control_period_s"]
    _require(_is_number(period), path, f"control_period_s must be a number of seconds, file says {period!r:.40}")
    period = _as_float(period)
    _require(CONTROL_PERIOD_MIN_S <= period <= CONTROL_PERIOD_MAX_S, path,
             f"control_period_s must be in {CONTROL_PERIOD_MIN_S:g}..{CONTROL_PERIOD_MAX_S:g} s, file says {period!r}")

    memory = _check_memory(meta.get("memory"), path)
    names = meta["state_names"]
    expected = list(state_names_for(memory))
    _require(isinstance(names, list) and names == expected, path,
             f"state layout {names!r:.200} differs from this companion's {expected!r:.200}")
    _require(isinstance(meta["body_frame"], str), path, "body_frame must be a string")
    _require(isinstance(meta["provenance"], dict), path, "provenance must be a JSON object")

    # The action must be exactly this companion's (names and order), with finite bounds inside
    # the paper's: a file cannot widen what the companion will command.
    action = meta["action"]
    _require(isinstance(action, dict), path, f"action must be a JSON object, file says {action!r}")
    spec = DEFAULT_ACTION_SPEC
    _require(action.get("names") == list(spec.names), path,
             f"action names {action.get('names')!r} differ from this companion's {list(spec.names)}")
    low = _numbers(action.get("low"), path, "action low", spec.dim)
    high = _numbers(action.get("high"), path, "action high", spec.dim)
    for name, lo, hi, lo_max, hi_max in zip(spec.names, low, high, spec.low, spec.high):
        _require(lo < hi, path, f"action {name}: low {lo:g} must be below high {hi:g}")
        _require(lo_max <= lo and hi <= hi_max, path,
                 f"action {name} bounds [{lo:g}, {hi:g}] exceed the onboard limits [{lo_max:g}, {hi_max:g}]")
    if version >= 2:
        _require("task" in meta, path, "policy.json lacks the field 'task' (required by format version 2)")
    return camera, ActionSpec(spec.names, low, high), float(period), _check_task(meta.get("task"), path), memory


def version1_notes(meta: dict, camera: CameraSpec) -> tuple[str, ...]:
    """How a version-1 ``policy.json`` is read (docs/policy_file.md, "Version 1"), one line each."""
    task = "its task" if meta.get("task") is not None else (
        f"task defaults (R {DEFAULT_TASK_SPEC.collision_radius_m:g} m, arrival {DEFAULT_TASK_SPEC.arrival_radius_m:g} m)")
    return (f"policy format version 1: read as a level camera, {camera.hfov_deg:g} x {camera.vertical_fov_deg:.4g} deg "
            f"(square pixels), range 0-{camera.max_range_m:g} m, invalid pixels read {camera.max_range_m:g} m, {task}",)


def _check_task(task: object, path: str) -> TaskSpec:
    """The ``task`` a policy was trained for (absent: the defaults, as in files written before it existed)."""
    if task is None:
        return DEFAULT_TASK_SPEC
    _require(isinstance(task, dict), path, f"task must be a JSON object, file says {task!r:.40}")
    radius = _finite_number(task.get("collision_radius_m"), path, "task collision_radius_m")
    arrival = _finite_number(task.get("arrival_radius_m"), path, "task arrival_radius_m")
    _require(0 < radius <= 10 and 0 < arrival <= 10, path,
             f"task radii must be in (0, 10] m, file says collision {radius:g}, arrival {arrival:g}")
    steps = _integer(task.get("max_episode_steps"), path, "task max_episode_steps", 1, 1_000_000)
    return TaskSpec(collision_radius_m=radius, arrival_radius_m=arrival, max_episode_steps=steps)


def _check_memory(memory: object, path: str) -> MemorySpec | None:
    """The remembered-depth input a policy takes (absent or null: none), every setting named."""
    if memory is None:
        return None
    _require(isinstance(memory, dict), path, f"memory must be a JSON object, file says {memory!r:.40}")
    names = [f.name for f in dataclasses.fields(MemorySpec)]
    _require(sorted(memory) == sorted(names), path,
             f"memory must have exactly the settings {names}, file says {sorted(memory)!r:.100}")
    values = dict(steps=_integer(memory["steps"], path, "memory steps", 1, MEMORY_MAX_STEPS),
                  every_steps=_integer(memory["every_steps"], path, "memory every_steps", 1, MEMORY_MAX_STEPS),
                  range_m=_finite_number(memory["range_m"], path, "memory range_m"),
                  pool=_integer(memory["pool"], path, "memory pool", 1, 16),
                  outside_view=_boolean(memory["outside_view"], path, "memory outside_view"))
    try:  # each value has its type; the spec checks how they go together
        return MemorySpec(**values)
    except ValueError as err:
        raise PolicyFileError(f"{path}: {err}") from None


def _check_governor(governor: object, path: str) -> GovernorSpec | None:
    """The speed governor a policy was trained with (absent or null: none), every setting named."""
    if governor is None:
        return None
    _require(isinstance(governor, dict), path, f"governor must be a JSON object, file says {governor!r:.40}")
    names = [f.name for f in dataclasses.fields(GovernorSpec)]
    unknown = sorted(set(governor) - set(names))
    _require(not unknown, path, f"governor has unknown settings {unknown} (this companion knows {names})")
    values = {}
    for name in names:
        if name in ADDED_SETTINGS and name not in governor:
            continue  # an older file, trained without it: the default
        value = governor.get(name)
        if name in MAY_BE_INFINITE and value is None:  # JSON has no inf: null is "never"
            values[name] = math.inf
            continue
        values[name] = _finite_number(value, path, f"governor {name}")
    try:
        return GovernorSpec(**values)
    except ValueError as err:
        raise PolicyFileError(f"{path}: {err}") from None


def load_policy(path: str | Path, *, check_forward: bool = True,
                providers: Sequence[str] | None = None) -> LoadedPolicy:
    """Load and validate a policy file; raise :class:`PolicyFileError` with the reason if invalid.

    A ``.onnx`` file is the same policy as an ONNX graph (:mod:`companion.onnx_policy`), run
    by onnxruntime with ``providers`` (default: CPU); anything else is read as TorchScript.
    With ``check_forward`` the module is run once on a blank observation and must return
    finite actions of shape [1, 3] inside its declared bounds.
    """
    import torch

    path = str(path)
    _require(Path(path).is_file(), path, "no such policy file")
    extra = {METADATA_FILE: ""}
    if Path(path).suffix.lower() == ".onnx":  # the same policy as an ONNX graph, run by onnxruntime
        from companion.onnx_policy import OnnxUnavailableError, read_onnx_policy, shape_problem

        try:
            module, extra[METADATA_FILE] = read_onnx_policy(path, providers, torch.get_num_threads())
        except (ValueError, OnnxUnavailableError) as err:
            raise PolicyFileError(f"{path}: {err}") from err
    else:
        _require(zipfile.is_zipfile(path), path,
                 "not a TorchScript policy file (not a zip archive: wrong or corrupted file)")
        try:
            with _QuietJitDeprecation():
                module = torch.jit.load(path, map_location="cpu", _extra_files=extra)
        except Exception as err:  # torch raises RuntimeError subclasses with long C++ traces
            first_line = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise PolicyFileError(f"{path}: not a loadable TorchScript module ({first_line})") from err
    _require(bool(extra[METADATA_FILE]), path, f"no {METADATA_FILE} inside: not a swarmnav policy file")
    try:
        meta = json.loads(extra[METADATA_FILE])
    except json.JSONDecodeError as err:
        raise PolicyFileError(f"{path}: {METADATA_FILE} is not valid JSON ({err})") from err
    camera, action, period_s, task, memory = _check_metadata(meta, path)
    state_dim = state_dim_for(memory)
    if Path(path).suffix.lower() == ".onnx":
        problem = shape_problem(module, camera.frames, camera.height, camera.width, state_dim)
        _require(problem is None, path, str(problem))
    module.eval()
    version = int(meta["format_version"])
    notes = version1_notes(meta, camera) if version == 1 else ()
    governor = _check_governor(meta.get("governor"), path)
    policy = LoadedPolicy(module, meta, camera, action, period_s, path, task, version, notes, governor, memory)
    if check_forward:
        blank_depth, blank_state = policy.blank_observation()
        try:
            out = policy.act(blank_depth, blank_state)
        except Exception as err:  # TorchScript errors span many lines: keep the one that says why
            raise PolicyFileError(f"{path}: forward(depth, state) failed on a blank observation "
                                  f"({torchscript_error_line(err)})") from err
        # Refuse a wrong shape here, by name: later it would only show as a hold blamed on "not finite".
        _require(out.shape == (1, 3), path, f"policy output has shape {list(out.shape)}, expected [1, 3]")
        _require(bool(np.all(np.isfinite(out))), path, "forward returned non-finite actions")
        low, high = action.low_array() - 1e-5, action.high_array() + 1e-5
        _require(bool(np.all((out >= low) & (out <= high))), path, f"forward returned {out[0]} outside the action bounds")
    return policy
