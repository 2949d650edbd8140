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
state           float32 [S]        the policy's state input (``policy.json``'s ``state_names``: 6, more
                                   with remembered depth; the header's ``state_dim``, absent: 6)
action          float32 [3]        the command sent (``vel_fwd_m_s, vel_down_m_s, yaw_rate_rad_s``)
pos_ned_m       float32 [3]        position from odometry
yaw_rad         float32            heading from odometry
==============  =================  =====================================================

Records are appended as the flight goes, so a recording cut short by a crash or power loss
is readable up to its last complete record.

A recording rotates into parts: once a file holds ``max_bytes`` it is renamed ``PATH.1``
(older parts move to ``PATH.2`` ... ``PATH.<keep>``, the oldest is deleted) and a new ``PATH``
starts with its own header (``part`` counts from 0), so every part is a complete recording
that :func:`read_recording` and ``--camera replay:`` read on their own (``--record-max-mb``,
``--record-keep``; defaults :data:`DEFAULT_RECORD_MAX_MB`, :data:`DEFAULT_RECORD_KEEP`).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from companion.flightlog import rotate_files
from companion.spec import STATE_DIM, CameraSpec

FORMAT = "swarmnav-recording"
VERSION = 1
#: Recording size cap: ~143 MB per flight hour at 10 Hz (32x32 frames), so a part holds ~1.8 h
#: and the whole recording (current + kept parts) at most ~1 GB.
DEFAULT_RECORD_MAX_MB = 256.0
DEFAULT_RECORD_KEEP = 3


class RecordingError(ValueError):
    """A file that is not a readable flight recording."""


#: Largest state a recording may declare (the paper's 6 plus remembered depth's sectors, with room).
MAX_RECORDED_STATE_DIM = 256


def record_dtype(camera: CameraSpec, state_dim: int = STATE_DIM) -> np.dtype:
    """The binary layout of one record for ``camera`` and a state of ``state_dim`` entries."""
    return np.dtype([
        ("t_wall_s", "<f8"), ("t_mono_s", "<f8"), ("step", "<u4"), ("frame_seq", "<u4"), ("hold", "u1"),
        ("depth_m", "<f4", (camera.height, camera.width)), ("state", "<f4", (state_dim,)), ("action", "<f4", (3,)),
        ("pos_ned_m", "<f4", (3,)), ("yaw_rad", "<f4"),
    ])


class FlightRecorder:
    """Appends one record per control step to a recording file."""

    def __init__(self, path: str | Path, camera: CameraSpec, control_period_s: float, policy_path: str,
                 max_bytes: int | None = None, keep: int = DEFAULT_RECORD_KEEP, state_dim: int = STATE_DIM) -> None:
        self.path = Path(path)
        self.state_dim = state_dim
        self.dtype = record_dtype(camera, state_dim)
        self.camera, self.control_period_s, self.policy_path = camera, control_period_s, policy_path
        self.max_bytes, self.keep = max_bytes, keep
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.part = 0
        self._open_part()
        self._record = np.zeros((), dtype=self.dtype)
        self.records = 0

    def _open_part(self) -> None:
        self._file = open(self.path, "wb")  # noqa: SIM115 - kept open for the flight
        header = {
            "format": FORMAT, "version": VERSION, "camera": self.camera.to_dict(),
            "control_period_s": self.control_period_s, "policy": self.policy_path, "part": self.part,
            "state_dim": self.state_dim,
            "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "record_dtype": [list(f) if len(f) == 2 else [f[0], f[1], list(f[2])] for f in self.dtype.descr],
        }
        self._file.write((json.dumps(header) + "\n").encode())
        self._size = self._file.tell()

    def write(self, *, t_wall_s: float, t_mono_s: float, step: int, frame_seq: int, hold: bool,
              depth_m: np.ndarray, state: np.ndarray, action: np.ndarray, pos_ned_m: np.ndarray,
              yaw_rad: float) -> None:
        """Append one control step."""
        r = self._record
        r["t_wall_s"], r["t_mono_s"], r["step"], r["frame_seq"], r["hold"] = t_wall_s, t_mono_s, step, frame_seq, hold
        r["depth_m"], r["state"], r["action"], r["pos_ned_m"], r["yaw_rad"] = depth_m, state, action, pos_ned_m, yaw_rad
        self._file.write(r.tobytes())
        self._size += self.dtype.itemsize
        self.records += 1
        if self.max_bytes is not None and self._size >= self.max_bytes:
            self._file.close()
            rotate_files(self.path, self.keep)
            self.part += 1
            self._open_part()
        elif self.records % 10 == 0:
            self._file.flush()  # at most a second of flight lost on a crash

    def close(self) -> None:
        if not self._file.closed:
            try:
                self._file.close()
            except OSError:
                pass  # the last records could not be flushed (disk full): what is on disk stays readable


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
    state_dim = header.get("state_dim", STATE_DIM)  # recordings written before it existed: the paper's 6
    if not (isinstance(state_dim, int) and not isinstance(state_dim, bool)
            and STATE_DIM <= state_dim <= MAX_RECORDED_STATE_DIM):
        raise RecordingError(f"{path}: state_dim must be an integer in {STATE_DIM}..{MAX_RECORDED_STATE_DIM}, "
                             f"header says {state_dim!r:.40}")
    dtype = record_dtype(camera, state_dim)
    body = data[end + 1:]
    count = len(body) // dtype.itemsize
    records = np.frombuffer(body[: count * dtype.itemsize], dtype=dtype)
    return header, records
