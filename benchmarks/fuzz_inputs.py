"""Hostile inputs for ``benchmarks/fuzz_companion.py``: MAVLink datagrams, depth datagrams, model metadata.

Every generator is driven by a seeded :class:`random.Random`, so a run can be repeated with
``--seed``. Each input is a :class:`Datagram`: the bytes, a ``kind`` (the name the report
counts it under) and who sends it: ``"autopilot"`` (from the autopilot's own address, the
hardest case: the companion cannot tell it from the autopilot by address) or ``"foreign"``
(from another loopback socket).

Depth frames the companion must never fly on (blinded, dead, stale, another vehicle's) carry
a ``seq`` in :data:`REFUSABLE_SEQ_BASE` .. +2^24, so the harness can tell from the companion's
step log (``frame_seq``) whether a step flew on one; other hostile-but-valid frames carry
:data:`TOLERABLE_SEQ_BASE` + n.
"""

from __future__ import annotations

import json
import math
import os
import random
import struct
import time
from dataclasses import dataclass

os.environ["MAVLINK20"] = "1"  # before pymavlink picks its wire protocol

from pymavlink import mavutil  # noqa: E402

from companion.depth_wire import HEADER, MAGIC, VERSION, encode_frame  # noqa: E402

mavutil.set_dialect("common")
mavlink = mavutil.mavlink

#: The simulated autopilot's ids (``sitl.vehicle --n 1``: system 1, component 1).
AUTOPILOT_IDS = (1, 1)
MAV_COMP_ID_ONBOARD_COMPUTER = 191
#: MAVLink 2 signing timestamps count 10 us since 2015-01-01 00:00 UTC.
SIGNING_EPOCH_S = 1420070400
#: The forged timestamp of issue 16 item 2: near the 48-bit maximum, so it outlives every real one.
SIGNING_TIMESTAMP_NEAR_MAX = 2 ** 48 - 100
REFUSABLE_SEQ_BASE = 0xFA000000
TOLERABLE_SEQ_BASE = 0xFB000000
_SEQ_SPAN = 1 << 24
_HOSTILE_FLOATS = (math.nan, math.inf, -math.inf, 3.4e38, -3.4e38, 1e20, -1e9)
_PX4_CUSTOM_MODES = (0x00030000, 0x00060000, 0x04040000, 0x03040000, 0x00010000, 0x00020000)  # POSCTL OFFB LOIT AUTO MAN ALT


@dataclass
class Datagram:
    """One hostile UDP datagram and where it comes from."""

    kind: str
    data: bytes
    sender: str = "foreign"  # "autopilot" (the autopilot's address) or "foreign"


def signing_timestamp_now() -> int:
    """The current MAVLink 2 signing timestamp (10 us units since 2015)."""
    return int((time.time() - SIGNING_EPOCH_S) * 1e5)


def _crc(header_tail: bytes, payload: bytes, crc_extra: int) -> int:
    crc = mavlink.x25crc(header_tail + payload)
    crc.accumulate(bytes([crc_extra & 0xFF]))
    return crc.crc


def raw_frame_v2(msgid: int, payload: bytes, sysid: int, compid: int, seq: int, *, crc_extra: int | None = None,
                 incompat: int = 0, tail: bytes = b"") -> bytes:
    """A MAVLink 2 frame with a correct CRC for ``crc_extra`` (the dialect's, unless given)."""
    if crc_extra is None:
        cls = mavlink.mavlink_map.get(msgid)
        crc_extra = cls.crc_extra if cls is not None else 0
    header = struct.pack("<BBBBBBBHB", 0xFD, len(payload), incompat, 0, seq & 0xFF, sysid & 0xFF, compid & 0xFF,
                         msgid & 0xFFFF, (msgid >> 16) & 0xFF)
    return header + payload + struct.pack("<H", _crc(header[1:], payload, crc_extra)) + tail


def raw_frame_v1(msgid: int, payload: bytes, sysid: int, compid: int, seq: int) -> bytes:
    """A MAVLink 1 frame with a correct CRC."""
    cls = mavlink.mavlink_map.get(msgid)
    header = struct.pack("<BBBBBB", 0xFE, len(payload), seq & 0xFF, sysid & 0xFF, compid & 0xFF, msgid & 0xFF)
    return header + payload + struct.pack("<H", _crc(header[1:], payload, cls.crc_extra if cls else 0))


def _payload_size(msgid: int) -> int:
    return mavlink.mavlink_map[msgid].unpacker.size


class _KindMix:
    """A weighted mix of input kinds (``kinds``: name, weight) that ``--kinds`` can narrow."""

    kinds: list[tuple[str, int]]
    rng: random.Random

    def _init_mix(self) -> None:
        self._names = [k for k, _ in self.kinds]
        self._weights = [w for _, w in self.kinds]

    def restrict(self, only: set[str] | None) -> bool:
        """Keep only the kinds in ``only`` (all with None); return whether any is left."""
        if only is not None:
            kept = [(k, w) for k, w in self.kinds if k in only]
            self._names, self._weights = [k for k, _ in kept], [w for _, w in kept]
        return bool(self._names)

    def pick(self) -> str:
        return self.rng.choices(self._names, self._weights)[0]


class MavlinkFuzzer(_KindMix):
    """Malformed and hostile MAVLink datagrams toward the companion.

    Args:
        rng: the seeded random source.
        captured: a callable returning raw datagrams captured from the vehicle (for bit flips).
    """

    def __init__(self, rng: random.Random, captured) -> None:
        self.rng = rng
        self.captured = captured
        self.seq = 0
        self.mav = mavlink.MAVLink(None, srcSystem=AUTOPILOT_IDS[0], srcComponent=AUTOPILOT_IDS[1])
        self.msg_ids = sorted(mavlink.mavlink_map)
        self.v1_ids = [i for i in self.msg_ids if i < 256]
        self.kinds = [
            ("random_bytes", 6), ("start_and_length", 6), ("truncated", 6), ("bit_flip", 6), ("bad_crc", 5),
            ("huge_length", 3), ("v1_random_payload", 6), ("v2_random_payload", 10), ("unknown_msgid", 2),
            ("fake_signature_flag", 3), ("heartbeat_foreign", 8), ("telemetry_hostile", 10), ("command_ack", 4),
            ("goal_out_of_range", 6), ("statustext_junk", 4), ("junk_then_frame", 3),
        ]
        self._init_mix()

    # ------------------------------------------------------------------ helpers
    def _next_seq(self) -> int:
        self.seq = (self.seq + 1) & 0xFF
        return self.seq

    def _pack(self, msg, sysid: int, compid: int, v1: bool = False) -> bytes:
        self.mav.srcSystem, self.mav.srcComponent = sysid, compid
        return msg.pack(self.mav, force_mavlink1=v1)

    def _foreign_ids(self) -> tuple[int, int]:
        return self.rng.randint(2, 254), self.rng.randint(0, 255)

    def _sender(self, p_autopilot: float = 0.5) -> str:
        return "autopilot" if self.rng.random() < p_autopilot else "foreign"

    def _valid_frame(self) -> bytes:
        """A real vehicle datagram if one was captured, else a foreign HEARTBEAT."""
        frames = self.captured()
        if frames and self.rng.random() < 0.7:
            return bytes(self.rng.choice(frames))
        return self._pack(self.mav.heartbeat_encode(2, 12, 0, 0, 3), *self._foreign_ids(), v1=self.rng.random() < 0.3)

    def _hostile(self) -> float:
        return self.rng.choice(_HOSTILE_FLOATS)

    def _maybe_hostile(self, normal: float, p: float = 0.5) -> float:
        return self._hostile() if self.rng.random() < p else normal

    # ------------------------------------------------------------------ the kinds
    def next(self) -> Datagram:
        kind = self.pick()
        return getattr(self, "_" + kind)(kind)

    def _random_bytes(self, kind: str) -> Datagram:
        return Datagram(kind, self.rng.randbytes(self.rng.randint(1, 300)), self._sender())

    def _start_and_length(self, kind: str) -> Datagram:
        """Issue 16 item 1: a bare start byte + length, before the real frames."""
        data = self.rng.choice([b"\xfd\xff", b"\xfe\xff", b"\xfd", b"\xfe",
                                bytes([self.rng.choice((0xFD, 0xFE)), self.rng.randint(0, 255)])])
        return Datagram(kind, data, self._sender(0.7))

    def _truncated(self, kind: str) -> Datagram:
        frame = self._valid_frame()
        return Datagram(kind, frame[: self.rng.randint(1, max(1, len(frame) - 1))], self._sender(0.7))

    def _bit_flip(self, kind: str) -> Datagram:
        data = bytearray(self._valid_frame())
        for _ in range(self.rng.randint(1, 4)):
            i = self.rng.randrange(len(data))
            data[i] ^= 1 << self.rng.randrange(8)
        return Datagram(kind, bytes(data), self._sender(0.7))

    def _bad_crc(self, kind: str) -> Datagram:
        msg = self.mav.heartbeat_encode(2, 12, 0, 0, 3)
        frame = bytearray(self._pack(msg, *self._foreign_ids(), v1=self.rng.random() < 0.3))
        frame[-1] ^= self.rng.randint(1, 255)
        return Datagram(kind, bytes(frame), self._sender(0.7))

    def _huge_length(self, kind: str) -> Datagram:
        choice = self.rng.randrange(3)
        if choice == 0:  # a v2 header claiming 255 bytes, followed by a few
            data = bytes([0xFD, 0xFF]) + self.rng.randbytes(self.rng.randint(8, 40))
        elif choice == 1:  # a datagram of start bytes
            data = bytes([self.rng.choice((0xFD, 0xFE))]) * self.rng.randint(256, 1400)
        else:  # a near-maximal datagram of junk
            data = self.rng.randbytes(self.rng.randint(8000, 65000))
        return Datagram(kind, data, self._sender(0.5))

    def _v1_random_payload(self, kind: str) -> Datagram:
        msgid = self.rng.choice(self.v1_ids)
        payload = self.rng.randbytes(_payload_size(msgid))
        sender = "foreign" if msgid == 0 else self._sender(0.3)  # HEARTBEAT only from foreign ids
        sysid, compid = AUTOPILOT_IDS if sender == "autopilot" else self._foreign_ids()
        return Datagram(kind, raw_frame_v1(msgid, payload, sysid, compid, self._next_seq()), sender)

    def _v2_random_payload(self, kind: str) -> Datagram:
        msgid = self.rng.choice(self.msg_ids)
        size = _payload_size(msgid)
        payload = self.rng.randbytes(self.rng.randint(1, size))  # v2 trims trailing zeros: shorter is legal
        sender = "foreign" if msgid == 0 else self._sender(0.3)
        sysid, compid = AUTOPILOT_IDS if sender == "autopilot" else self._foreign_ids()
        return Datagram(kind, raw_frame_v2(msgid, payload, sysid, compid, self._next_seq()), sender)

    def _unknown_msgid(self, kind: str) -> Datagram:
        msgid = self.rng.choice([0xFFFFFF, 0x123456, 60000, 299 + self.rng.randint(1000, 9000)])
        payload = self.rng.randbytes(self.rng.randint(1, 255))
        return Datagram(kind, raw_frame_v2(msgid, payload, *self._foreign_ids(), self._next_seq(),
                                           crc_extra=self.rng.randint(0, 255)), self._sender())

    def _fake_signature_flag(self, kind: str) -> Datagram:
        """A frame that says it is signed, with 13 random bytes as its signature."""
        msgid = self.rng.choice([0, 331, 84, 77, 253])
        payload = self.rng.randbytes(_payload_size(msgid))
        sender = "foreign" if msgid == 0 else self._sender(0.5)
        sysid, compid = AUTOPILOT_IDS if sender == "autopilot" else self._foreign_ids()
        return Datagram(kind, raw_frame_v2(msgid, payload, sysid, compid, self._next_seq(), incompat=1,
                                           tail=self.rng.randbytes(13)), sender)

    def _heartbeat_foreign(self, kind: str) -> Datagram:
        """A HEARTBEAT with a random mode from another system (never the autopilot's own ids)."""
        r = self.rng
        msg = self.mav.heartbeat_encode(r.choice([2, 1, 13, 6, 18, r.randint(0, 255)]), r.choice([12, 3, 8, r.randint(0, 255)]),
                                        r.randint(0, 255), r.choice(_PX4_CUSTOM_MODES + (r.getrandbits(32),)), r.randint(0, 8))
        sysid = self.rng.randint(2, 254)
        compid = self.rng.choice([1, self.rng.randint(0, 255)])
        return Datagram(kind, self._pack(msg, sysid, compid, v1=self.rng.random() < 0.2), self._sender())

    def _telemetry_hostile(self, kind: str) -> Datagram:
        """ODOMETRY / LOCAL_POSITION_NED / ATTITUDE with NaN, inf or huge fields (issue 16 item 13)."""
        m, h = self.mav, self._maybe_hostile
        which = self.rng.randrange(3)
        if which == 0:
            nan_q = self.rng.random() < 0.2
            q = [math.nan, 0, 0, 0] if nan_q else [1.0, 0.0, 0.0, 0.0]
            msg = m.odometry_encode(int(time.time() * 1e6) & 0xFFFFFFFFFFFFFFFF, 1, 1, h(1.0), h(0.0), h(-3.0), q,
                                    h(1.0), h(0.0), h(0.0), h(0.0, 0.7), h(0.0, 0.7), h(0.0, 0.7),
                                    [math.nan] * 21, [math.nan] * 21, 0, 0, 0)
        elif which == 1:
            msg = m.local_position_ned_encode(0, h(1.0), h(0.0), h(-3.0), h(1.0), h(0.0), h(0.0))
        else:
            msg = m.attitude_encode(0, h(0.0), h(0.0), h(0.0), h(0.0, 0.7), h(0.0, 0.7), h(0.0, 0.7))
        sender = self._sender(0.7)
        sysid, compid = AUTOPILOT_IDS if sender == "autopilot" else self._foreign_ids()
        return Datagram(kind, self._pack(msg, sysid, compid), sender)

    def _command_ack(self, kind: str) -> Datagram:
        command = self.rng.choice([400, 176, 22, 21, 511, self.rng.randint(0, 65535)])
        msg = self.mav.command_ack_encode(command, self.rng.randint(0, 255), self.rng.randint(0, 100),
                                          self.rng.randint(-2**31, 2**31 - 1), self.rng.randint(0, 255), self.rng.randint(0, 255))
        sender = self._sender(0.7)
        sysid, compid = AUTOPILOT_IDS if sender == "autopilot" else self._foreign_ids()
        return Datagram(kind, self._pack(msg, sysid, compid), sender)

    def _goal_out_of_range(self, kind: str) -> Datagram:
        """A run-time goal to component 191 that no one should fly to (issue 16 item 14)."""
        r = self.rng
        bad = [3.4e38, -3.4e38, 1e9, -1e9, math.nan, math.inf, -math.inf]
        x, y, z = r.choice(bad + [10.0]), r.choice(bad + [0.0]), r.choice(bad + [50.0, 1e4, -3.0])
        if all(math.isfinite(v) and abs(v) < 1e3 for v in (x, y)) and -1e3 < z < 1.0:
            z = 50.0  # keep it out of range: 50 m underground
        msg = self.mav.set_position_target_local_ned_encode(0, r.choice([0, 1]), MAV_COMP_ID_ONBOARD_COMPUTER, 1,
                                                            0b110111111000, x, y, z, 0, 0, 0, 0, 0, 0, math.nan, math.nan)
        sysid, compid = r.choice([(255, 190), (r.randint(2, 254), r.randint(0, 255)), AUTOPILOT_IDS])
        return Datagram(kind, self._pack(msg, sysid, compid), self._sender())

    def _statustext_junk(self, kind: str) -> Datagram:
        msg = self.mav.statustext_encode(self.rng.randint(0, 255), self.rng.randbytes(50),
                                         self.rng.randint(0, 65535), self.rng.randint(0, 255))
        sender = self._sender(0.5)
        sysid, compid = AUTOPILOT_IDS if sender == "autopilot" else self._foreign_ids()
        return Datagram(kind, self._pack(msg, sysid, compid), sender)

    def _junk_then_frame(self, kind: str) -> Datagram:
        """Junk and a real frame in one datagram (junk first: a parser must resynchronise)."""
        junk = self.rng.choice([b"\xfd\xff", b"\xfe\xff", self.rng.randbytes(self.rng.randint(1, 30))])
        return Datagram(kind, junk + self._valid_frame(), self._sender(0.3))


class SigningFuzzer(_KindMix):
    """Forged (wrong key), replayed and unsigned traffic for a companion with MAVLink 2 signing.

    Args:
        rng: the seeded random source.
        onboard_frames: callable returning signed vehicle->companion datagrams (link id 1) captured live.
        gcs_frames: callable returning signed vehicle->ground-station datagrams (link id 2) captured
            before takeoff (a disarmed vehicle in its start mode: a hand-back if accepted).
    """

    def __init__(self, rng: random.Random, onboard_frames, gcs_frames) -> None:
        self.rng = rng
        self.onboard_frames, self.gcs_frames = onboard_frames, gcs_frames
        self.wrong_key = bytes(rng.getrandbits(8) for _ in range(32))
        self.forger = mavlink.MAVLink(None, srcSystem=AUTOPILOT_IDS[0], srcComponent=AUTOPILOT_IDS[1])
        self.forger.signing.secret_key = self.wrong_key
        self.forger.signing.sign_outgoing = True
        self.plain = mavlink.MAVLink(None, srcSystem=AUTOPILOT_IDS[0], srcComponent=AUTOPILOT_IDS[1])
        self.kinds = [("forged_autopilot", 8), ("forged_near_max_timestamp", 3), ("forged_foreign_streams", 4),
                      ("replay_same_link", 6), ("replay_other_link", 6), ("unsigned_autopilot", 6)]
        self._init_mix()

    def next(self) -> Datagram:
        kind = self.pick()
        return getattr(self, "_" + kind)(kind)

    def _message(self, mav):
        """A message that changes behaviour if believed: hand-back heartbeat, goal, telemetry, ack."""
        r = self.rng
        which = r.randrange(4)
        if which == 0:  # PX4 POSCTL, disarmed: "the pilot took over"
            return mav.heartbeat_encode(2, 12, r.choice([0, 81]), r.choice(_PX4_CUSTOM_MODES), 3)
        if which == 1:
            return mav.set_position_target_local_ned_encode(0, 1, MAV_COMP_ID_ONBOARD_COMPUTER, 1, 0b110111111000,
                                                            r.uniform(-20, 20), r.uniform(-20, 20), -3.0,
                                                            0, 0, 0, 0, 0, 0, math.nan, math.nan)
        if which == 2:
            return mav.odometry_encode(0, 1, 1, r.uniform(-50, 50), r.uniform(-50, 50), -3.0, [1.0, 0.0, 0.0, 0.0],
                                       0.0, 0.0, 0.0, 0.0, 0.0, 0.0, [math.nan] * 21, [math.nan] * 21, 0, 0, 0)
        return mav.command_ack_encode(r.choice([400, 176, 22, 511]), r.randint(0, 6), 0, 0, 1, 191)

    def _forge(self, sysid: int, compid: int, link_id: int, timestamp: int) -> bytes:
        f = self.forger
        f.srcSystem, f.srcComponent = sysid, compid
        f.signing.link_id, f.signing.timestamp = link_id, timestamp
        return self._message(f).pack(f)

    def _forged_autopilot(self, kind: str) -> Datagram:
        ts = signing_timestamp_now() + self.rng.randint(-500_000, 500_000)
        link_id = self.rng.choice([1, 1, 2, 0, self.rng.randint(0, 255)])
        return Datagram(kind, self._forge(*AUTOPILOT_IDS, link_id, ts), self.rng.choice(["autopilot", "foreign"]))

    def _forged_near_max_timestamp(self, kind: str) -> Datagram:
        """Issue 16 item 2: a wrong-key frame from the autopilot's ids with timestamp 2^48-100."""
        return Datagram(kind, self._forge(*AUTOPILOT_IDS, self.rng.choice([1, 1, 2, self.rng.randint(0, 255)]),
                                          SIGNING_TIMESTAMP_NEAR_MAX), self.rng.choice(["autopilot", "foreign"]))

    def _forged_foreign_streams(self, kind: str) -> Datagram:
        """Wrong-key frames from ever new (link, system, component) streams (issue 16 item 12)."""
        r = self.rng
        return Datagram(kind, self._forge(r.randint(2, 254), r.randint(0, 255), r.randint(0, 255),
                                          signing_timestamp_now()), "foreign")

    def _replay(self, kind: str, frames) -> Datagram:
        if not frames:
            return self._unsigned_autopilot("unsigned_autopilot")
        return Datagram(kind, bytes(self.rng.choice(frames)), self.rng.choice(["autopilot", "foreign"]))

    def _replay_same_link(self, kind: str) -> Datagram:
        return self._replay(kind, self.onboard_frames())

    def _replay_other_link(self, kind: str) -> Datagram:
        """Issue 16 item 3: the vehicle's own signed frames from its ground-station link (link id 2)."""
        return self._replay(kind, self.gcs_frames())

    def _unsigned_autopilot(self, kind: str) -> Datagram:
        return Datagram(kind, self._message(self.plain).pack(self.plain), self.rng.choice(["autopilot", "foreign"]))


class DepthFuzzer(_KindMix):
    """Hostile depth datagrams (format: :mod:`companion.depth_wire`) for the companion's depth port.

    Args:
        rng: the seeded random source.
        width, height, hfov_deg, max_range_m: what the real camera sends (the policy's camera).
        vehicle: the index of the vehicle the companion flies.
    """

    #: Frames no step may fly on (issue 16 item 5). A stamp from the future (``future_stamp``) is
    #: sent but not judged: whether a camera clock ahead of ours is refused is a design choice.
    REFUSABLE = ("all_zero", "all_negative", "all_nan", "all_inf", "mostly_invalid", "wrong_vehicle",
                 "stale_stamp", "uint16_zero")

    def __init__(self, rng: random.Random, width: int, height: int, hfov_deg: float, max_range_m: float,
                 vehicle: int = 0) -> None:
        self.rng = rng
        self.width, self.height, self.hfov_deg, self.max_range_m = width, height, hfov_deg, max_range_m
        self.vehicle = vehicle
        self.refusable_count = 0
        self.tolerable_count = 0
        self.kinds = [
            ("bad_magic", 3), ("bad_version", 3), ("bad_encoding", 2), ("truncated", 4), ("huge_dims", 4),
            ("empty_dims", 2), ("bad_fov", 3), ("bad_range", 3), ("bad_scale", 3), ("random_bytes", 3),
            ("all_zero", 6), ("all_negative", 4), ("all_nan", 4), ("all_inf", 3), ("mostly_invalid", 4),
            ("some_nan", 3), ("huge_pixels", 3), ("wrong_vehicle", 5), ("stale_stamp", 5), ("future_stamp", 3),
            ("uint16_zero", 3), ("tiny_frame", 2),
        ]
        self._init_mix()

    def _seq(self, refusable: bool) -> int:
        if refusable:
            self.refusable_count += 1
            return REFUSABLE_SEQ_BASE + self.refusable_count % _SEQ_SPAN
        self.tolerable_count += 1
        return TOLERABLE_SEQ_BASE + self.tolerable_count % _SEQ_SPAN

    def frame(self, pixels, *, refusable: bool, vehicle: int | None = None, stamp_us: int | None = None,
              depth_scale: float | None = None) -> bytes:
        """A well-formed datagram carrying ``pixels`` (metres), tagged by ``seq``."""
        import numpy as np

        pixels = np.broadcast_to(np.asarray(pixels, np.float32), (self.height, self.width))
        return encode_frame(pixels, vehicle=self.vehicle if vehicle is None else vehicle, seq=self._seq(refusable),
                            stamp_us=int(time.time() * 1e6) if stamp_us is None else stamp_us,
                            hfov_deg=self.hfov_deg, max_range_m=self.max_range_m, depth_scale=depth_scale)

    def _header(self, **over) -> bytes:
        f = dict(magic=MAGIC, version=VERSION, encoding=1, vehicle=self.vehicle, seq=self._seq(False),
                 stamp_us=int(time.time() * 1e6), height=self.height, width=self.width, hfov_deg=self.hfov_deg,
                 max_range_m=self.max_range_m, depth_scale=0.0, reserved=0)
        f.update(over)
        return HEADER.pack(f["magic"], f["version"], f["encoding"], f["vehicle"], f["seq"], f["stamp_us"], f["height"],
                           f["width"], f["hfov_deg"], f["max_range_m"], f["depth_scale"], f["reserved"])

    def _clear(self) -> bytes:
        return struct.pack(f"<{self.height * self.width}f", *([self.max_range_m] * (self.height * self.width)))

    def next(self) -> Datagram:
        kind = self.pick()
        return Datagram(kind, self.make(kind), "foreign")

    def make(self, kind: str) -> bytes:
        """One datagram of ``kind``."""
        import numpy as np

        r, n = self.rng, self.height * self.width
        if kind == "bad_magic":
            return self._header(magic=r.randbytes(4)) + self._clear()
        if kind == "bad_version":
            return self._header(version=r.choice([0, 2, 255])) + self._clear()
        if kind == "bad_encoding":
            return self._header(encoding=r.choice([0, 3, 255])) + self._clear()
        if kind == "truncated":
            data = self._header() + self._clear()
            return data[: r.randint(0, len(data) - 1)]
        if kind == "huge_dims":
            return self._header(height=r.choice([65535, 4096]), width=r.choice([65535, 4096])) + self._clear()
        if kind == "empty_dims":
            return self._header(height=r.choice([0, self.height]), width=0)
        if kind == "bad_fov":
            return self._header(hfov_deg=r.choice([math.nan, math.inf, 0.0, -90.0, 180.0, 1e30])) + self._clear()
        if kind == "bad_range":
            return self._header(max_range_m=r.choice([math.nan, math.inf, 0.0, -20.0])) + self._clear()
        if kind == "bad_scale":
            return self._header(encoding=2, depth_scale=r.choice([0.0, -1e-3, math.nan, math.inf])) + bytes(2 * n)
        if kind == "random_bytes":
            return r.randbytes(r.randint(1, 8000))
        if kind == "all_zero":
            return self.frame(0.0, refusable=True)
        if kind == "all_negative":
            return self.frame(-r.uniform(0.01, 100.0), refusable=True)
        if kind == "all_nan":
            return self.frame(math.nan, refusable=True)
        if kind == "all_inf":
            return self.frame(r.choice([math.inf, -math.inf]), refusable=True)
        if kind == "mostly_invalid":  # >= 95 % holes: a covered lens with a few speckles
            pix = np.full(n, r.choice([0.0, math.nan, -1.0]), np.float32)
            keep = np.random.default_rng(r.getrandbits(32)).choice(n, size=max(1, n // 40), replace=False)
            pix[keep] = self.max_range_m
            return self.frame(pix.reshape(self.height, self.width), refusable=True)
        if kind == "some_nan":  # stereo holes: tolerable
            pix = np.full(n, self.max_range_m, np.float32)
            holes = np.random.default_rng(r.getrandbits(32)).choice(n, size=n // 10, replace=False)
            pix[holes] = math.nan
            return self.frame(pix.reshape(self.height, self.width), refusable=False)
        if kind == "huge_pixels":
            return self.frame(r.choice([1e30, 3.4e38, 1e6]), refusable=False)
        if kind == "wrong_vehicle":  # a wall at 1 m from another vehicle's camera
            return self.frame(1.0, refusable=True, vehicle=r.choice([self.vehicle + 1, 7, 65535]))
        if kind == "stale_stamp":  # a wall at 1 m, captured seconds to hours ago
            return self.frame(1.0, refusable=True, stamp_us=int((time.time() - r.uniform(2.0, 3600.0)) * 1e6))
        if kind == "future_stamp":
            return self.frame(1.0, refusable=False, stamp_us=int((time.time() + r.uniform(2.0, 3600.0)) * 1e6))
        if kind == "uint16_zero":  # a z16 frame of nothing but "no data": blinded
            return self.frame(0.0, refusable=True, depth_scale=0.001)
        if kind == "tiny_frame":
            return encode_frame(np.full((1, 1), self.max_range_m, np.float32), vehicle=self.vehicle,
                                seq=self._seq(False), stamp_us=int(time.time() * 1e6), hfov_deg=self.hfov_deg,
                                max_range_m=self.max_range_m)
        raise ValueError(f"unknown depth kind {kind}")


# --------------------------------------------------------------------------- model metadata


#: Fixed hostile edits of policy.json (issue 16 items 6, 8, 9): name -> (path, value).
#: A path is a tuple of keys; the value replaces what is there (``_DELETE`` removes it).
_DELETE = object()
NAMED_MODEL_MUTATIONS: dict[str, tuple[tuple, object]] = {  # the cases first (--smoke takes the first few)
    "bounds_inf": (("action",), "BOUNDS_INF"),
    "control_period_inf": (("control_period_s",), math.inf),
    "control_period_abc": (("control_period_s",), "abc"),
    "hfov_null": (("depth", "hfov_deg"), None),
    "bounds_100": (("action",), "BOUNDS_100"),
    "control_period_1e-4": (("control_period_s",), 1e-4),
    "depth_string": (("depth",), "abc"),
    "bounds_strings": (("action", "low"), ["a", "b", "c"]),
    "bounds_null": (("action", "high"), None),
    "control_period_nan": (("control_period_s",), math.nan),
    "control_period_null": (("control_period_s",), None),
    "action_names_wrong": (("action", "names"), ["a", "b", "c"]),
    "action_names_swapped": (("action", "names"), ["vel_down_m_s", "vel_fwd_m_s", "yaw_rate_rad_s"]),
    "action_four_values": (("action",), "FOUR"),
    "width_float": (("depth", "width"), 31.5),
    "width_huge": (("depth", "width"), 10 ** 9),
    "frames_zero": (("depth", "frames"), 0),
    "max_range_inf": (("depth", "max_range_m"), math.inf),
    "state_names_wrong": (("state_names",), ["x"] * 6),
    "format_version_string": (("format_version",), "1"),
    "action_number": (("action",), 3),
    "metadata_list": ((), []),
    "missing_action": (("action",), _DELETE),
}
_RANDOM_TARGETS = (("control_period_s",), ("depth", "height"), ("depth", "width"), ("depth", "frames"),
                   ("depth", "hfov_deg"), ("depth", "max_range_m"), ("depth", "units"), ("depth", "kind"),
                   ("action", "low"), ("action", "high"), ("action", "names"), ("state_names",), ("format_version",),
                   ("depth",), ("action",))
_RANDOM_VALUES = (None, "abc", math.inf, -math.inf, math.nan, 1e308, -1.0, 0, 0.5, True, [], {}, [None] * 3,
                  [math.inf] * 3, [-100.0] * 3, [100.0] * 3, "", [1, 2], 2 ** 63)


def _special(value, meta: dict):
    action = meta.get("action", {})
    if value == "BOUNDS_INF":
        return {**action, "low": [-math.inf] * 3, "high": [math.inf] * 3}
    if value == "BOUNDS_100":
        return {**action, "low": [-100.0] * 3, "high": [100.0] * 3}
    if value == "FOUR":
        return {"names": list(action["names"]) + ["extra"], "low": list(action["low"]) + [0.0],
                "high": list(action["high"]) + [1.0]}
    return value


def mutate_metadata(meta: dict, path: tuple, value) -> object:
    """A deep copy of ``meta`` with ``value`` at ``path`` (the whole document for an empty path)."""
    new = json.loads(json.dumps(meta))
    value = _special(value, new)
    if not path:
        return value
    node = new
    for key in path[:-1]:
        node = node[key]
    if value is _DELETE:
        node.pop(path[-1], None)
    else:
        node[path[-1]] = value
    return new


def model_mutations(rng: random.Random, count: int) -> list[tuple[str, tuple, object]]:
    """``count`` hostile edits: the named ones first (issue 16's), then random ones."""
    named = [(name, path, value) for name, (path, value) in NAMED_MODEL_MUTATIONS.items()]
    out = named[:count]
    while len(out) < count:
        path = rng.choice(_RANDOM_TARGETS)
        value = rng.choice(_RANDOM_VALUES)
        out.append((f"random:{'.'.join(path)}={value!r}"[:80], path, value))
    return out


def all_kinds() -> set[str]:
    """Every input kind of the MAVLink, signing and depth mixes."""
    rng = random.Random(0)
    mixes = (MavlinkFuzzer(rng, list), SigningFuzzer(rng, list, list), DepthFuzzer(rng, 32, 32, 90.0, 20.0))
    return {k for mix in mixes for k, _ in mix.kinds}


#: The kinds only a signing run sends.
SIGNING_KINDS = frozenset(k for k, _ in SigningFuzzer(random.Random(0), list, list).kinds)
