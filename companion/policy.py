"""The policy file contract: ``policy.pt`` is what training hands to flight.

A policy file is a TorchScript module saved with ``torch.jit.save`` that carries its
metadata as the extra file ``policy.json``. Its ``forward(depth, state)`` takes

* ``depth``: float32 [B, frames, H, W], planar depth in metres, oldest frame first, pixels
  with no return set to ``max_range_m`` (exactly what :mod:`companion.observation` builds);
* ``state``: float32 [B, 6] laid out as ``metadata["state_names"]``;

and returns float32 [B, 3] deterministic actions in physical units, already inside the
action bounds. Normalisation happens inside the module, so callers pass raw metres.

``policy.json`` (format version 1)::

    {
      "format_version": 1,
      "depth": {"height": 32, "width": 32, "frames": 3, "hfov_deg": 90.0, "max_range_m": 20.0,
                "units": "m", "kind": "planar", "order": "oldest_first"},
      "control_period_s": 0.1,
      "body_frame": "heading FRD ...",
      "state_names": ["goal_fwd_m", ...],
      "action": {"names": [...], "low": [...], "high": [...]},
      "provenance": {"method": ..., "scenario": ..., "steps": ..., "wall_time_s": ...,
                     "git_commit": ..., "evaluation": {...}}
    }

:func:`load_policy` validates a file against this contract and refuses anything else with
a :class:`PolicyFileError` that says what is wrong.
"""

from __future__ import annotations

import json
import warnings
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion.spec import STATE_NAMES, ActionSpec, CameraSpec

FORMAT_VERSION = 1
METADATA_FILE = "policy.json"
BODY_FRAME = ("heading frame FRD as MAV_FRAME_BODY_NED: x forward along the heading, y right, z down; "
              "yaw from north, positive turning right")


class PolicyFileError(ValueError):
    """A file that is not a valid swarmnav policy."""


def build_metadata(camera: CameraSpec, action: ActionSpec, control_period_s: float, provenance: dict) -> dict:
    """The ``policy.json`` content for a policy trained with ``camera`` and ``action``."""
    return {
        "format_version": FORMAT_VERSION,
        "depth": {
            "height": camera.height, "width": camera.width, "frames": camera.frames,
            "hfov_deg": camera.hfov_deg, "max_range_m": camera.max_range_m,
            "units": "m", "kind": "planar", "order": "oldest_first",
        },
        "control_period_s": control_period_s,
        "body_frame": BODY_FRAME,
        "state_names": list(STATE_NAMES),
        "action": {"names": list(action.names), "low": list(action.low), "high": list(action.high)},
        "provenance": provenance,
    }


def save_policy(module, metadata: dict, path: str | Path) -> None:
    """Script ``module`` (if it is not already TorchScript) and save it with its metadata."""
    import torch

    _check_metadata(metadata, str(path))
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
    """A validated policy: the TorchScript module and what its metadata promises."""

    module: object
    metadata: dict
    camera: CameraSpec
    action: ActionSpec
    control_period_s: float
    path: str

    def act(self, depth_m: np.ndarray, state: np.ndarray) -> np.ndarray:
        """Deterministic actions [B, 3] (float32) for a batch of observations."""
        import torch

        with torch.inference_mode():
            out = self.module(torch.from_numpy(np.ascontiguousarray(depth_m, dtype=np.float32)),
                              torch.from_numpy(np.ascontiguousarray(state, dtype=np.float32)))
        return out.numpy()


def _require(cond: bool, path: str, message: str) -> None:
    if not cond:
        raise PolicyFileError(f"{path}: {message}")


def _check_metadata(meta: dict, path: str) -> None:
    _require(isinstance(meta, dict), path, "policy.json is not a JSON object")
    version = meta.get("format_version")
    _require(version == FORMAT_VERSION, path,
             f"unsupported policy format_version {version!r} (this companion reads version {FORMAT_VERSION})")
    for key in ("depth", "control_period_s", "state_names", "action", "body_frame", "provenance"):
        _require(key in meta, path, f"policy.json lacks the field {key!r}")
    depth = meta["depth"]
    for key in ("height", "width", "frames", "hfov_deg", "max_range_m", "units", "kind"):
        _require(key in depth, path, f"policy.json depth lacks the field {key!r}")
    _require(depth["units"] == "m" and depth["kind"] == "planar", path,
             f"depth must be planar metres, file says {depth['kind']} in {depth['units']}")
    _require(list(meta["state_names"]) == list(STATE_NAMES), path,
             f"state layout {meta['state_names']} differs from this companion's {list(STATE_NAMES)}")
    action = meta["action"]
    _require(len(action.get("names", [])) == 3 and len(action.get("low", [])) == 3 and len(action.get("high", [])) == 3,
             path, "action must name 3 components with low and high bounds")
    _require(all(lo < hi for lo, hi in zip(action["low"], action["high"])), path, "action low must be below high")
    _require(float(meta["control_period_s"]) > 0, path, "control_period_s must be > 0")


def load_policy(path: str | Path, *, check_forward: bool = True) -> LoadedPolicy:
    """Load and validate a policy file; raise :class:`PolicyFileError` with the reason if invalid.

    With ``check_forward`` the module is run once on a blank observation and must return
    finite actions of shape [1, 3] inside its declared bounds.
    """
    import torch

    path = str(path)
    _require(Path(path).is_file(), path, "no such policy file")
    _require(zipfile.is_zipfile(path), path, "not a TorchScript policy file (not a zip archive: wrong or corrupted file)")
    extra = {METADATA_FILE: ""}
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
    _check_metadata(meta, path)
    depth = meta["depth"]
    try:
        camera = CameraSpec(width=int(depth["width"]), height=int(depth["height"]), hfov_deg=float(depth["hfov_deg"]),
                            max_range_m=float(depth["max_range_m"]), frames=int(depth["frames"]))
    except ValueError as err:
        raise PolicyFileError(f"{path}: invalid depth specification ({err})") from err
    action = ActionSpec(tuple(meta["action"]["names"]), tuple(map(float, meta["action"]["low"])),
                        tuple(map(float, meta["action"]["high"])))
    module.eval()
    policy = LoadedPolicy(module, meta, camera, action, float(meta["control_period_s"]), path)
    if check_forward:
        blank_depth = np.full((1, camera.frames, camera.height, camera.width), camera.max_range_m, np.float32)
        blank_state = np.zeros((1, len(STATE_NAMES)), np.float32)
        blank_state[0, 0] = 10.0
        try:
            out = policy.act(blank_depth, blank_state)
        except Exception as err:
            raise PolicyFileError(f"{path}: forward(depth, state) failed on a blank observation ({err})") from err
        _require(out.shape == (1, 3), path, f"forward returned shape {tuple(out.shape)}, expected (1, 3)")
        _require(bool(np.all(np.isfinite(out))), path, "forward returned non-finite actions")
        low, high = action.low_array() - 1e-5, action.high_array() + 1e-5
        _require(bool(np.all((out >= low) & (out <= high))), path, f"forward returned {out[0]} outside the action bounds")
    return policy
