"""systemd's notify protocol (``Type=notify``), without a dependency.

systemd passes ``NOTIFY_SOCKET`` (a unix datagram socket, possibly abstract: ``@name``)
and, with ``WatchdogSec=``, ``WATCHDOG_USEC``. The companion sends ``READY=1`` once model,
camera and link are up, ``WATCHDOG=1`` from the control loop (so a stalled loop gets the
service restarted) and ``STATUS=`` lines with the flight phase. Outside systemd every call
does nothing.
"""

from __future__ import annotations

import os
import socket


class SystemdNotifier:
    """Sends notify messages to systemd if it asked for them."""

    def __init__(self) -> None:
        address = os.environ.get("NOTIFY_SOCKET", "")
        self._address = "\0" + address[1:] if address.startswith("@") else address
        self._sock: socket.socket | None = None
        if self._address:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            self._sock.setblocking(False)
        usec = os.environ.get("WATCHDOG_USEC", "")
        watchdog_s = int(usec) / 1e6 if usec.isdigit() and int(usec) > 0 else None
        pid = os.environ.get("WATCHDOG_PID", "")
        if pid.isdigit() and int(pid) != os.getpid():
            watchdog_s = None  # the watchdog is meant for another process
        self.watchdog_s = watchdog_s
        # Feed well inside the period, but not on every tick (a sendto per tick is wasted).
        self._feed_every_s = watchdog_s / 4 if watchdog_s else 1.0
        self._last_feed_s = -1e9

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def notify(self, message: str) -> None:
        """Send one raw notify message (e.g. ``READY=1``)."""
        if self._sock is None:
            return
        try:
            self._sock.sendto(message.encode(), self._address)
        except OSError:
            pass  # systemd gone or the socket full: nothing the flight depends on

    def ready(self, status: str) -> None:
        self.notify(f"READY=1\nSTATUS={status}")

    def status(self, status: str) -> None:
        self.notify(f"STATUS={status}")

    def watchdog(self, now_s: float) -> None:
        """Feed the watchdog (rate-limited); call from the control loop."""
        if self._sock is not None and now_s - self._last_feed_s >= self._feed_every_s:
            self._last_feed_s = now_s
            self.notify("WATCHDOG=1")

    def stopping(self, status: str) -> None:
        self.notify(f"STOPPING=1\nSTATUS={status}")
