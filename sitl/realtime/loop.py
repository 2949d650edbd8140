"""The one real-time loop of ``python -m sitl.vehicle`` and ``python -m sitl.world``.

Both processes wait for MAVLink on their sockets, do their periodic work, render every
vehicle's depth camera on a fixed time grid and log a status line a second, until a signal
(SIGTERM, SIGINT) or ``--duration`` stops them. What differs is behind :class:`RealtimeProcess`.
"""

from __future__ import annotations

import math
import select
import signal
import sys
import time
from typing import Protocol

from sitl.realtime.event_log import EventLog

STATUS_PERIOD_S = 1.0
MAX_WAIT_S = 0.1  # the longest select() wait: links and heartbeats are serviced at least at 10 Hz


class RealtimeProcess(Protocol):
    """What :func:`run` drives."""

    log: EventLog
    skipped_frames: int  # camera frames skipped because the loop fell behind

    def fds(self) -> dict[int, object]:
        """The sockets to wait on: file descriptor -> the link :meth:`receive` gets."""

    def receive(self, link: object, now_s: float) -> None:
        """Read and act on everything waiting on ``link``."""

    def wake_s(self) -> float:
        """The monotonic time the process next needs :meth:`tick` (``math.inf``: only for messages)."""

    def tick(self, now_s: float) -> None:
        """The work of every pass: physics, telemetry, link upkeep."""

    def render_and_send(self, now_s: float) -> None:
        """Render every vehicle's camera and send the frames."""

    def status(self, now_s: float) -> None:
        """Log a status line per vehicle."""

    def warm_up(self) -> None:
        """Load (or compile) the camera kernel before the process announces it is ready."""

    def close(self) -> None:
        """Close every socket and file."""


def run(process: RealtimeProcess, duration_s: float | None, camera_hz: float) -> None:
    """Until a signal or ``duration_s``: receive, :meth:`~RealtimeProcess.tick`, render at ``camera_hz``, status at 1 Hz."""
    stop: list[str] = []
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda signum, _frame: stop.append(signal.Signals(signum).name))
    started = now = time.monotonic()
    next_camera, next_status = now, now + STATUS_PERIOD_S
    camera_period = 1.0 / camera_hz
    while not stop:
        if duration_s is not None and now - started >= duration_s:
            stop.append("duration")
            break
        fds = process.fds()
        wake = min(next_camera, next_status, process.wake_s())
        timeout = min(max(0.0, wake - time.monotonic()), MAX_WAIT_S)
        readable: list[int] = []
        if fds:
            try:
                readable, _, _ = select.select(list(fds), [], [], timeout)
            except InterruptedError:
                pass
        else:
            time.sleep(timeout)
        now = time.monotonic()
        for fd in readable:
            process.receive(fds[fd], now)
        process.tick(now)
        if now >= next_camera:
            process.render_and_send(now)
            next_camera += camera_period
            if next_camera <= now:  # fell behind: skip frames but keep the camera's time grid
                skipped = math.ceil((now - next_camera) / camera_period + 1e-9)
                next_camera += skipped * camera_period
                process.skipped_frames += skipped
        if now >= next_status:
            process.status(now)
            next_status += STATUS_PERIOD_S
    process.status(time.monotonic())
    process.log("stopped", reason=stop[0] if stop else "?")


def serve(process: RealtimeProcess, duration_s: float | None, camera_hz: float, ready: dict, banner: str) -> int:
    """A process's life after parsing: warm up, log ``ready`` with ``ready``'s fields, print
    ``banner`` to stderr, :func:`run`; then close the process and its log whatever happens."""
    try:
        process.warm_up()
        process.log("ready", **ready)
        print(banner, file=sys.stderr, flush=True)
        run(process, duration_s, camera_hz)
    finally:
        process.close()
        process.log.close()
    return 0
