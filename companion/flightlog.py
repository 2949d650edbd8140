"""Structured logs: one JSON object per line for every control step and every event.

Each line has ``t`` (UNIX time, s), ``mono`` (monotonic time, s) and ``kind``:

* ``step`` — one control step: ``step``, ``phase``, ``mode``, ``armed``, ``sent`` (a setpoint
  went out), ``hold`` (why a hold replaced the policy, or null), ``cmd`` (the command sent,
  ``[vel_fwd_m_s, vel_down_m_s, yaw_rate_rad_s]``), ``policy`` (raw policy output),
  ``clamped``, ``pos_ned``, ``goal_ned``, ``dist_m``, ``depth_age_ms``, ``odom_age_ms``,
  ``frame_seq``, ``frame_to_setpoint_ms``, ``inference_ms``, ``tick_late_ms``, ``period_ms``;
* ``event`` — ``event`` names what happened (``phase``, ``mode``, ``goal``, ``failsafe``,
  ``arrived``, ``link``, ``refused_unsigned``, ``autopilot_text``, ``exit``...) with details;
  every event is also printed to stderr as one readable line;
* ``summary`` — latency and deadline statistics, every 10 s (over those 10 s, ``"window":
  "10 s"``) and at exit (over the whole flight, ``"window": "flight"``, percentiles from a
  bounded histogram: within 1 % of the exact value).

The log file rotates: once it holds ``max_bytes`` it is renamed ``PATH.1`` (older ones move
to ``PATH.2`` ... ``PATH.<keep>``, the oldest is deleted) and a new ``PATH`` starts
(``--log-max-mb``, ``--log-keep``; defaults :data:`DEFAULT_LOG_MAX_MB`, :data:`DEFAULT_LOG_KEEP`).
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from pathlib import Path
from typing import IO

import numpy as np


def _jsonable(value):
    if isinstance(value, np.ndarray):
        return [_jsonable(v) for v in value.tolist()]
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.floating, float)):
        v = float(value)
        return round(v, 4) if math.isfinite(v) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


#: Step-log size cap: the log grows ~16 MB per flight hour at 10 Hz, so one file holds ~4 h and
#: the whole log (current + kept) at most ~320 MB of an onboard SD card.
DEFAULT_LOG_MAX_MB = 64.0
DEFAULT_LOG_KEEP = 4


def rotate_files(path: Path, keep: int) -> None:
    """Shift ``path`` -> ``path.1`` -> ... -> ``path.<keep>`` (the oldest is deleted)."""
    path = Path(path)
    if keep < 1:
        path.unlink(missing_ok=True)
        return
    Path(f"{path}.{keep}").unlink(missing_ok=True)
    for index in range(keep - 1, 0, -1):
        older = Path(f"{path}.{index}")
        if older.exists():
            os.replace(older, f"{path}.{index + 1}")
    if path.exists():
        os.replace(path, f"{path}.1")


class RotatingTextFile:
    """A text file opened for appending that rotates (:func:`rotate_files`) past ``max_bytes``.

    Whole lines are never split: the line that crosses the cap is the last one of its file.
    """

    def __init__(self, path: str | Path, max_bytes: int, keep: int = DEFAULT_LOG_KEEP) -> None:
        self.path, self.max_bytes, self.keep = Path(path), int(max_bytes), int(keep)
        self._file = open(self.path, "a", encoding="utf-8")  # noqa: SIM115 - kept open for the flight
        self._size = self._file.tell()
        self.rotations = 0

    def write(self, text: str) -> int:
        written = self._file.write(text)
        self._size += len(text.encode("utf-8")) if not text.isascii() else len(text)
        if self._size >= self.max_bytes and text.endswith("\n"):
            self._file.close()
            try:
                rotate_files(self.path, self.keep)
            except OSError:
                pass  # cannot rename (read-only, full): keep appending to the same file rather than go silent
            self._file = open(self.path, "a", encoding="utf-8")  # noqa: SIM115
            self._size = self._file.tell()
            self.rotations += 1
        return written

    def flush(self) -> None:
        self._file.flush()

    def close(self) -> None:
        self._file.close()


class RunningStats:
    """Statistics of a stream of durations (s) that cost O(window) to report, whatever the flight length.

    The samples since the last :meth:`window` call are kept exactly (bounded by
    ``max_window``); the whole flight lives in a log-spaced histogram (1 us .. 1000 s,
    ``bins_per_decade`` bins per decade: 1.2 % wide at the default) plus an exact max.
    """

    def __init__(self, max_window: int = 100_000, bins_per_decade: int = 200) -> None:
        self._window: list[float] = []
        self.max_window = max_window
        self._lo_exp, self._decades, self._per_decade = -6, 9, bins_per_decade
        self._counts = np.zeros(self._decades * bins_per_decade + 2, dtype=np.int64)  # + under/overflow
        self.n = 0
        self.max_s = -math.inf

    def append(self, value_s: float) -> None:
        if len(self._window) < self.max_window:
            self._window.append(value_s)
        self.n += 1
        if value_s > self.max_s:
            self.max_s = value_s
        if value_s <= 0 or not math.isfinite(value_s):
            index = 0 if not value_s > 0 else len(self._counts) - 1
        else:
            index = int((math.log10(value_s) - self._lo_exp) * self._per_decade) + 1
            index = min(max(index, 0), len(self._counts) - 1)
        self._counts[index] += 1

    def __len__(self) -> int:
        return self.n

    def window(self) -> dict:
        """Percentiles (ms) of the samples since the last call; starts a new window."""
        samples, self._window = self._window, []
        return percentiles_ms(samples)

    def total(self, qs=(50, 99)) -> dict:
        """Percentiles (ms) over every sample so far, from the histogram (bin centres)."""
        if self.n == 0:
            return percentiles_ms([], qs)
        cumulative = np.cumsum(self._counts)
        out = {}
        for q in qs:
            index = int(np.searchsorted(cumulative, q / 100.0 * self.n, side="left"))
            if index == 0:
                value_s = 0.0
            elif index >= len(self._counts) - 1:
                value_s = self.max_s
            else:
                value_s = min(10.0 ** (self._lo_exp + (index - 0.5) / self._per_decade), self.max_s)
            out[f"p{q}"] = round(value_s * 1000.0, 3)
        out["max"] = round(self.max_s * 1000.0, 3)
        out["n"] = self.n
        return out


class FlightLog:
    """Writes JSON lines to ``stream`` and readable event lines to ``human``."""

    def __init__(self, stream: IO[str] | None, human: IO[str] | None = sys.stderr) -> None:
        self.stream = stream
        self.human = human

    def _write(self, record: dict) -> None:
        if self.stream is None:
            return
        try:
            self.stream.write(json.dumps(record, separators=(",", ":")) + "\n")
            self.stream.flush()
        except (OSError, ValueError):
            pass  # a full disk must not stop the flight loop

    def step(self, **fields) -> None:
        self._write({"t": round(time.time(), 4), "mono": round(time.monotonic(), 4), "kind": "step",
                     **{k: _jsonable(v) for k, v in fields.items()}})

    def event(self, event: str, message: str, **fields) -> None:
        """Record an event and print ``companion: <message>`` to stderr."""
        self._write({"t": round(time.time(), 4), "mono": round(time.monotonic(), 4), "kind": "event",
                     "event": event, "message": message, **{k: _jsonable(v) for k, v in fields.items()}})
        if self.human is not None:
            try:
                print(f"companion: {message}", file=self.human, flush=True)
            except (OSError, ValueError):
                pass

    def summary(self, **fields) -> None:
        self._write({"t": round(time.time(), 4), "mono": round(time.monotonic(), 4), "kind": "summary",
                     **{k: _jsonable(v) for k, v in fields.items()}})

    def close(self) -> None:
        if self.stream not in (None, sys.stdout, sys.stderr):
            self.stream.close()


def percentiles_ms(samples_s, qs=(50, 99)) -> dict:
    """{"p50": ms, "p99": ms, "max": ms, "n": count} of samples in seconds (empty -> nulls)."""
    data = np.asarray(list(samples_s), dtype=np.float64)
    if data.size == 0:
        return {f"p{q}": None for q in qs} | {"max": None, "n": 0}
    out = {f"p{q}": round(float(np.percentile(data, q)) * 1000.0, 3) for q in qs}
    out["max"] = round(float(data.max()) * 1000.0, 3)
    out["n"] = int(data.size)
    return out


def resident_memory_mb() -> dict:
    """Current and peak resident set size of this process in MiB (Linux)."""
    current = peak = None
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    current = int(line.split()[1]) / 1024.0
                elif line.startswith("VmHWM:"):
                    peak = int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return {"rss_mb": None if current is None else round(current, 1), "peak_rss_mb": None if peak is None else round(peak, 1)}
