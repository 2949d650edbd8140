"""A training run's progress for a person: which stage, how far, the validation scores, the time left.

On a terminal it is a tqdm bar (its postfix carries the scores); anywhere else — CI logs,
Ray workers, output redirected to a file — tqdm's carriage-return redraws would be noise,
so it prints a plain line every ``every_s`` seconds instead, with the same content.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO


def format_duration(seconds: float) -> str:
    """``42 s``, ``12.5 min`` or ``2 h 05 min``."""
    if seconds != seconds or seconds == float("inf"):  # NaN or no rate yet
        return "?"
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.1f} min"
    hours, minutes = divmod(round(seconds / 60), 60)
    return f"{hours} h {minutes:02d} min"


class Progress:
    """Progress of one stage of a run towards ``total`` ``unit``\\ s (updates or episodes).

    Args:
        total: the stage's end, in ``unit``.
        initial: what is already done (a resumed run).
        unit: ``update`` or ``episode``.
        desc: the stage's label, first on every line.
        stream: where it writes (stderr by default).
        every_s: seconds between two plain lines when ``stream`` is not a terminal.
        tty: force the bar (True) or plain lines (False); default: whether ``stream`` is a terminal.
    """

    def __init__(self, total: int, initial: int, unit: str, desc: str, stream: TextIO | None = None,
                 every_s: float = 60.0, tty: bool | None = None) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.total, self.done, self.unit, self.desc = total, initial, unit, desc
        self.every_s = every_s
        self.fields: dict[str, str] = {}
        self._start_done = initial
        self._t0 = self._last_line = time.perf_counter()
        isatty = getattr(self.stream, "isatty", None)
        self.tty = bool(isatty and isatty()) if tty is None else tty
        self.bar = None
        if self.tty:
            from tqdm import tqdm

            self.bar = tqdm(total=total, initial=initial, unit=unit, desc=desc, file=self.stream,
                            dynamic_ncols=True, mininterval=2.0)

    def update(self, n: int = 1) -> None:
        self.done += n
        if self.bar is not None:
            self.bar.update(n)

    def set_fields(self, **fields) -> None:
        """Scores and rates shown after the count (the bar's postfix, or the line's tail)."""
        self.fields.update({k: str(v) for k, v in fields.items()})
        if self.bar is not None:
            self.bar.set_postfix(self.fields, refresh=False)

    def write(self, message: str) -> None:
        """A message that must not be overdrawn by the bar (a validation result)."""
        if self.bar is not None:
            self.bar.write(message, file=self.stream)
        else:
            print(message, file=self.stream, flush=True)

    def elapsed_s(self) -> float:
        return time.perf_counter() - self._t0

    def eta_s(self, elapsed_s: float | None = None) -> float:
        """Seconds left at this session's rate (``elapsed_s`` for what is done so far; inf until something is)."""
        done = self.done - self._start_done
        elapsed_s = self.elapsed_s() if elapsed_s is None else elapsed_s
        return (self.total - self.done) * elapsed_s / done if done > 0 else float("inf")

    def line(self) -> str:
        share = 100.0 * self.done / self.total if self.total else 0.0
        tail = ", ".join(f"{k} {v}" for k, v in self.fields.items())
        return (f"{self.desc}: {self.done}/{self.total} {self.unit}s ({share:.0f} %), "
                f"{format_duration(self.elapsed_s())} elapsed, {format_duration(self.eta_s())} left"
                + (f"; {tail}" if tail else ""))

    def tick(self) -> None:
        """Print the plain line when it is due (no-op on a terminal: the bar redraws itself)."""
        if self.bar is None and time.perf_counter() - self._last_line >= self.every_s:
            self._last_line = time.perf_counter()
            print(self.line(), file=self.stream, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
        else:
            print(self.line(), file=self.stream, flush=True)
