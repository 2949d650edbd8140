"""Fuzz a running companion: malformed MAVLink, hostile depth frames, forged/replayed signed traffic, bad models.

Starts the real ``python -m companion.cli`` flying a real ``python -m sitl.vehicle --n 1``
(``--arm --takeoff 3 --goal 200,0,-3``, ``models/policy.pt``, ``--camera sitl:PORT``), all on
127.0.0.1, and puts itself between them as a transparent UDP proxy: the vehicle sends to the
proxy, the proxy forwards every datagram unchanged from its own socket, so *the proxy's
address is the companion's autopilot*. On the way back it decodes every
SET_POSITION_TARGET_LOCAL_NED the companion sends and checks it against
:class:`companion.spec.ActionSpec` (forward 0..2 m/s, down +-0.5 m/s, yaw rate +-0.5 rad/s)
and for finiteness: measured on the wire, not from logs.

Once the companion is in ``flying_to_goal`` (read from its JSON-lines ``--log``) the phases
run, each injecting at ``--rate`` inputs/s (bounded by ``--inputs`` and ``--seconds``):

1. ``mavlink``: malformed and hostile MAVLink toward the companion's MAVLink port, from the
   autopilot's own address (the proxy's socket) and from foreign loopback sockets
   (:class:`fuzz_inputs.MavlinkFuzzer`);
2. ``signing`` (``--signing``: vehicle and companion share a key): frames signed with a
   wrong key (incl. timestamp 2^48-100), replays of the vehicle's signed frames from its
   onboard link (link id 1) and from its ground-station link captured before takeoff (link
   id 2), unsigned frames (:class:`fuzz_inputs.SigningFuzzer`);
3. ``depth``: hostile datagrams to the companion's depth port (:class:`fuzz_inputs.DepthFuzzer`),
   then short probes of one kind each (all-zero, all-negative, another vehicle's, stale);
4. ``model``: mutated copies of models/policy.pt's ``policy.json``, each run as
   ``companion --model X``: expected exit 3 with a one-line reason, never a traceback.

After the mavlink and signing phases the harness waits the link timeout (2 s) + 0.5 s, so a
link loss they caused is counted. If the companion is not flying when a phase starts (it
lost the link, handed back or died), a fresh vehicle + companion pair is started for it.

The last line of output is one JSON object: ``inputs_sent`` / ``inputs_by_phase`` /
``inputs_by_kind``, ``rate_inputs_per_s``, ``crashes`` (companion exited or a traceback on its
stderr), ``setpoints_checked`` / ``setpoints_out_of_bounds`` / ``setpoints_non_finite`` (on the
wire), ``link_drops`` (``link_lost`` while or up to 2.5 s after fuzzing), ``holds_by_phase``
(hold episodes and steps by reason), ``mavlink_phase_hold_findings``, ``goals_accepted_by_phase``,
``depth_steps_flown_on_refusable_frames`` (policy steps flown on a blinded, dead, stale or
foreign frame, told by its ``seq``), ``depth_probes``, ``replies_to_foreign_senders``,
``signing_behaviour_changes`` (``--signing``), ``models``, ``rig_restarts`` and ``findings``.
Targets (issue 16) at 100,000 inputs: 0 crashes, 0 setpoints out of bounds, 0 non-finite
setpoints, 0 link drops from malformed/unauthenticated input; with ``--signing`` 0 behaviour
changes from forged/replayed traffic. ``findings`` lists every miss; the exit status is 0
without findings, 1 with, 3 when the harness itself could not run.

Usage::

    python benchmarks/fuzz_companion.py [--inputs N] [--seconds S] [--signing] [--smoke] [--seed K]
"""

from __future__ import annotations

import argparse
import errno
import json
import math
import os
import random
import select
import socket
import sys
import tempfile
import threading
import time
from collections import Counter, deque
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import fuzz_inputs as fi  # noqa: E402
from fuzz_inputs import mavlink  # noqa: E402

from companion.spec import ActionSpec  # noqa: E402
from sitl.cli_args import int_range, positive_float, positive_int  # noqa: E402
from tests.companion_helpers import Processes, free_udp_ports, read_jsonl  # noqa: E402

MODEL = REPO / "models" / "policy.pt"
GOAL = "200,0,-3"
TAKEOFF_M = "3"
LINK_TIMEOUT_S = 2.0  # the companion's default --link-timeout
SETTLE_AFTER_MAVLINK_S = LINK_TIMEOUT_S + 0.5  # a link loss shows up to link_timeout after the last input
SETTLE_AFTER_DEPTH_S = 0.5
SETTLE_AFTER_PROBE_S = 0.3
PROBE_KINDS = ("all_zero", "all_negative", "wrong_vehicle", "stale_stamp")
PROBE_S = 0.4
PROBE_HZ = 200.0
FOREIGN_SOCKETS = 16
MODELS_DURING_STARTUP = 4  # up to this many hostile model runs overlap the first start-up
#: Hold reasons the harness provokes on purpose from the autopilot's own ids (NaN/huge telemetry):
#: a hold that says so names the real source and is the right reaction, not a finding.
_TELEMETRY_WORDS = ("odometry", "telemetry", "attitude", "local_position", "position", "velocity")
_INVALID_WORDS = ("finite", "invalid", "range", "nan", "implausible", "bad", "rejected", "refused")
_STALE_WORDS = ("stale",)


def reason_kind(reason: str) -> str:
    """The hold's kind, as the companion groups it: its text before ' (' and ':'."""
    return reason.split(" (")[0].split(":")[0].strip()


# --------------------------------------------------------------------------- the wire check


class SetpointChecker:
    """Decodes companion->autopilot datagrams and checks every SET_POSITION_TARGET_LOCAL_NED.

    Each datagram is parsed on its own (a UDP datagram carries whole frames) by a parser
    without a signing key, so signed setpoints are read too.
    """

    def __init__(self, spec: ActionSpec, tol: float = 1e-5) -> None:
        self.low, self.high, self.tol = spec.low, spec.high, tol
        self.names = spec.names
        self.checked = 0
        self.out_of_bounds = 0
        self.non_finite = 0
        self.unexpected_format = 0
        self.datagrams = 0
        self.examples: list[dict] = []
        self.max_abs = [0.0, 0.0, 0.0]
        self.lock = threading.Lock()

    def check(self, data: bytes) -> None:
        self.datagrams += 1
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        try:
            msgs = parser.parse_buffer(data) or []
        except Exception:  # noqa: BLE001 - a datagram the companion sent that we cannot parse: not a setpoint
            return
        for msg in msgs:
            if msg.get_type() == "SET_POSITION_TARGET_LOCAL_NED":
                self._check(msg)

    def _example(self, what: str, msg) -> None:
        if len(self.examples) < 10:
            self.examples.append({"problem": what, "frame": msg.coordinate_frame, "type_mask": msg.type_mask,
                                  "vx": msg.vx, "vy": msg.vy, "vz": msg.vz, "yaw_rate": msg.yaw_rate})

    def _check(self, msg) -> None:
        with self.lock:
            self.checked += 1
            if msg.coordinate_frame != 8 or msg.type_mask != 1479:
                self.unexpected_format += 1
                self._example("frame/type_mask", msg)
            values = (msg.vx, msg.vz, msg.yaw_rate)
            if not all(math.isfinite(v) for v in (*values, msg.vy)):
                self.non_finite += 1
                self._example("non-finite", msg)
                return
            for i, v in enumerate(values):
                self.max_abs[i] = max(self.max_abs[i], abs(v))
            outside = [v < lo - self.tol or v > hi + self.tol for v, lo, hi in zip(values, self.low, self.high)]
            if any(outside) or abs(msg.vy) > self.tol:
                self.out_of_bounds += 1
                self._example("out of bounds", msg)


# --------------------------------------------------------------------------- the proxy


class Proxy:
    """A transparent loopback UDP proxy between the vehicle and the companion's MAVLink port.

    ``autopilot_sock`` is what the companion knows as its autopilot: everything the vehicle
    sends leaves from it, and the harness injects "from the autopilot" through it too.
    It also listens on the vehicle's ground-station port and keeps the first HEARTBEATs sent
    there (before the companion engages: not OFFBOARD) for replay.
    """

    def __init__(self, vehicle_port: int, companion_port: int, gcs_port: int, checker: SetpointChecker) -> None:
        self.vehicle_sock = self._bind(vehicle_port)
        self.autopilot_sock = self._bind(0)
        self.gcs_sock = self._bind(gcs_port)
        self.companion_addr = ("127.0.0.1", companion_port)
        self.checker = checker
        self.vehicle_addr: tuple[str, int] | None = None
        self.onboard_frames: deque[bytes] = deque(maxlen=256)
        self.gcs_frames: list[bytes] = []
        # Only HEARTBEATs from before the companion engages (the vehicle not in OFFBOARD): a later,
        # OFFBOARD one replayed first would make every older one "old" to the signing check.
        self.capture_gcs = True
        self.forwarded = Counter()
        # Issue 16 item 1's attack, timed by the proxy (it alone sees the real frames go by): while
        # ``prefix_rng`` is set, a bare start byte + length goes out just before every real
        # HEARTBEAT and before 1 in 10 other datagrams. Counted in ``prefixes``.
        self.prefix_rng: random.Random | None = None
        self.prefixes = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fuzz-proxy", daemon=True)

    @staticmethod
    def _bind(port: int) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", port))
        sock.setblocking(False)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        return sock

    def start(self) -> None:
        self._thread.start()

    def onboard(self) -> list[bytes]:
        return list(self.onboard_frames)

    def gcs(self) -> list[bytes]:
        return list(self.gcs_frames)

    def _drain(self, sock: socket.socket):
        while True:
            try:
                yield sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return

    def _run(self) -> None:
        socks = [self.vehicle_sock, self.autopilot_sock, self.gcs_sock]
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select(socks, [], [], 0.1)
            except (OSError, ValueError):
                return
            for sock in ready:
                for data, addr in self._drain(sock):
                    try:
                        self._route(sock, data, addr)
                    except OSError:
                        pass

    def _route(self, sock: socket.socket, data: bytes, addr) -> None:
        if sock is self.vehicle_sock:  # vehicle -> companion
            self.vehicle_addr = addr
            rng = self.prefix_rng
            if rng is not None and (_is_heartbeat(data) or rng.random() < 0.1):
                self.autopilot_sock.sendto(rng.choice((b"\xfd\xff", b"\xfe\xff", b"\xfd", data[:5])), self.companion_addr)
                self.prefixes += 1
            self.autopilot_sock.sendto(data, self.companion_addr)
            self.forwarded["to_companion"] += 1
            self.onboard_frames.append(data)
        elif sock is self.autopilot_sock:  # companion -> vehicle
            if addr != self.companion_addr:
                return
            self.checker.check(data)
            if self.vehicle_addr is not None:
                self.vehicle_sock.sendto(data, self.vehicle_addr)
                self.forwarded["to_vehicle"] += 1
        elif self.capture_gcs and len(self.gcs_frames) < 16 and _is_heartbeat(data) and data[5:7] == b"\x01\x01":
            self.gcs_frames.append(data)  # the autopilot's own (1/1), not the companion's the vehicle routes there

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2)
        for sock in (self.vehicle_sock, self.autopilot_sock, self.gcs_sock):
            sock.close()


def _is_heartbeat(data: bytes) -> bool:
    """Whether a datagram starts with a MAVLink 1 or 2 HEARTBEAT (message id 0)."""
    if len(data) >= 10 and data[0] == 0xFD:
        return data[7] == data[8] == data[9] == 0
    return len(data) >= 6 and data[0] == 0xFE and data[5] == 0


# --------------------------------------------------------------------------- the companion's log


class CompanionLog:
    """Reads the companion's JSON-lines log as it grows."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.pos = 0
        self.partial = b""
        self.records: list[dict] = []
        self.phase: str | None = None

    def poll(self) -> None:
        try:
            with open(self.path, "rb") as f:
                f.seek(self.pos)
                chunk = f.read()
        except FileNotFoundError:
            return
        self.pos += len(chunk)
        lines = (self.partial + chunk).split(b"\n")
        self.partial = lines.pop()
        for line in lines:
            try:
                record = json.loads(line)
            except (json.JSONDecodeError, UnicodeDecodeError):
                continue
            self.records.append(record)
            if record.get("kind") == "event" and record.get("event") == "phase" and record.get("to"):
                self.phase = record["to"]

    def between(self, t0_mono: float, t1_mono: float) -> list[dict]:
        return [r for r in self.records if t0_mono <= r.get("mono", -1.0) < t1_mono]


# --------------------------------------------------------------------------- vehicle + companion


class Rig:
    """One ``sitl.vehicle --n 1`` and its companion, talking through a :class:`Proxy`."""

    def __init__(self, procs: Processes, workdir: Path, checker: SetpointChecker, key_file: Path | None,
                 duration_s: float) -> None:
        self.procs, self.workdir = procs, workdir
        for attempt in range(5):
            self.vehicle_port, self.companion_port, self.depth_port, self.gcs_port = free_udp_ports(4)
            try:
                self.proxy = Proxy(self.vehicle_port, self.companion_port, self.gcs_port, checker)
                break
            except OSError as err:  # a port probed free was taken before the bind (another process's late start)
                if err.errno != errno.EADDRINUSE or attempt == 4:
                    raise
        self.proxy.start()
        self.log = CompanionLog(workdir / "companion.jsonl")
        self.vehicle_log = workdir / "vehicle.jsonl"
        signing = ["--signing-key", str(key_file)] if key_file else []
        self.companion = procs.start("companion", [
            "-m", "companion.cli", "--connect", f"udpin:127.0.0.1:{self.companion_port}", "--model", str(MODEL),
            "--camera", f"sitl:{self.depth_port}", "--arm", "--takeoff", TAKEOFF_M, "--goal", GOAL,
            "--log", str(self.log.path), "--heartbeat-timeout", "30", *signing])
        self.vehicle = procs.start("vehicle", [
            "-m", "sitl.vehicle", "--n", "1", "--base-port", str(self.vehicle_port), "--depth-port", str(self.depth_port),
            "--gcs-port", str(self.gcs_port), "--log", str(self.vehicle_log), "--duration", f"{duration_s:.0f}",
            "--airborne", "--start", "0,0,-3", *signing])  # hovering: the companion engages without a 6 s climb
        self.started_s = time.monotonic()
        self.flying_after_s: float | None = None
        self.stopped_on_purpose = False
        self.exit_recorded = False  # an unexpected companion exit is counted once

    def wait_flying(self, timeout_s: float) -> None:
        """Until the policy flies (phase flying_to_goal and a step sent forward); raise on failure."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.log.poll()
            if self.log.phase == "flying_to_goal" and any(
                    r.get("kind") == "step" and r.get("phase") == "flying_to_goal" and r.get("sent")
                    and not r.get("hold") and (r.get("cmd") or [0])[0] > 0.3 for r in self.log.records[-20:]):
                self.flying_after_s = round(time.monotonic() - self.started_s, 2)
                self.proxy.capture_gcs = False
                return
            if self.companion.poll() is not None or self.vehicle.poll() is not None:
                break
            time.sleep(0.1)
        raise RuntimeError(f"the companion did not start flying within {timeout_s:g} s (phase {self.log.phase}); "
                           f"companion stderr: {self.stderr_tail('companion')!r}")

    def flying(self) -> bool:
        self.log.poll()
        return self.companion.poll() is None and self.vehicle.poll() is None and self.log.phase == "flying_to_goal"

    def stderr_tail(self, name: str, chars: int = 400) -> str:
        return self.procs.stderr(name)[-chars:]

    def vehicle_overruns(self, t0_wall: float, t1_wall: float) -> int:
        return sum(1 for r in read_jsonl(self.vehicle_log) if r.get("event") == "overrun" and t0_wall <= r.get("t", 0) < t1_wall)

    def stop(self) -> None:
        self.stopped_on_purpose = True
        self.procs.stop_all()
        self.proxy.stop()
        self.log.poll()


# --------------------------------------------------------------------------- the harness


class Fuzzer:
    """Runs the phases and collects what the report needs."""

    def __init__(self, args: argparse.Namespace, workdir: Path) -> None:
        self.args, self.workdir = args, workdir
        self.rng = random.Random(args.seed)
        self.spec = ActionSpec()
        self.checker = SetpointChecker(self.spec)
        self.inputs = Counter()  # "phase/kind" -> count
        self.send_errors = 0
        self.rigs: list[Rig] = []
        self.rig: Rig | None = None
        self.windows: list[dict] = []  # one per phase: name, mono/wall start and end (with settle), rig
        self.crashes: list[dict] = []
        self.restarts: list[str] = []
        self.refusable_seqs: dict[int, str] = {}
        self.probes: dict[str, dict] = {}
        self.foreign = [self._foreign_socket() for _ in range(FOREIGN_SOCKETS)]
        self.foreign_replies = Counter()  # datagrams the companion sent to foreign senders, by socket index
        self.injected_s = Counter()  # phase -> seconds spent injecting
        self.before_injection = None  # called once before the first input (the smoke run's model phase joins)
        self.vehicle_duration_s = 120.0 + args.seconds * 1.5
        self.key_file: Path | None = None
        if args.signing:
            self.key_file = workdir / "signing.key"
            self.key_file.write_text(os.urandom(32).hex() + "\n")

    @staticmethod
    def _foreign_socket() -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", 0))
        sock.setblocking(False)
        return sock

    # ------------------------------------------------------------------ rigs
    def _new_rig(self, why: str) -> Rig:
        if self.rig is not None:
            self._retire_rig()
        if why:
            self.restarts.append(why)
        folder = self.workdir / f"rig{len(self.rigs)}"
        folder.mkdir()
        rig = Rig(Processes(folder), folder, self.checker, self.key_file, self.vehicle_duration_s)
        self.rigs.append(rig)
        self.rig = rig
        rig.wait_flying(self.args.start_timeout)
        return rig

    def _retire_rig(self) -> None:
        rig = self.rig
        self._check_alive(rig)
        rig.stop()
        for name in ("companion", "vehicle"):
            if "Traceback (most recent call last)" in rig.procs.stderr(name):
                tail = rig.procs.stderr(name).strip().splitlines()[-1:]
                self.crashes.append({"process": name, "rig": self.rigs.index(rig), "what": "traceback on stderr",
                                     "last_line": tail[0] if tail else ""})
        self.rig = None

    def _check_alive(self, rig: Rig) -> None:
        """Record an unexpected exit of the companion (once per rig)."""
        if rig.stopped_on_purpose or rig.exit_recorded:
            return
        code = rig.companion.poll()
        if code is not None:
            rig.exit_recorded = True
            tail = rig.stderr_tail("companion").strip().splitlines()[-1:]
            self.crashes.append({"process": "companion", "rig": self.rigs.index(rig), "what": f"exited {code}",
                                 "last_line": tail[0] if tail else ""})

    def _ensure_flying(self, phase: str) -> None:
        if self.rig is None:
            self._new_rig("")
        elif not self.rig.flying():
            self._check_alive(self.rig)
            state = "exited" if self.rig.companion.poll() is not None else self.rig.log.phase
            self._new_rig(f"before {phase}: companion {state}")

    # ------------------------------------------------------------------ injection
    def _housekeeping(self) -> None:
        self.rig.log.poll()
        self._check_alive(self.rig)
        for i, sock in enumerate(self.foreign):
            while True:
                try:
                    sock.recv(65535)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:  # ICMP errors from earlier sends: nothing to read
                    break
                self.foreign_replies[i] += 1

    def _inject(self, phase: str, count: int, budget_s: float, generator, port: int, progress) -> int:
        """Send ``count`` inputs from ``generator`` to ``port`` at ``--rate``; return how many were sent."""
        if self.before_injection is not None:
            self.before_injection()
            self.before_injection = None
        interval = 1.0 / self.args.rate
        target = ("127.0.0.1", port)
        started = last_house = time.monotonic()
        sent = 0
        while sent < count:
            now = time.monotonic()
            if now - started > budget_s:
                break
            ahead = started + sent * interval - now
            if ahead > 0:
                time.sleep(ahead)
            if now - last_house > 0.1:
                self._housekeeping()
                last_house = now
            batch = min(16, count - sent)
            for _ in range(batch):
                self._send(phase, generator.next(), target)
            sent += batch
            if progress is not None:
                progress.update(batch)
        self.injected_s[phase] += time.monotonic() - started
        return sent

    def _send(self, phase: str, dg: fi.Datagram, target) -> None:
        sock = self.rig.proxy.autopilot_sock if dg.sender == "autopilot" else self.rng.choice(self.foreign)
        try:
            sock.sendto(dg.data, target)
        except OSError:
            self.send_errors += 1
        self.inputs[f"{phase}/{dg.kind}"] += 1

    def _window(self, name: str, t0_mono: float, t0_wall: float, settle_s: float) -> dict:
        end_mono = time.monotonic()
        time.sleep(settle_s)
        self.rig.log.poll()
        window = {"name": name, "t0": t0_mono, "t1": end_mono, "t_settled": time.monotonic(), "wall0": t0_wall,
                  "wall1": time.time(), "rig": self.rig}
        self.windows.append(window)
        return window

    # ------------------------------------------------------------------ phases
    def run_flight_phases(self, counts: dict[str, int], budgets: dict[str, float], progress) -> None:
        only = self.args.kinds
        onboard = lambda: self.rig.proxy.onboard()  # noqa: E731 - the current rig's captures
        gcs = lambda: self.rig.proxy.gcs()  # noqa: E731
        generators = {
            "mavlink": fi.MavlinkFuzzer(self.rng, onboard),
            "signing": fi.SigningFuzzer(self.rng, onboard, gcs),
            "depth": _TaggingDepthFuzzer(fi.DepthFuzzer(self.rng, 32, 32, 90.0, 20.0), self.refusable_seqs),
        }
        for phase, gen in generators.items():
            prefix = phase == "mavlink" and (only is None or "start_before_real_frame" in only)
            if counts.get(phase, 0) <= 0 or not (gen.restrict(only) or prefix):
                continue
            self._ensure_flying(phase)
            if not self.args.smoke:
                print(f"fuzz: phase {phase}: {counts[phase]} inputs at {self.args.rate:g}/s", file=sys.stderr)
            t0, w0 = time.monotonic(), time.time()
            if phase == "mavlink":
                proxy = self.rig.proxy
                proxy.prefix_rng = random.Random(self.rng.getrandbits(32)) if prefix else None
                try:
                    if gen.restrict(only):
                        self._inject(phase, counts[phase], budgets[phase], gen, self.rig.companion_port, progress)
                    else:  # only the proxy's prefixes: let them run as long as the phase would
                        time.sleep(min(budgets[phase], counts[phase] / self.args.rate))
                finally:
                    proxy.prefix_rng = None
                self.inputs[f"{phase}/start_before_real_frame"] += proxy.prefixes
                self._window(phase, t0, w0, SETTLE_AFTER_MAVLINK_S)
            elif phase == "signing":
                self._inject(phase, counts[phase], budgets[phase], gen, self.rig.companion_port, progress)
                self._window(phase, t0, w0, SETTLE_AFTER_MAVLINK_S)
            else:
                self._inject(phase, counts[phase], budgets[phase], gen, self.rig.depth_port, progress)
                self._window(phase, t0, w0, SETTLE_AFTER_DEPTH_S)
                self._depth_probes(gen)
        if self.rig is not None:
            self._retire_rig()

    def _depth_probes(self, gen: _TaggingDepthFuzzer) -> None:
        """Short bursts of one refusable kind each, faster than the camera, so they are what the policy sees."""
        for kind in PROBE_KINDS:
            if self.args.kinds is not None and kind not in self.args.kinds:
                continue
            self._ensure_flying(f"probe {kind}")
            t0, w0 = time.monotonic(), time.time()
            probe = _OneKind(gen, kind)
            self._inject("probe", int(PROBE_S * PROBE_HZ), PROBE_S * 3, _Paced(probe, PROBE_HZ), self.rig.depth_port, None)
            window = self._window(f"probe:{kind}", t0, w0, SETTLE_AFTER_PROBE_S)
            self.probes[kind] = self._probe_result(window)

    def _probe_result(self, window: dict) -> dict:
        steps = [r for r in window["rig"].log.between(window["t0"], window["t_settled"])
                 if r.get("kind") == "step" and r.get("phase") == "flying_to_goal"]
        flown = [r for r in steps if _flown(r) and r.get("frame_seq") in self.refusable_seqs]
        holds = Counter(reason_kind(r["hold"]) for r in steps if r.get("hold"))
        return {"steps": len(steps), "steps_flown_on_probe_frames": len(flown), "hold_steps": sum(holds.values()),
                "hold_reasons": dict(holds)}

    # ------------------------------------------------------------------ the model phase
    def run_model_phase(self, count: int) -> dict:
        """Run ``companion --model X`` on ``count`` mutated copies of models/policy.pt (own random stream)."""
        import warnings

        import torch

        from companion.policy import METADATA_FILE

        extra = {METADATA_FILE: ""}
        with warnings.catch_warnings():  # TorchScript is deprecated in torch >= 2.9 but is the policy format
            warnings.simplefilter("ignore", DeprecationWarning)
            module = torch.jit.load(str(MODEL), map_location="cpu", _extra_files=extra)
        meta = json.loads(extra[METADATA_FILE])
        folder = self.workdir / "models"
        folder.mkdir()
        results = []
        exit_codes, tracebacks = Counter(), 0
        for i, (name, path, value) in enumerate(fi.model_mutations(random.Random(self.args.seed + 1), count)):
            mutant = fi.mutate_metadata(meta, path, value)
            file = folder / f"mutant{i}.pt"
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", DeprecationWarning)
                torch.jit.save(module, str(file), _extra_files={METADATA_FILE: json.dumps(mutant)})
            code, stderr = self._run_companion_on(file, folder / f"mutant{i}")
            traceback = "Traceback (most recent call last)" in stderr
            tracebacks += traceback
            exit_codes[str(code)] += 1
            self.inputs[f"model/{name.split(':')[0]}"] += 1
            last = stderr.strip().splitlines()[-1] if stderr.strip() else ""
            results.append({"mutation": name, "exit": code, "traceback": traceback, "last_line": last[:200]})
        # Refused = exit 3, no traceback, and the last line is the companion's own one-line reason.
        not_refused = [r for r in results if r["exit"] != 3 or r["traceback"] or not r["last_line"].startswith("companion:")]
        return {"mutants": len(results), "exit_codes": dict(exit_codes), "tracebacks": tracebacks,
                "refused_with_exit_3": len(results) - len(not_refused), "not_refused": not_refused}

    def _run_companion_on(self, model: Path, stem: Path) -> tuple[int | None, str]:
        """``companion --model X`` with nothing to talk to: a good model ends in exit 5 (no heartbeat)."""
        mav_port, depth_port = free_udp_ports(2)
        procs = Processes(stem.parent)
        name = stem.name
        proc = procs.start(name, ["-m", "companion.cli", "--connect", f"udpin:127.0.0.1:{mav_port}", "--model",
                                  str(model), "--camera", f"sitl:{depth_port}", "--heartbeat-timeout", "1",
                                  "--log", str(stem) + ".jsonl"])
        try:
            code = proc.wait(timeout=self.args.model_timeout)
        except Exception:  # noqa: BLE001 - subprocess.TimeoutExpired: a companion that hangs on a bad model
            code = None
        finally:
            procs.stop_all()
        return code, procs.stderr(name)

    # ------------------------------------------------------------------ the report
    def report(self, wall_s: float, models: dict | None, error: str | None = None) -> dict:
        by_phase: dict[str, dict] = {}
        link_drops = Counter()
        goals_accepted = Counter()
        mavlink_hold_findings: list[str] = []
        behaviour_changes = Counter()
        flown_on_refusable = Counter()
        for w in self.windows:
            name = w["name"].split(":")[0]
            records = w["rig"].log.between(w["t0"], w["t_settled"])
            holds = by_phase.setdefault(name, {"hold_episodes": 0, "by_reason": Counter(), "hold_steps": 0,
                                               "steps": 0, "examples": {}})
            overruns = w["rig"].vehicle_overruns(w["wall0"], w["wall1"])
            for r in records:
                if r.get("kind") == "step" and r.get("phase") == "flying_to_goal":
                    holds["steps"] += 1
                    holds["hold_steps"] += bool(r.get("hold"))
                    if name in ("depth", "probe") and _flown(r) and r.get("frame_seq") in self.refusable_seqs:
                        flown_on_refusable[self.refusable_seqs[r["frame_seq"]]] += 1
                if r.get("kind") != "event":
                    continue
                event = r.get("event")
                if event == "failsafe" and r.get("reason"):
                    kind = reason_kind(r["reason"])
                    holds["hold_episodes"] += 1
                    holds["by_reason"][kind] += 1
                    holds["examples"].setdefault(kind, r["reason"][:160])
                    if name == "mavlink" and not _excused_mavlink_hold(r["reason"], overruns):
                        mavlink_hold_findings.append(r["reason"][:160])
                    if name == "signing":
                        behaviour_changes["hold"] += 1
                if event == "phase" and r.get("to") == "link_lost":
                    link_drops[name] += 1
                if event == "goal" and r.get("goal_ned") is not None:
                    goals_accepted[name] += 1
                if name == "signing":
                    if event == "phase":
                        behaviour_changes[f"phase:{r.get('to')}"] += 1
                    elif event == "mode":
                        behaviour_changes["mode"] += 1
                    elif event == "goal" and r.get("goal_ned") is not None:
                        behaviour_changes["goal"] += 1
        for holds in by_phase.values():
            holds["by_reason"] = dict(holds["by_reason"])

        kinds = Counter()
        phases = Counter()
        for key, n in self.inputs.items():
            phase, kind = key.split("/", 1)
            kinds[kind] += n
            phases[phase] += n
        fuzz_s = sum(t for p, t in self.injected_s.items() if p != "probe")  # probes run at PROBE_HZ by design
        fuzz_inputs = sum(n for p, n in phases.items() if p not in ("model", "probe"))
        c = self.checker
        report = {
            "ok": False,
            "findings": [],
            "seed": self.args.seed, "smoke": self.args.smoke, "signing": self.args.signing,
            "inputs_sent": sum(self.inputs.values()),
            "inputs_by_phase": dict(phases),
            "inputs_by_kind": dict(sorted(kinds.items())),
            "rate_inputs_per_s": round(fuzz_inputs / fuzz_s, 1) if fuzz_s else 0.0,
            "target_rate_inputs_per_s": self.args.rate,
            "injection_s_by_phase": {p: round(t, 2) for p, t in self.injected_s.items()},
            "rig_start_to_flying_s": [r.flying_after_s for r in self.rigs],
            "wall_s": round(wall_s, 1),
            "crashes": len(self.crashes),
            "crash_details": self.crashes,
            "setpoints_checked": c.checked,
            "setpoints_out_of_bounds": c.out_of_bounds,
            "setpoints_non_finite": c.non_finite,
            "setpoints_unexpected_format": c.unexpected_format,
            "setpoint_max_abs": dict(zip(c.names, (round(v, 4) for v in c.max_abs))),
            "setpoint_examples": c.examples,
            "link_drops": sum(link_drops.values()),
            "link_drops_by_phase": dict(link_drops),
            "holds_by_phase": by_phase,
            "mavlink_phase_hold_findings": mavlink_hold_findings,
            "goals_accepted_by_phase": dict(goals_accepted),
            "depth_steps_flown_on_refusable_frames": sum(flown_on_refusable.values()),
            "depth_flown_on_refusable_by_kind": dict(flown_on_refusable),
            "depth_probes": self.probes,
            "replies_to_foreign_senders": sum(self.foreign_replies.values()),
            "foreign_senders_answered": len(self.foreign_replies),
            "rig_restarts": self.restarts,
            "send_errors": self.send_errors,
            "workdir": str(self.workdir),
        }
        if self.args.signing:
            report["signing_behaviour_changes"] = sum(behaviour_changes.values())
            report["signing_behaviour_changes_by_kind"] = dict(behaviour_changes)
        if models is not None:
            report["models"] = models
        if error:
            report["error"] = error
        report["findings"] = findings(report)
        report["ok"] = not report["findings"] and not error
        return report


class _TaggingDepthFuzzer:
    """Wraps a :class:`fuzz_inputs.DepthFuzzer` and remembers which seq stands for which refusable kind."""

    def __init__(self, inner: fi.DepthFuzzer, seqs: dict[int, str]) -> None:
        self.inner, self.seqs = inner, seqs

    def restrict(self, only: set[str] | None) -> bool:
        return self.inner.restrict(only)

    def _tag(self, kind: str) -> None:
        if kind in fi.DepthFuzzer.REFUSABLE:
            self.seqs[fi.REFUSABLE_SEQ_BASE + self.inner.refusable_count] = kind

    def next(self) -> fi.Datagram:
        dg = self.inner.next()
        self._tag(dg.kind)
        return dg

    def make(self, kind: str) -> fi.Datagram:
        dg = fi.Datagram(kind, self.inner.make(kind), "foreign")
        self._tag(kind)
        return dg


class _OneKind:
    def __init__(self, gen: _TaggingDepthFuzzer, kind: str) -> None:
        self.gen, self.kind = gen, kind

    def next(self) -> fi.Datagram:
        return self.gen.make(self.kind)


class _Paced:
    """Marks a generator for the probe rate (the injection loop paces by ``--rate``; probes are slower)."""

    def __init__(self, gen, hz: float) -> None:
        self.gen, self.interval, self.next_s = gen, 1.0 / hz, 0.0

    def next(self) -> fi.Datagram:
        now = time.monotonic()
        if now < self.next_s:
            time.sleep(self.next_s - now)
        self.next_s = max(now, self.next_s) + self.interval
        return self.gen.next()


def _flown(step: dict) -> bool:
    """A step in which the policy's command went out (not a hold)."""
    return bool(step.get("sent")) and not step.get("hold") and step.get("policy") is not None


def _excused_mavlink_hold(reason: str, vehicle_overruns: int) -> bool:
    """Whether a hold during MAVLink fuzzing is the right reaction rather than a finding.

    The harness sends NaN/huge telemetry from the autopilot's own ids on purpose: a hold that
    names the telemetry as invalid is correct. A stale-input hold is excused only when the
    vehicle process itself logged that it fell behind real time (CPU starvation of the machine).
    """
    text = reason.lower()
    if any(w in text for w in _TELEMETRY_WORDS) and any(w in text for w in _INVALID_WORDS):
        return True
    return vehicle_overruns > 0 and any(w in text for w in _STALE_WORDS)


def findings(report: dict) -> list[str]:
    """Every target of issue 16 the run missed, one line each."""
    out = []
    if report["crashes"]:
        out.append(f"{report['crashes']} crash(es): {report['crash_details'][:3]}")
    if report["setpoints_out_of_bounds"]:
        out.append(f"{report['setpoints_out_of_bounds']} setpoint(s) outside the action bounds")
    if report["setpoints_non_finite"]:
        out.append(f"{report['setpoints_non_finite']} non-finite setpoint(s)")
    if report["link_drops"]:
        out.append(f"{report['link_drops']} link drop(s) caused by fuzzing: {report['link_drops_by_phase']}")
    if report["mavlink_phase_hold_findings"]:
        kinds = Counter(reason_kind(r) for r in report["mavlink_phase_hold_findings"])
        out.append(f"holds caused by malformed MAVLink: {dict(kinds)}")
    if report["goals_accepted_by_phase"].get("mavlink"):
        out.append(f"{report['goals_accepted_by_phase']['mavlink']} out-of-range goal(s) accepted")
    if report["depth_steps_flown_on_refusable_frames"]:
        out.append(f"{report['depth_steps_flown_on_refusable_frames']} step(s) flown on blinded/stale/foreign depth "
                   f"frames: {report['depth_flown_on_refusable_by_kind']}")
    if report["replies_to_foreign_senders"]:
        out.append(f"the companion sent {report['replies_to_foreign_senders']} datagram(s) to "
                   f"{report['foreign_senders_answered']} foreign sender(s) (not its autopilot)")
    if report.get("signing_behaviour_changes"):
        out.append(f"{report['signing_behaviour_changes']} behaviour change(s) from forged/replayed traffic: "
                   f"{report['signing_behaviour_changes_by_kind']}")
    models = report.get("models")
    if models and models["not_refused"]:
        out.append(f"{len(models['not_refused'])} hostile model file(s) not refused with exit 3: "
                   f"{[(m['mutation'], m['exit']) for m in models['not_refused']][:8]}")
    if models and models["tracebacks"]:
        out.append(f"{models['tracebacks']} traceback(s) on hostile model files")
    return out


# --------------------------------------------------------------------------- command line


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--inputs", type=positive_int, metavar="N",
                        help="MAVLink/signing/depth inputs in all (default 100000; 4000 with --smoke)")
    parser.add_argument("--seconds", type=positive_float, metavar="S",
                        help="most seconds of injection in all (default: 1.5 x inputs / rate + 5)")
    parser.add_argument("--rate", type=positive_float, metavar="HZ",
                        help="injection rate in inputs/s (default 2000, 800 with --smoke: robustness, not CPU starvation)")
    parser.add_argument("--models", type=int_range(0), metavar="M",
                        help="hostile model files to try (default 24; 3 with --smoke)")
    parser.add_argument("--signing", action="store_true", help="vehicle and companion sign; add forged/replayed traffic")
    parser.add_argument("--smoke", action="store_true",
                        help="a short run for CI: 4000 inputs at 800/s (the MAVLink phase lasts 3 s, longer than "
                             "the 2 s link timeout), 3 models")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--kinds", metavar="K1,K2", type=lambda t: set(filter(None, t.split(","))),
                        help="send only these input kinds (to reproduce one fault), e.g. replay_other_link")
    parser.add_argument("--start-timeout", type=positive_float, default=60.0, metavar="S",
                        help="most seconds for a vehicle + companion to start flying (default 60)")
    parser.add_argument("--model-timeout", type=positive_float, default=60.0, metavar="S",
                        help="most seconds for one companion run on a hostile model (default 60)")
    parser.add_argument("--workdir", metavar="DIR", help="keep logs and model files here (default: a temporary folder)")
    args = parser.parse_args(argv)
    if args.kinds is not None:
        known = fi.all_kinds() | {"start_before_real_frame"}
        unknown = sorted(args.kinds - known)
        if unknown or not args.kinds:
            parser.error(f"--kinds: unknown kind(s) {unknown}; known: {', '.join(sorted(known))}")
        if not args.signing and args.kinds <= fi.SIGNING_KINDS:
            parser.error("--kinds: these kinds need --signing")
    if args.inputs is None:
        args.inputs = 4000 if args.smoke else 100_000
    if args.rate is None:
        args.rate = 800.0 if args.smoke else 2000.0
    if args.models is None:
        args.models = 3 if args.smoke else 24
    if args.seconds is None:
        args.seconds = 1.5 * args.inputs / args.rate + 5.0
    return args


def split_inputs(total: int, seconds: float, signing: bool) -> tuple[dict[str, int], dict[str, float]]:
    """Inputs and seconds per flight phase: MAVLink gets the largest share."""
    shares = {"mavlink": 0.4, "signing": 0.3, "depth": 0.3} if signing else {"mavlink": 0.6, "depth": 0.4}
    counts = {p: max(1, int(round(total * s))) for p, s in shares.items()}
    return counts, {p: seconds * s for p, s in shares.items()}


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    started = time.monotonic()
    keep = args.workdir is not None
    workdir = Path(args.workdir) if keep else Path(tempfile.mkdtemp(prefix="fuzz_companion_"))
    workdir.mkdir(parents=True, exist_ok=True)
    fuzzer = Fuzzer(args, workdir)
    counts, budgets = split_inputs(args.inputs, args.seconds, args.signing)
    error = None
    models = None
    progress = None
    try:
        from tqdm import tqdm

        progress = tqdm(total=sum(counts.values()), desc="fuzz", unit="input", file=sys.stderr,
                        disable=args.smoke, mininterval=1.0 if sys.stderr.isatty() else 5.0)
    except ImportError:
        pass
    model_result: dict = {}
    model_thread = None
    if 0 < args.models <= MODELS_DURING_STARTUP:
        # A few model runs fit into the first vehicle + companion's start-up (mostly waiting);
        # injection waits for them, so their CPU load never overlaps the fuzzing.
        def run_models() -> None:
            try:
                model_result["models"] = fuzzer.run_model_phase(args.models)
            except Exception as err:  # noqa: BLE001 - reported as the harness's error below
                model_result["error"] = f"model phase failed: {type(err).__name__}: {err}"

        model_thread = threading.Thread(target=run_models, name="fuzz-models", daemon=True)
        model_thread.start()
        fuzzer.before_injection = model_thread.join
    try:
        fuzzer.run_flight_phases(counts, budgets, progress)
        if progress is not None:
            progress.close()
        if model_thread is not None:
            model_thread.join()
            models = model_result.get("models")
            if "error" in model_result:
                raise RuntimeError(model_result["error"])
        elif args.models:
            print(f"fuzz: {args.models} hostile model file(s)", file=sys.stderr)
            models = fuzzer.run_model_phase(args.models)
    except RuntimeError as err:
        error = str(err)
        print(f"fuzz_companion: error: {error}", file=sys.stderr)
    finally:
        if fuzzer.rig is not None:
            fuzzer._retire_rig()
        for sock in fuzzer.foreign:
            sock.close()
    report = fuzzer.report(time.monotonic() - started, models, error)
    if not keep and report["ok"]:
        import shutil

        shutil.rmtree(workdir, ignore_errors=True)
        report["workdir"] = None
    print(json.dumps(report, default=str))
    if error:
        return 3
    return 0 if report["ok"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
