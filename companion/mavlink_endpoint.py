"""The companion's MAVLink endpoint: the transport under :class:`companion.mavlink_link.AutopilotLink`.

Two things here replace pymavlink behaviour that let one packet from anyone ground the vehicle
(issue 16):

* :class:`VerifyFirstMAVLink` — the MAVLink 2 parser with a signature check that verifies the
  signature *before* it records the stream's timestamp, and bounds the stream table.
  pymavlink 2.4.50's ``MAVLink.check_signature`` does it the other way round: it stores the
  (link id, system, component) stream's timestamp first and verifies afterwards, so one packet
  signed with a *wrong* key and a timestamp near 2^48 makes every later genuine packet of that
  stream "old" and refused, for good; and every wrong-key packet from a new id adds a table entry.
* :class:`UdpEndpoint` — UDP (``udpin``/``udpout``) without pymavlink's ``mavudp``. It reads
  datagrams itself and parses each one with fresh parser state (a datagram carries whole frames;
  pymavlink keeps a partial header across datagrams, so a 2-byte datagram ``fd ff`` swallows the
  next real frame). It binds its port exclusively (no ``SO_REUSEADDR``: nobody else can read the
  autopilot's traffic or share the port), talks only to the autopilot it locked onto (pymavlink's
  udpin replies to every address that ever sent a byte), and drops datagrams from anyone else
  before parsing them.

TCP and serial links are byte streams: they keep pymavlink's stream parser (``mavutil``), with
:class:`VerifyFirstMAVLink` swapped in for the signature check.
"""

from __future__ import annotations

import hashlib
import hmac
import math
import os
import socket
import time

os.environ["MAVLINK20"] = "1"  # before pymavlink picks its wire protocol: always MAVLink 2

from pymavlink import mavutil  # noqa: E402

mavutil.set_dialect("common")
mavlink = mavutil.mavlink

#: At most this many signed (link id, system, component) streams are remembered. Only holders of
#: the key can create one (the signature is checked first), and a vehicle's onboard link carries a
#: handful (autopilot, routed ground stations); the cap only bounds memory if a key leaks. When
#: full, packets of *new* streams are refused (fail closed: the streams already known, the
#: autopilot's first among them, keep working and replays of them stay impossible).
MAX_SIGNING_STREAMS = 64

#: MAVLink 2 signing's acceptance window for a new stream: 1 minute in 10 µs units (the spec's and
#: pymavlink's value: a new stream may start at most this far behind our own timestamp).
NEW_STREAM_WINDOW_10US = 6000 * 1000

#: Datagrams read per :meth:`UdpEndpoint.recv_msg` call at most, so a flood of foreign datagrams
#: cannot keep the control loop inside one read (the rest waits for the next pass).
MAX_DATAGRAMS_PER_READ = 1000

_MAX_DATAGRAM_BYTES = 65535
_SIGNATURE_LEN = 6  # the truncated SHA-256 at the end of a signed frame
_SIGNED_TAIL_LEN = 13  # link id (1) + timestamp (6) + signature (6)
_MAVLINK_EPOCH_UNIX_S = 1420070400  # 2015-01-01, where signing timestamps start


class VerifyFirstMAVLink(mavlink.MAVLink):
    """pymavlink's MAVLink 2 codec with a signature check that verifies before it stores.

    Upstream ``check_signature`` (pymavlink 2.4.50) updates ``signing.stream_timestamps`` before
    comparing signatures; here nothing about a packet is remembered unless its signature is valid.
    """

    def check_signature(self, msgbuf: bytearray, srcSystem: int, srcComponent: int) -> bool:  # noqa: N803
        """True if ``msgbuf`` is signed with our key and is newer than its stream's last packet."""
        signing = self.signing
        digest = hashlib.sha256(signing.secret_key + bytes(msgbuf[:-_SIGNATURE_LEN])).digest()
        if not hmac.compare_digest(digest[:_SIGNATURE_LEN], bytes(msgbuf[-_SIGNATURE_LEN:])):
            return False  # wrong key or corrupted: it must change nothing
        link_id = msgbuf[-_SIGNED_TAIL_LEN]
        tlow, thigh = self.mav_sign_unpacker.unpack(msgbuf[-12:-6])
        timestamp = tlow + (thigh << 32)
        stream = (link_id, srcSystem, srcComponent)
        last = signing.stream_timestamps.get(stream)
        if last is not None:
            if timestamp <= last:
                return False  # a replay (or a duplicate)
        else:
            if timestamp + NEW_STREAM_WINDOW_10US < signing.timestamp:
                return False  # a new stream from the past: a replay of a captured one
            if len(signing.stream_timestamps) >= MAX_SIGNING_STREAMS:
                return False
        signing.stream_timestamps[stream] = timestamp
        signing.timestamp = max(signing.timestamp, timestamp)
        return True


def new_parser(file, source_system: int, source_component: int) -> VerifyFirstMAVLink:
    """A robust-parsing MAVLink 2 codec writing to ``file`` (anything with ``write(bytes)``)."""
    mav = VerifyFirstMAVLink(file, srcSystem=source_system, srcComponent=source_component)
    mav.robust_parsing = True  # bad bytes become BAD_DATA messages instead of exceptions
    return mav


def setup_signing(mav: mavlink.MAVLink, key: bytes, allow_unsigned_callback, link_id: int = 0) -> None:
    """Sign what ``mav`` sends with ``key`` and check what it receives (as ``mavfile.setup_signing``).

    Our own timestamp starts at the wall clock (10 µs units since 2015-01-01, the MAVLink epoch).
    """
    mav.signing.secret_key = key
    mav.signing.sign_outgoing = True
    mav.signing.allow_unsigned_callback = allow_unsigned_callback
    mav.signing.link_id = link_id
    mav.signing.timestamp = int(max(time.time() - _MAVLINK_EPOCH_UNIX_S, 0) * 100_000)


def _reset_parser(mav: mavlink.MAVLink) -> None:
    """Forget any partial frame: the next bytes are parsed as the start of a new datagram."""
    mav.buf = bytearray()
    mav.buf_index = 0
    mav.expected_length = mavlink.HEADER_LEN_V1 + 2  # what pymavlink's constructor starts with
    mav.have_prefix_error = False


def parse_datagram(mav: mavlink.MAVLink, data: bytes) -> tuple[list, bool]:
    """Every message in one UDP datagram, parsed by ``mav`` from a fresh state (BAD_DATA included).

    A datagram carries whole frames: a frame cut off at its end is dropped, never completed by
    the next datagram (from whoever sends it). Returns (messages, ok); ok is False when the
    datagram broke the parser (the messages before the break are kept).
    """
    _reset_parser(mav)
    out: list = []
    ok = True
    try:
        msg = mav.parse_char(data)
        while msg is not None:
            out.append(msg)
            msg = mav.parse_char(b"")
    except Exception:  # noqa: BLE001 - a hostile datagram must never take the link down
        ok = False
    _reset_parser(mav)
    return out, ok


class UdpEndpoint:
    """A MAVLink 2 UDP endpoint that parses datagram by datagram and talks to one peer.

    Args:
        scheme: ``udpin`` (bind ``host:port`` and wait for the autopilot to send first: PX4's
            onboard link) or ``udpout`` (send to ``host:port`` from an ephemeral port).
        host, port: the address to bind (udpin) or to send to (udpout).
        source_system, source_component: our ids in outgoing frames.

    Raises:
        OSError: the port cannot be bound (``EADDRINUSE`` when another process holds it).

    Until :meth:`lock` names the autopilot's address, a ``udpin`` endpoint sends nothing and a
    ``udpout`` one sends only to its fixed address. After it, datagrams from any other address
    are dropped unparsed (counted in :attr:`dropped_foreign`), and nothing they carry can change
    where we send.
    """

    def __init__(self, scheme: str, host: str, port: int, source_system: int, source_component: int) -> None:
        if scheme not in ("udpin", "udpout"):
            raise ValueError(f"UdpEndpoint handles udpin/udpout, not {scheme}")
        self.scheme = scheme
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            # No SO_REUSEADDR / SO_REUSEPORT on purpose: the port is ours alone.
            if scheme == "udpin":
                self.sock.bind((host, port))
                self.peer: tuple[str, int] | None = None
            else:
                self.sock.bind(("0.0.0.0", 0))
                self.peer = (socket.gethostbyname(host), port)
            self.sock.setblocking(False)
        except OSError:
            self.sock.close()
            raise
        self.fd = self.sock.fileno()
        self.mav = new_parser(self, source_system, source_component)
        self.locked_address: tuple[str, int] | None = None
        #: After this long without a datagram from the locked address, datagrams from other addresses
        #: are parsed again (tagged ``_relock_candidate``) so the link can follow an autopilot or router
        #: that restarted on a new source port; None: never (the lock is for life).
        self.relock_after_s: float | None = None
        self.last_locked_rx_s = -math.inf  # monotonic time of the last datagram from the locked address
        self.dropped_foreign = 0  # datagrams from addresses other than the locked autopilot
        self.bad_datagrams = 0  # datagrams the parser could not take apart at all
        self._ready: list = []  # messages of the last datagram not yet handed out

    def lock(self, address: tuple[str, int]) -> None:
        """Talk to the autopilot at ``address`` only (until it falls silent and re-locks, see ``relock_after_s``)."""
        self.locked_address = address
        self.last_locked_rx_s = time.monotonic()
        if self.scheme == "udpin":
            self.peer = address

    def write(self, buf: bytes) -> None:
        """Send one frame to the peer (called by the codec for every packed message)."""
        if self.peer is None:
            return  # udpin before the lock: nobody to talk to yet
        try:
            self.sock.sendto(buf, self.peer)
        except OSError:
            pass  # nobody listening (ICMP port unreachable) or a full buffer: UDP may drop

    def recv_msg(self):
        """The next message (with ``_source_addr`` set to the sender), or None when nothing waits."""
        if self._ready:
            return self._ready.pop(0)
        for _ in range(MAX_DATAGRAMS_PER_READ):
            try:
                data, address = self.sock.recvfrom(_MAX_DATAGRAM_BYTES)
            except (BlockingIOError, InterruptedError):
                return None
            except ConnectionRefusedError:
                continue  # an earlier send hit a closed port: not about this read
            candidate = False
            if self.locked_address is not None:
                now_s = time.monotonic()
                if address == self.locked_address:
                    self.last_locked_rx_s = now_s
                elif self.relock_after_s is not None and now_s - self.last_locked_rx_s > self.relock_after_s:
                    candidate = True  # the autopilot has been silent: it may be talking from a new port
                else:
                    self.dropped_foreign += 1
                    continue
            messages = self.parse_datagram(data)
            for msg in messages:
                msg._source_addr = address
                msg._relock_candidate = candidate
            if messages:
                self._ready = messages
                return self._ready.pop(0)
        return None

    def parse_datagram(self, data: bytes) -> list:
        """Every message in one datagram, parsed from a fresh state (BAD_DATA included)."""
        out, ok = parse_datagram(self.mav, data)
        if not ok:
            self.bad_datagrams += 1
        return out

    def close(self) -> None:
        self.sock.close()
