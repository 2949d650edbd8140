"""JSON-lines event log of the simulator processes (``sitl.vehicle``, ``sitl.world``).

Tests and users read these files to learn what a real-time process did (modes, crashes,
overruns, status lines), so every record is one self-contained JSON object with the UNIX
time ``t`` and the ``event`` name.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import TextIO

import numpy as np


class EventLog:
    """JSON lines with the UNIX time of each event; ``log("overrun", behind_s=0.2)``."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream

    @classmethod
    def open(cls, path: str) -> EventLog:
        """``-`` logs to stdout; anything else is a file appended to, line-buffered."""
        return cls(sys.stdout if path == "-" else open(Path(path), "a", buffering=1))  # noqa: SIM115

    def __call__(self, event: str, **fields) -> None:
        record = {"t": round(time.time(), 4), "event": event, **fields}
        try:
            self.stream.write(json.dumps(record, default=_json_default) + "\n")
            self.stream.flush()
        except (OSError, ValueError):  # a full disk or closed pipe must not stop the simulation
            pass

    def close(self) -> None:
        if self.stream is not sys.stdout:
            self.stream.close()


def _json_default(value):
    if isinstance(value, np.ndarray):
        return value.round(3).tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return str(value)
