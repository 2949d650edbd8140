"""Flight recordings: the policy's depth frame, state and command of every control step.

``companion --record flight.snrec`` writes one; ``--camera replay:flight.snrec`` plays its
depth frames back through the same converter and control loop.

File format (version 1): one line of JSON (the header, UTF-8, ending in ``\\n``), then
fixed-size little-endian binary records back to back, one per control step in which the
companion had a depth frame. The header holds ``format`` ("swarmnav-recording"),
``version``, ``camera`` (the policy's :class:`~companion.spec.CameraSpec` as a dict),
``control_period_s``, ``policy`` (path) and ``record_dtype`` (numpy's description of one
record); a record holds

==============  =================  =====================================================
field           type               meaning
==============  =================  =====================================================
t_wall_s        float64            UNIX time of the step
t_mono_s        float64            monotonic time of the step (replay timing)
step            uint32             control step index
frame_seq       uint32             sequence number of the depth frame
hold            uint8              1 if the step sent a hold instead of the policy's action
depth_m         float32 [H, W]     newest depth frame as the policy saw it (metres)
state           float32 [6]        the policy's state input (``STATE_NAMES``)
action          float32 [3]        the command sent (``vel_fwd_m_s, vel_down_m_s, yaw_rate_rad_s``)
pos_ned_m       float32 [3]        position from odometry
yaw_rad         float32            heading from odometry
==============  =================  =====================================================

Records are appended as the flight goes, so a recording cut short by a crash or power loss
is readable up to its last complete record.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from companion.spec import CameraSpec

FORMAT = "swarmnav-recording"
VERSION = 1


class RecordingError(ValueError):
    """A file that is not a readable flight recording."""


def record_dtype(camera: CameraSpec) -> np.dtype:
    """The binary layout of one record for ``camera``."""
    return np.dtype([
        ("t_wall_s", "<f8"), ("t_mono_s", "<f8"), ("step", "<u4"), ("frame_seq", "<u4"), ("hold", "u1"),
        ("depth_m", "<f4", (camera.height, camera.width)), ("state", "<f4", (6,)), ("action", "<f4", (3,)),
        ("pos_ned_m", "<f4", (3,)), ("yaw_rad", "<f4"),
    ])


class FlightRecorder:
    """Appends one record per control step to a recording file."""

    def __init__(self, path: str | Path, camera: CameraSpec, control_period_s: float, policy_path: str) -> None:
        self.path = Path(path)
        self.dtype = record_dtype(camera)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")  # noqa: SIM115 - kept open for the flight
        header = {
            "format": FORMAT, "version": VERSION, "camera": camera.to_dict(),
            "control_period_s": control_period_s, "policy": policy_path,
            "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "record_dtype": [list(f) if len(f) == 2 else [f[0], f[1], list(f[2])] for f in self.dtype.descr],
        }
        self._file.write((json.dumps(header) + "\n").encode())
        self._record = np.zeros((), dtype=self.dtype)
        self.records = 0

    def write(self, *, t_wall_s: float, t_mono_s: float, step: int, frame_seq: int, hold: bool,
              depth_m: np.ndarray, state: np.ndarray, action: np.ndarray, pos_ned_m: np.ndarray,
              yaw_rad: float) -> None:
        """Append one control step."""
        r = self._record
        r["t_wall_s"], r["t_mono_s"], r["step"], r["frame_seq"], r["hold"] = t_wall_s, t_mono_s, step, frame_seq, hold
        r["depth_m"], r["state"], r["action"], r["pos_ned_m"], r["yaw_rad"] = depth_m, state, action, pos_ned_m, yaw_rad
        self._file.write(r.tobytes())
        self.records += 1
        if self.records % 10 == 0:
            self._file.flush()  # at most a second of flight lost on a crash

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()


def read_recording(path: str | Path) -> tuple[dict, np.ndarray]:
    """Return ``(header, records)`` of a recording; a truncated last record is dropped."""
    data = Path(path).read_bytes()
    end = data.find(b"\n")
    if end < 0:
        raise RecordingError(f"{path}: no header line (not a swarmnav recording)")
    try:
        header = json.loads(data[:end])
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise RecordingError(f"{path}: the header is not JSON (not a swarmnav recording)") from err
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise RecordingError(f"{path}: not a swarmnav recording")
    if header.get("version") != VERSION:
        raise RecordingError(f"{path}: recording version {header.get('version')} is not supported (reads {VERSION})")
    try:
        camera = CameraSpec(**header["camera"])
    except (KeyError, TypeError, ValueError) as err:
        raise RecordingError(f"{path}: invalid camera in the header ({err})") from err
    dtype = record_dtype(camera)
    body = data[end + 1:]
    count = len(body) // dtype.itemsize
    records = np.frombuffer(body[: count * dtype.itemsize], dtype=dtype)
    return header, records
