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
* ``summary`` — latency and deadline statistics, every 10 s and at exit.
"""

from __future__ import annotations

import json
import math
import sys
import time
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
