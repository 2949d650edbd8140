"""A simulated autopilot's MAVLink 2 link as a TCP server, like ArduPilot SITL's SERIAL ports.

ArduPilot SITL instance ``I`` listens on TCP ``5760 + 10*I`` (SERIAL0) and ``5762 + 10*I``
(SERIAL1, where a companion connects); the port exists only once the autopilot has booted,
and one client at a time is served (a new connection replaces the old one). This endpoint
does the same for ``python -m sitl.vehicle --transport tcp``, with the interface of
:class:`sitl.realtime.udp_endpoint.MavlinkUdpEndpoint` that :class:`SimAutopilot` uses
(``mav``, ``forward``, ``receive``, ``silenced``...). TCP is a byte stream: one pymavlink
stream parser per connection, with the companion's verify-first signature check.
"""

from __future__ import annotations

import errno
import select
import socket

from companion.mavlink_endpoint import mavlink
from sitl.realtime.udp_endpoint import SignedCodecs

#: ArduPilot SITL's ports: instance I's SERIAL0 is 5760 + 10*I, SERIAL1 (the companion's) 5762 + 10*I.
ARDUPILOT_SERIAL0_BASE_PORT = 5760
ARDUPILOT_SERIAL1_BASE_PORT = 5762
ARDUPILOT_INSTANCE_PORT_STEP = 10
_SEND_TIMEOUT_S = 0.05  # a client that stops reading must not stall the real-time loop for long
#: Reads per :meth:`MavlinkTcpServer.receive` call at most: a client streaming faster than we read
#: must not keep the real-time loop inside one receive.
_MAX_READS_PER_RECEIVE = 16


class MavlinkTcpServer(SignedCodecs):
    """One listening TCP port serving one MAVLink client at a time.

    Args:
        name: what the link is, for the logs (``onboard``).
        bind: the address to listen on.
        src_system, src_component: our ids in every frame we send.
        signing_key, link_id: MAVLink 2 signing as :class:`MavlinkUdpEndpoint`.

    Raises:
        OSError: the port cannot be bound (the socket is closed again).
    """

    def __init__(self, name: str, bind: tuple[str, int], src_system: int, src_component: int,
                 signing_key: bytes | None = None, link_id: int = 0) -> None:
        self.name = name
        self.src_system, self.src_component = src_system, src_component
        self.signing_key, self.link_id = signing_key, link_id
        self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # a restarted vehicle rebinds at once
            self.listener.bind(bind)
            self.listener.listen(1)
        except OSError:
            self.listener.close()
            raise
        self.listener.setblocking(False)
        self.client: socket.socket | None = None
        self.silenced = False  # failure injection: the link is dead both ways
        self.refused_unsigned = 0
        self.sent = 0
        self.connections = 0
        self.mav = self._codec(self)

    def fileno(self) -> int:
        return self.listener.fileno()

    def fds(self) -> list[int]:
        """The descriptors to wait on: the listener and the connected client, if any."""
        return [self.listener.fileno()] + ([self.client.fileno()] if self.client is not None else [])

    # ------------------------------------------------------------------ sending
    def write(self, buf: bytes) -> None:
        """pymavlink's ``file`` interface of :attr:`mav`: send to the connected client (if any)."""
        if self.client is None or self.silenced:
            return
        try:
            self.client.sendall(buf)
            self.sent += 1
        except OSError:
            self._drop_client()  # reset, or a client that stopped reading: wait for a new one

    def forward(self, raw: bytes) -> None:
        """Send a message received on another link unchanged (signature included)."""
        self.write(bytes(raw))

    # ------------------------------------------------------------------ receiving
    def _accept(self) -> None:
        while True:
            try:
                client, _address = self.listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            self._drop_client()
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            client.settimeout(_SEND_TIMEOUT_S)  # sendall blocks at most this long
            self.client = client
            self.connections += 1
            self.mav = self._codec(self)  # a new stream: no half frame from the last client

    def _drop_client(self) -> None:
        if self.client is not None:
            try:
                self.client.close()
            except OSError:
                pass
            self.client = None

    def receive(self) -> list:
        """Accept a waiting client, then every message it sent; BAD_DATA and silenced ones dropped."""
        self._accept()
        out: list = []
        if self.client is None:
            return out
        for _ in range(_MAX_READS_PER_RECEIVE):
            # The client socket has a timeout (for sendall), and CPython waits for readability up to
            # that timeout before any recv, MSG_DONTWAIT or not: a client sending every <= 50 ms
            # (the companion's 20 Hz exit hold) kept this loop reading for seconds. Poll first.
            if not select.select([self.client], [], [], 0.0)[0]:
                break
            try:
                data = self.client.recv(65536)
            except (BlockingIOError, InterruptedError, socket.timeout):
                break
            except OSError as err:
                if err.errno in (errno.EAGAIN, errno.EWOULDBLOCK):
                    break
                self._drop_client()
                break
            if not data:  # the client closed: everything it sent before is parsed above
                self._drop_client()
                break
            if self.silenced:
                continue
            try:
                msg = self.mav.parse_char(data)
                while msg is not None:
                    if msg.get_type() != "BAD_DATA":
                        out.append(msg)
                    msg = self.mav.parse_char(b"")
            except Exception:  # noqa: BLE001 - a hostile stream must not take the vehicle down
                self.mav = self._codec(self)
        return out

    def close(self) -> None:
        self._drop_client()
        self.listener.close()
