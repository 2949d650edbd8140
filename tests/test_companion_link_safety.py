"""The companion's MAVLink endpoint under hostile traffic (issue 16, items 1-3 and 10-13).

Each test drives the real :class:`companion.mavlink_link.AutopilotLink` over real UDP sockets
on 127.0.0.1, with the simulator's own MAVLink endpoint (:class:`sitl.realtime.udp_endpoint.MavlinkUdpEndpoint`)
as the autopilot and plain sockets as the attacker; the odometry test flies the real vehicle and
companion processes with a relay on the wire that corrupts ODOMETRY. All bounded in time.
"""

from __future__ import annotations

import math
import select
import socket
import subprocess
import sys
import threading
import time

import pytest

from companion.mavlink_endpoint import MAX_SIGNING_STREAMS, mavlink
from companion.mavlink_link import AutopilotLink, LinkError, OdometryInvalid, odometry_from_msg
from sitl.realtime.udp_endpoint import MavlinkUdpEndpoint
from tests.companion_helpers import CONTROL_PERIOD_S, REPO, Processes, Rig, env, free_udp_ports, make_policy

pytestmark = pytest.mark.timeout(120)

KEY = bytes(range(32))
WRONG_KEY = bytes(range(1, 33))
PX4_POSCTL = 3 << 16  # PX4 custom mode: main mode 3 (POSCTL)
PX4_OFFBOARD = 6 << 16


# --------------------------------------------------------------------------- helpers


def _open_link(key: bytes | None = None) -> tuple[AutopilotLink, int]:
    port = free_udp_ports(1)[0]
    link = AutopilotLink(f"udpin:127.0.0.1:{port}", signing_key=key)
    link.open()
    return link, port


def _autopilot(port: int, key: bytes | None = None, link_id: int = 1) -> MavlinkUdpEndpoint:
    """The simulator's PX4-style endpoint (system 1, component 1) sending to the companion's port."""
    return MavlinkUdpEndpoint.autopilot_link("onboard", ("127.0.0.1", port), 1, key, link_id=link_id)


def _heartbeat(ap: MavlinkUdpEndpoint, custom_mode: int = PX4_OFFBOARD, armed: bool = True) -> None:
    base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
    ap.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base, custom_mode,
                          mavlink.MAV_STATE_ACTIVE)


def _pump(link: AutopilotLink, until, timeout_s: float, events: list | None = None) -> bool:
    """Receive until ``until()`` is true (True) or ``timeout_s`` passed (False)."""
    deadline = time.monotonic() + timeout_s
    while True:
        got = link.receive(time.monotonic())
        if events is not None:
            events.extend(got)
        if until():
            return True
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return False
        select.select([link.fileno()], [], [], min(remaining, 0.02))


def _dropped(link: AutopilotLink) -> tuple[int, int]:
    """(from other addresses, from other signing link ids): 0 where a link does not count them."""
    return getattr(link, "dropped_foreign_address", 0), getattr(link, "dropped_foreign_link", 0)


def _connected(key: bytes | None = None) -> tuple[AutopilotLink, MavlinkUdpEndpoint]:
    link, port = _open_link(key)
    ap = _autopilot(port, key)
    _heartbeat(ap)
    link.wait_for_autopilot(3.0)
    return link, ap


class _SocketFile:
    """Lets a pymavlink codec write its frames to ``addr`` through ``sock``."""

    def __init__(self, sock: socket.socket, addr: tuple[str, int]) -> None:
        self.sock, self.addr = sock, addr

    def write(self, buf: bytes) -> None:
        self.sock.sendto(buf, self.addr)


def _codec(sock: socket.socket, addr, sysid: int = 1, compid: int = 1, key: bytes | None = None,
           link_id: int = 0, timestamp: int | None = None) -> mavlink.MAVLink:
    mav = mavlink.MAVLink(_SocketFile(sock, addr), srcSystem=sysid, srcComponent=compid)
    if key is not None:
        mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.link_id = key, True, link_id
        mav.signing.timestamp = timestamp if timestamp is not None else int((time.time() - 1420070400) * 1e5)
    return mav


# --------------------------------------------------------------------------- item 1: per-datagram parsing


def _truncated_frame() -> bytes:
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    return mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 0, 3).pack(mav)[:9]


@pytest.mark.parametrize("junk", [b"\xfd\xff", b"\xfe\xff", _truncated_frame()], ids=["v2_header", "v1_header", "truncated"])
def test_a_short_junk_datagram_does_not_swallow_the_next_frame(junk):
    link, ap = _connected()
    try:
        parsed = misses = 0
        for i in range(200):
            ap.sock.sendto(junk, ap.remote)  # from the autopilot's own address: only parsing can save it
            _heartbeat(ap, custom_mode=(i + 1) << 16)
            if _pump(link, lambda i=i: link.heartbeat.custom_mode == (i + 1) << 16, 0.25):
                parsed += 1
            else:
                misses += 1
                if misses >= 5:
                    break  # the old parser loses them all: do not wait 200 times
        assert parsed == 200, f"{parsed} of 200 heartbeats parsed after {junk!r} datagrams"
    finally:
        link.close()
        ap.close()


# --------------------------------------------------------------------------- item 2: verify before store


def test_a_forged_max_timestamp_packet_does_not_lock_the_autopilot_out():
    link, ap = _connected(KEY)
    try:
        # One HEARTBEAT with the autopilot's ids and link id, a wrong key and timestamp 2^48-100,
        # sent from the autopilot's own address (as over a serial or TCP link).
        forger = _codec(ap.sock, ap.remote, key=WRONG_KEY, link_id=1, timestamp=2**48 - 100)
        forger.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                              mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, PX4_POSCTL, mavlink.MAV_STATE_ACTIVE)
        time.sleep(0.05)
        link.receive(time.monotonic())
        assert link.heartbeat.custom_mode == PX4_OFFBOARD  # the forgery changed nothing
        assert max(link.conn.mav.signing.stream_timestamps.values()) < 2**48 - 1000
        accepted = 0
        for i in range(20):  # the genuine autopilot keeps being heard
            _heartbeat(ap, custom_mode=(i + 10) << 16)
            accepted += _pump(link, lambda i=i: link.heartbeat.custom_mode == (i + 10) << 16, 0.25)
        assert accepted == 20, f"{accepted} of 20 genuine heartbeats accepted after the forgery"
    finally:
        link.close()
        ap.close()


# --------------------------------------------------------------------------- item 3: lock to the autopilot


def test_a_replayed_heartbeat_from_another_link_id_is_ignored_and_routed_goals_still_work():
    link, ap = _connected(KEY)
    capture = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    capture.bind(("127.0.0.1", 0))
    capture.settimeout(2.0)
    gcs_link = MavlinkUdpEndpoint.autopilot_link("gcs", capture.getsockname(), 1, KEY, link_id=2)  # the autopilot's GCS link
    attacker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        # What the autopilot told the ground station: POSCTL, disarmed (the pilot has it).
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        gcs_link.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base, PX4_POSCTL,
                                    mavlink.MAV_STATE_STANDBY)
        captured = capture.recv(4096)
        events: list = []
        # Replayed through the autopilot's own address (a router, TCP) and from another address.
        ap.sock.sendto(captured, ap.remote)
        attacker.sendto(captured, ap.remote)
        _pump(link, lambda: min(_dropped(link)) >= 1 or link.heartbeat.custom_mode != PX4_OFFBOARD, 1.0, events)
        assert link.heartbeat.custom_mode == PX4_OFFBOARD and link.heartbeat.armed, "the replay was acted upon"
        assert _dropped(link) == (1, 1)
        # Reported once per reason, however often it happens.
        for _ in range(5):
            ap.sock.sendto(captured, ap.remote)
            attacker.sendto(captured, ap.remote)
        # (Through the autopilot's address the copies are now old for their stream: refused by the signature check.)
        assert _pump(link, lambda: _dropped(link)[0] >= 6 and link.refused_unsigned >= 5, 1.0, events)
        ignored = [e for e in events if e.kind == "ignored_traffic"]
        assert len(ignored) == 2, [e.detail for e in ignored]
        assert link.heartbeat.custom_mode == PX4_OFFBOARD
        # The documented goal path: a ground station's signed goal (system 255, its own link id),
        # routed by the autopilot onto the companion's link, still arrives.
        gcs = _codec(ap.sock, ap.remote, sysid=255, compid=190, key=KEY, link_id=7)
        gcs.set_position_target_local_ned_send(0, 1, 191, 1, 3576, 20.0, 5.0, -6.0, 0, 0, 0, 0, 0, 0, 0, 0)
        goals: list = []
        assert _pump(link, lambda: any(e.kind == "goal" for e in goals), 1.0, goals)
        goal = next(e for e in goals if e.kind == "goal")
        assert goal.detail["goal_ned"] == [20.0, 5.0, -6.0] and goal.detail["signed"]
    finally:
        for closable in (link, ap, gcs_link, capture, attacker):
            closable.close()


# --------------------------------------------------------------------------- item 10: one peer


def test_foreign_senders_are_never_sent_to_and_never_heard():
    link, port = _open_link()
    strangers = []
    ap = None
    try:
        for _ in range(50):  # before the autopilot is heard: one byte and a valid frame each
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", 0))
            s.setblocking(False)
            s.sendto(b"\x00", ("127.0.0.1", port))
            strangers.append(s)
        gcs = _codec(strangers[0], ("127.0.0.1", port), sysid=255, compid=190)
        gcs.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        link.receive(time.monotonic())
        link.send_heartbeat()  # before the lock there is nobody to talk to
        ap = _autopilot(port)
        _heartbeat(ap)
        link.wait_for_autopilot(3.0)
        # After the lock: strangers spoof the autopilot's heartbeat and send junk.
        for s in strangers:
            s.sendto(b"\x01", ("127.0.0.1", port))
            _codec(s, ("127.0.0.1", port)).heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                                                           0, PX4_POSCTL, mavlink.MAV_STATE_ACTIVE)
        _pump(link, lambda: _dropped(link)[0] >= 100, 1.0)
        assert link.heartbeat.custom_mode == PX4_OFFBOARD and link.heartbeat.armed, "a spoofed heartbeat was acted upon"
        assert _dropped(link)[0] == 100
        for _ in range(5):
            link.send_heartbeat()
            link.send_velocity_setpoint(1.0, 0.0, 0.0)
        link.send_statustext(mavlink.MAV_SEVERITY_INFO, "hello")
        assert len(ap.receive()) + len(_drain_wait(ap)) >= 11  # the autopilot gets everything
        time.sleep(0.1)
        heard = 0
        for s in strangers:
            try:
                while s.recv(4096):
                    heard += 1
            except BlockingIOError:
                pass
        assert heard == 0, f"{heard} datagrams went to {len(strangers)} strangers"
    finally:
        link.close()
        if ap is not None:
            ap.close()
        for s in strangers:
            s.close()


def test_the_link_follows_an_autopilot_that_restarts_on_a_new_port_only_after_silence():
    """A router or autopilot restarted on a new source port is heard again once the old one has been
    silent for the re-lock time; while the old one talks, the same heartbeat from a new port is dropped."""
    port = free_udp_ports(1)[0]
    link = AutopilotLink(f"udpin:127.0.0.1:{port}", relock_after_s=0.5)
    link.open()
    old = _autopilot(port)
    new = None
    try:
        _heartbeat(old)
        link.wait_for_autopilot(3.0)
        first = link.conn.locked_address
        new = _autopilot(port)  # the same system and component, from another port
        _heartbeat(old)
        _heartbeat(new, custom_mode=PX4_POSCTL)
        _pump(link, lambda: _dropped(link)[0] >= 1, 1.0)
        assert link.conn.locked_address == first and link.heartbeat.custom_mode == PX4_OFFBOARD
        time.sleep(0.7)  # the old port falls silent past the re-lock time
        events: list = []
        _heartbeat(new, custom_mode=PX4_POSCTL)
        assert _pump(link, lambda: link.conn.locked_address != first, 1.0, events)
        assert link.heartbeat.custom_mode == PX4_POSCTL
        assert [e.kind for e in events if e.kind == "relocked"] == ["relocked"]
        for _ in range(3):
            link.send_heartbeat()
        assert _drain_wait(new), "the new port gets our traffic"
        _heartbeat(old, custom_mode=PX4_OFFBOARD)  # the old port again: now a stranger
        dropped = _dropped(link)[0]
        _pump(link, lambda: _dropped(link)[0] > dropped, 1.0)
        assert link.heartbeat.custom_mode == PX4_POSCTL
    finally:
        link.close()
        old.close()
        if new is not None:
            new.close()


def _drain_wait(ap: MavlinkUdpEndpoint) -> list:
    select.select([ap.sock], [], [], 0.2)
    time.sleep(0.05)
    return ap.receive()


# --------------------------------------------------------------------------- item 11: exclusive port


def test_the_port_cannot_be_shared():
    link, port = _open_link()
    try:
        for reuse in (False, True):
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as second:
                if reuse:
                    second.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                with pytest.raises(OSError):
                    second.bind(("127.0.0.1", port))
        other = AutopilotLink(f"udpin:127.0.0.1:{port}")
        with pytest.raises(LinkError, match=rf"cannot open udpin:127.0.0.1:{port}: address already in use"):
            other.open()
    finally:
        link.close()


def test_a_second_companion_on_the_port_exits_5_with_one_line(tmp_path):
    link, port = _open_link()
    try:
        model = make_policy(tmp_path / "policy.pt")
        depth_port = free_udp_ports(1)[0]
        proc = subprocess.run([sys.executable, "-m", "companion.cli", "--connect", f"udpin:127.0.0.1:{port}",
                               "--model", str(model), "--camera", f"sitl:{depth_port}", "--heartbeat-timeout", "2"],
                              cwd=REPO, env=env(), capture_output=True, text=True, timeout=60)
    finally:
        link.close()
    assert proc.returncode == 5, proc.stderr
    assert "Traceback" not in proc.stderr
    errors = [line for line in proc.stderr.splitlines() if "address already in use" in line]
    assert len(errors) == 1 and f"udpin:127.0.0.1:{port}" in errors[0], proc.stderr


# --------------------------------------------------------------------------- item 12: bounded signing table


def test_wrong_key_traffic_leaves_no_trace_and_the_stream_table_is_capped():
    link, ap = _connected(KEY)
    try:
        table = link.conn.mav.signing.stream_timestamps
        forger = _codec(ap.sock, ap.remote, key=WRONG_KEY)
        sent = 0
        for i in range(10_240):  # distinct (link id, system, component) every time
            forger.signing.link_id, forger.srcSystem, forger.srcComponent = i & 0xFF, 2 + (i >> 8), 1
            forger.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            sent += 1
            if i % 200 == 199:
                link.receive(time.monotonic(), max_messages=1000)  # keep the socket buffer from dropping
        _pump(link, lambda: False, 0.2)
        assert sent == 10_240
        assert len(table) <= 1, f"{len(table)} signing streams after {sent} wrong-key messages"
        # Even key holders cannot grow it past the cap.
        holder = _codec(ap.sock, ap.remote, key=KEY)
        for i in range(3 * MAX_SIGNING_STREAMS):
            holder.signing.link_id, holder.srcSystem = i & 0xFF, 100 + (i >> 8)
            holder.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        _pump(link, lambda: False, 0.2)
        assert len(table) == MAX_SIGNING_STREAMS
        _heartbeat(ap, custom_mode=PX4_POSCTL)  # the autopilot's stream is still known and heard
        assert _pump(link, lambda: link.heartbeat.custom_mode == PX4_POSCTL, 1.0)
    finally:
        link.close()
        ap.close()


# --------------------------------------------------------------------------- item 13: odometry values


def _odometry_msg(**fields) -> mavlink.MAVLink_odometry_message:
    values = dict(time_usec=0, frame_id=1, child_frame_id=1, x=1.0, y=2.0, z=-3.0, q=[1.0, 0.0, 0.0, 0.0],
                  vx=0.5, vy=0.0, vz=0.0, rollspeed=0.0, pitchspeed=0.0, yawspeed=0.1,
                  pose_covariance=[math.nan] * 21, velocity_covariance=[math.nan] * 21)
    values.update(fields)
    return mavlink.MAVLink_odometry_message(**values)


@pytest.mark.parametrize("fields, what", [
    ({"pitchspeed": math.nan, "yawspeed": math.nan}, "ODOMETRY holds non-finite angular rates"),
    ({"q": [math.nan, 0.0, 0.0, 0.0]}, "ODOMETRY holds non-finite attitude"),
    ({"q": [0.0, 0.0, 0.0, 0.0]}, "ODOMETRY attitude is not a unit quaternion"),
    ({"vx": 3.4e38}, "ODOMETRY holds out-of-range velocity"),
])
def test_odometry_with_impossible_values_is_refused_with_its_reason(fields, what):
    with pytest.raises(OdometryInvalid, match=what):
        odometry_from_msg(_odometry_msg(**fields), 0.0)


def test_local_position_and_attitude_with_nan_rates_set_and_clear_the_odometry_fault():
    link, ap = _connected()
    try:
        def send(yawspeed: float) -> None:
            ap.mav.local_position_ned_send(0, 1.0, 2.0, -3.0, 0.5, 0.0, 0.0)
            ap.mav.attitude_send(0, 0.0, 0.0, 0.3, 0.0, math.nan if math.isnan(yawspeed) else 0.0, yawspeed)

        send(0.1)
        assert _pump(link, lambda: link.odometry is not None, 1.0) and link.odometry_fault is None
        send(math.nan)
        assert _pump(link, lambda: link.odometry_fault is not None, 1.0)
        assert link.odometry_fault == "odometry invalid: ATTITUDE holds non-finite angular rates"
        send(0.1)
        assert _pump(link, lambda: link.odometry_fault is None, 1.0)
    finally:
        link.close()
        ap.close()


class _OdometryCorruptingRelay:
    """A wire between the vehicle and the companion that can set ODOMETRY's body rates to NaN.

    The vehicle sends to ``vehicle_port`` (bound here); the relay forwards each datagram, rewritten
    or not, to the companion at ``companion_port`` from one socket, and the companion's replies back.
    """

    def __init__(self, vehicle_port: int, companion_port: int) -> None:
        self.vehicle_side = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.vehicle_side.bind(("127.0.0.1", vehicle_port))
        self.companion_side = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.companion_side.bind(("127.0.0.1", 0))
        self.companion = ("127.0.0.1", companion_port)
        self.vehicle: tuple[str, int] | None = None
        self.corrupt = threading.Event()
        self.first_corrupted_t: float | None = None  # UNIX time
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _rewrite(self, data: bytes) -> bytes:
        parser = mavlink.MAVLink(None)
        msgs = parser.parse_buffer(data) or []
        out = b""
        for msg in msgs:
            if msg.get_type() == "ODOMETRY":
                msg.pitchspeed = msg.yawspeed = math.nan
                out += msg.pack(mavlink.MAVLink(None, msg.get_srcSystem(), msg.get_srcComponent()))
                if self.first_corrupted_t is None:
                    self.first_corrupted_t = time.time()
            else:
                out += bytes(msg.get_msgbuf())
        return out

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.vehicle_side, self.companion_side], [], [], 0.05)
            for sock in ready:
                data, addr = sock.recvfrom(65535)
                if sock is self.vehicle_side:
                    self.vehicle = addr
                    if self.corrupt.is_set():
                        data = self._rewrite(data)
                    self.companion_side.sendto(data, self.companion)
                elif self.vehicle is not None:
                    self.vehicle_side.sendto(data, self.vehicle)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.vehicle_side.close()
        self.companion_side.close()


def test_nan_body_rates_in_odometry_hold_within_two_periods_with_the_odometry_reason(tmp_path):
    T = CONTROL_PERIOD_S
    with Processes(tmp_path) as procs:
        rig = Rig(procs, tmp_path)
        companion_port = free_udp_ports(1)[0]
        relay = _OdometryCorruptingRelay(rig.mav_port, companion_port)
        try:
            policy = make_policy(tmp_path / "policy.pt")
            rig.start_vehicle("--airborne", "--start", "0,0,-3", gcs=False)
            rig.mav_port = companion_port  # the companion listens behind the relay
            rig.start_companion(policy, "--goal", "500,0,-3", "--arm", "--takeoff", "3", "--timeout", "60")
            rig.wait_flying(60)
            relay.corrupt.set()
            deadline = time.monotonic() + 2.0
            while relay.first_corrupted_t is None and time.monotonic() < deadline:
                time.sleep(0.01)
            t_fault = relay.first_corrupted_t
            assert t_fault is not None
            reason = "odometry invalid: ODOMETRY holds non-finite angular rates"
            hold = rig.wait_for_event(lambda r: r.get("kind") == "step" and r["t"] >= t_fault
                                      and r.get("hold") == reason, 3.0, "a hold for the NaN body rates")
            assert hold["sent"] and hold["cmd"] == [0.0, 0.0, 0.0] and hold["phase"] == "flying_to_goal"
            assert hold["t"] - t_fault <= 2 * T, f"hold {hold['t'] - t_fault:.3f} s after the fault"
            print(f"hold {hold['t'] - t_fault:.3f} s = {(hold['t'] - t_fault) / T:.2f} control periods "
                  "after the first NaN-rate ODOMETRY")
            time.sleep(1.5)  # it stays held for the same reason: no flapping, no blame on the policy
            relay.corrupt.clear()
            t_clear = time.time()
            rig.wait_for_event(lambda r: r.get("kind") == "step" and r["t"] > t_clear + 0.3 and not r.get("hold")
                               and (r.get("cmd") or [0])[0] > 0.1, 3.0, "policy steps after the rates are sane again")
            records = rig.companion_records()
        finally:
            relay.close()
    during = [r for r in records if r.get("kind") == "step" and hold["t"] <= r["t"] < t_clear]
    assert len(during) >= 10 and all(r.get("hold") == reason and r["cmd"] == [0.0, 0.0, 0.0] for r in during)
    failsafes = [r for r in records if r.get("event") == "failsafe" and t_fault <= r["t"] < t_clear]
    assert len(failsafes) == 1 and failsafes[0]["reason"] == reason


def test_over_tcp_the_stream_parser_stays_and_replays_from_another_link_id_are_ignored():
    """A byte stream (ArduPilot's tcp:) keeps pymavlink's parser, with the same lock and signature check."""
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    link = AutopilotLink(f"tcp:127.0.0.1:{server.getsockname()[1]}", signing_key=KEY)
    link.open()
    conn, _ = server.accept()
    try:
        ap = _codec(conn, None, key=KEY, link_id=1)
        ap.file.write = conn.sendall  # a stream: no address
        captured = []
        gcs_side = _codec(conn, None, key=KEY, link_id=2)
        gcs_side.file.write = captured.append  # what the autopilot sent its ground station (not sent here)
        gcs_side.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                                mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, PX4_POSCTL, mavlink.MAV_STATE_STANDBY)
        ap.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                          mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_SAFETY_ARMED,
                          PX4_OFFBOARD, mavlink.MAV_STATE_ACTIVE)
        assert link.wait_for_autopilot(3.0).custom_mode == PX4_OFFBOARD
        forger = _codec(conn, None, key=WRONG_KEY, link_id=1, timestamp=2**48 - 100)
        forger.file.write = conn.sendall
        forger.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, PX4_POSCTL, 0)
        conn.sendall(captured[0])  # the replay
        _pump(link, lambda: _dropped(link)[1] >= 1 or link.heartbeat.custom_mode != PX4_OFFBOARD, 1.0)
        assert link.heartbeat.custom_mode == PX4_OFFBOARD and _dropped(link)[1] == 1
        ap.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, PX4_OFFBOARD | 1, 0)
        assert _pump(link, lambda: link.heartbeat.custom_mode == PX4_OFFBOARD | 1, 1.0)  # still heard after the forgery
    finally:
        link.close()
        conn.close()
        server.close()
