"""The simulator side's one MAVLink 2 UDP endpoint.

Every MAVLink UDP socket of the real-time processes is a :class:`MavlinkUdpEndpoint`:

* a simulated autopilot's link (:mod:`sitl.realtime.vehicle`): bound to an ephemeral local
  port, it sends to the fixed port where its companion or ground station listens (as PX4
  SITL does) and takes the replies on its own port;
* the depth bridge's ground-station port (:mod:`sitl.realtime.depth_bridge`, ``--px4``) and
  the MAVLink evaluation's ground station (:mod:`sitl.realtime.mavlink_swarm`): bound to a
  known port where many autopilots send, each answered at the address it talks from.

Datagrams are parsed one by one from a fresh parser state
(:func:`companion.mavlink_endpoint.parse_datagram`), so frames from different senders never
mix, with the companion's verify-first signature check. Unlike the companion's own endpoint
(:class:`companion.mavlink_endpoint.UdpEndpoint`), it is not locked to one peer: a
simulated autopilot and a ground station hear everyone, as the real ones do.
"""

from __future__ import annotations

import socket

from companion.mavlink_endpoint import mavlink, new_parser, parse_datagram, setup_signing

Address = tuple[str, int]

PX4_ONBOARD_BASE_PORT = 14540  # PX4 SITL instance i's onboard (companion) link: UDP 14540 + i
GCS_PORT = 14550  # where autopilots send their ground-station link (QGroundControl's port)
MAX_DATAGRAMS_PER_READ = 5000  # a flood cannot keep the real-time loop inside one read


class _Peer:
    """pymavlink's output ``file`` for one address: each packed message is one datagram there."""

    def __init__(self, endpoint: MavlinkUdpEndpoint, address: Address) -> None:
        self.endpoint, self.address = endpoint, address

    def write(self, buf: bytes) -> None:
        self.endpoint.send_datagram(buf, self.address)


class SignedCodecs:
    """What both simulated-autopilot links (UDP here, TCP in :mod:`sitl.realtime.tcp_endpoint`) share:
    codecs with our ids that, given a key, sign what they send and refuse (and count) unsigned input.

    The class using it sets ``src_system``, ``src_component``, ``signing_key``, ``link_id`` and
    ``refused_unsigned``.
    """

    def _codec(self, file) -> mavlink.MAVLink:
        mav = new_parser(file, self.src_system, self.src_component)
        if self.signing_key is not None:
            setup_signing(mav, self.signing_key, self._refuse_unsigned, self.link_id)
        return mav

    def _refuse_unsigned(self, _mav, _msg_id: int) -> bool:
        self.refused_unsigned += 1
        return False


class MavlinkUdpEndpoint(SignedCodecs):
    """One MAVLink 2 UDP socket: sends to a fixed remote and/or answers systems where they talk from.

    Args:
        name: what the link is, for the logs (``onboard``, ``gcs``).
        bind: the local address; port 0 picks an ephemeral one.
        src_system, src_component: our ids in every frame we send.
        remote: where :attr:`mav` sends (an autopilot's companion or ground station), or None:
            use :meth:`encoder_for` to answer a system at the address it was last heard from.
        signing_key: MAVLink 2 signing: sign everything sent, refuse unsigned messages.
        link_id: the signing link id of what we send.

    Raises:
        OSError: ``bind`` cannot be bound (the socket is closed again).
    """

    def __init__(self, name: str, bind: Address, src_system: int, src_component: int,
                 remote: Address | None = None, signing_key: bytes | None = None, link_id: int = 0) -> None:
        self.name, self.remote = name, remote
        self.src_system, self.src_component = src_system, src_component
        self.signing_key, self.link_id = signing_key, link_id
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.bind(bind)
        except OSError:
            self.sock.close()
            raise
        self.sock.setblocking(False)
        self.silenced = False  # failure injection: the link is dead both ways
        self.refused_unsigned = 0
        self.sent = 0
        self.address_of: dict[int, Address] = {}  # system id -> where it last talked from
        self._encoders: dict[int, tuple[Address, mavlink.MAVLink]] = {}
        self.mav = self._codec(self)  # sends to ``remote``; parses every datagram received

    @classmethod
    def autopilot_link(cls, name: str, remote: Address, sysid: int, signing_key: bytes | None = None,
                       link_id: int = 0) -> MavlinkUdpEndpoint:
        """A simulated autopilot's link, as PX4 SITL's: from an ephemeral loopback port to ``remote``."""
        return cls(name, ("127.0.0.1", 0), sysid, mavlink.MAV_COMP_ID_AUTOPILOT1, remote=remote,
                   signing_key=signing_key, link_id=link_id)


    def fileno(self) -> int:
        return self.sock.fileno()

    # ------------------------------------------------------------------ sending
    def send_datagram(self, buf: bytes, address: Address) -> None:
        """Send one packed message to ``address`` (dropped while the link is silenced)."""
        if self.silenced:
            return
        try:
            self.sock.sendto(buf, address)
            self.sent += 1
        except OSError:
            pass  # nobody listening (ICMP port unreachable) or a vanished peer: as UDP on a real autopilot

    def write(self, buf: bytes) -> None:
        """pymavlink's ``file`` interface of :attr:`mav`: send to the fixed remote."""
        if self.remote is not None:
            self.send_datagram(buf, self.remote)

    def forward(self, raw: bytes) -> None:
        """Send a message received on another link unchanged (signature included)."""
        self.write(bytes(raw))

    def encoder_for(self, sysid: int) -> mavlink.MAVLink | None:
        """An encoder whose messages go to where system ``sysid`` last talked from (None: not heard yet)."""
        address = self.address_of.get(sysid)
        if address is None:
            return None
        known = self._encoders.get(sysid)
        if known is None or known[0] != address:  # new, or the system restarted on another port
            known = self._encoders[sysid] = (address, self._codec(_Peer(self, address)))
        return known[1]

    # ------------------------------------------------------------------ receiving
    def receive(self) -> list:
        """Every message waiting on the socket; BAD_DATA, refused and silenced messages dropped."""
        out: list = []
        for _ in range(MAX_DATAGRAMS_PER_READ):
            try:
                data, address = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                continue  # an ICMP error for something we sent to a vanished peer
            if self.silenced:
                continue
            msgs, _ok = parse_datagram(self.mav, data)
            for msg in msgs:
                if msg.get_type() == "BAD_DATA":
                    continue
                self.address_of[msg.get_srcSystem()] = address
                out.append(msg)
        return out

    def close(self) -> None:
        self.sock.close()
