"""The control loop's clock: fixed-rate ticks, optionally phase-locked to the depth camera's frames.

Used by :class:`companion.runtime.Companion`; docs/companion.md "Control loop and timing" describes the lock.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np


class ControlClock:
    """Fixed-rate ticks at ``period_s`` with deadline accounting, optionally phase-locked to frames.

    Frames come from a camera clock at period P (a multiple of the control rate locks
    exactly); their arrival times scatter *late* of that grid (scheduling, transport). The
    lock estimates the grid's early edge and the spread of the lateness from the last 64
    arrivals, and steers the ticks to ``early edge + p95 lateness + guard``: late enough that
    ~95 % of frames are in before the tick, early enough that they wait only milliseconds.
    The target delay follows the lateness estimate with a ~1 s time constant. The next tick
    moves later by at most ``acquire_slew_s`` (a tick before its frame costs a frame period
    of latency) and earlier by at most ``track_slew_s`` near the target (``acquire_slew_s``
    far from it), so the lock itself adds little period jitter.
    """

    def __init__(self, period_s: float, start_s: float, lock: bool = True, guard_s: float = 0.0015,
                 min_margin_s: float = 0.003, acquire_slew_s: float = 0.002, track_slew_s: float = 0.0005,
                 gain: float = 0.5) -> None:
        self.period_s = period_s
        self.next_tick_s = start_s + period_s
        self.lock = lock
        self.guard_s, self.min_margin_s = guard_s, min_margin_s
        self.acquire_slew_s, self.track_slew_s, self.gain = acquire_slew_s, track_slew_s, gain
        self._arrivals: deque[float] = deque(maxlen=64)
        self.missed_ticks = 0
        self.margin_s = min_margin_s  # current target delay after the frame grid (for logs)
        self.locked = False

    def start(self, now_s: float) -> None:
        """(Re)start the ticks: the first is due one period after ``now_s``."""
        self.next_tick_s = now_s + self.period_s

    def frame_arrived(self, arrival_s: float) -> None:
        self._arrivals.append(arrival_s)

    def frame_period_s(self) -> float | None:
        if len(self._arrivals) < 8:
            return None
        return float(np.median(np.diff(np.asarray(self._arrivals))))

    def _phase_error_s(self, scheduled: float) -> float | None:
        """How far (s, wrapped to +-P/2) the scheduled tick is from where the lock wants it."""
        frame_period = self.frame_period_s()
        if not frame_period or not 1e-3 < frame_period <= 1.2 * self.period_s:
            return None
        arrivals = np.asarray(self._arrivals)
        newest = arrivals[-1]
        if scheduled - newest > 2.0 * frame_period:
            return None  # frames stopped: nothing to lock to
        phases = (arrivals - newest + frame_period / 2.0) % frame_period - frame_period / 2.0
        edge = float(np.percentile(phases, 5))  # the camera grid, before transport delays
        lateness = float(np.percentile(phases - edge, 95))
        target = float(np.clip(lateness + self.guard_s, self.min_margin_s, 0.4 * frame_period))
        self.margin_s += 0.1 * (target - self.margin_s)  # ~1 s to follow: one late frame must not jerk the ticks
        error = scheduled - (newest + edge + self.margin_s)
        return (error + frame_period / 2.0) % frame_period - frame_period / 2.0

    def advance(self, now_s: float) -> float:
        """Schedule the tick after the one due now; return the correction applied (s)."""
        scheduled = self.next_tick_s
        correction = 0.0
        error = self._phase_error_s(scheduled) if self.lock else None
        if error is not None:
            self.locked = abs(error) < 0.001
            # A tick early of its frame gets the previous one (a whole frame period old): move
            # later quickly. A tick late of its frame only waits a little longer: move earlier slowly.
            earlier = self.track_slew_s if abs(error) < 0.005 else self.acquire_slew_s
            correction = float(np.clip(-self.gain * error, -earlier, self.acquire_slew_s))
        following = scheduled + self.period_s + correction
        if following <= now_s:  # overran whole periods: skip them instead of bursting
            missed = math.floor((now_s - following) / self.period_s) + 1
            self.missed_ticks += missed
            following += missed * self.period_s
        self.next_tick_s = following
        return correction
