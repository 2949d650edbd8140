"""Real ArduCopter and PX4 (SIH) SITL swarms with ``sitl.world`` and one ``companion`` each.

``python -m sitl.real_autopilots`` (docs/real_autopilots.md) and ``tests/test_real_autopilots.py``
use this module to start, on loopback only:

* N autopilot SITL instances, each at its own home on the ground, in its own working
  directory under the run's folder: ArduCopter ``arducopter -I i --home LAT,LON,ALT,0``
  (SERIAL0 on TCP 5760 + 10 i for the world, SERIAL1 5762 + 10 i for the companion, SERIAL2
  5763 + 10 i for this module's ground-station link) or PX4 with its built-in SIH simulator
  (``PX4_HOME_LAT``/``PX4_HOME_LON`` per instance; onboard UDP 14540 + i for the companion,
  ground-station link to UDP 14550 for the world, payload link 14280 + i <-> 14030 + i for
  this module);
* ``python -m sitl.world`` on their telemetry (``--trace``: every vehicle's world position,
  velocity, mode and armed state at 10 Hz, from which everything here is measured);
* one ``companion`` per vehicle (``--arm --takeoff``), sent its goal by this module acting as
  a ground station (SET_POSITION_TARGET_LOCAL_NED to component 191, which the autopilot routes
  to its companion), so that a circle of vehicles starts together.

Every child runs in its own session and gets SIGTERM when this process dies (Linux
``PR_SET_PDEATHSIG``); :meth:`RealSwarm.close` stops them all (SIGINT / SIGTERM, then SIGKILL).

Positions are the autopilots' estimates placed in the world frame (vehicle 0's local frame)
by the world: separate SITL instances cannot collide, so a "collision" is two vehicles closer
than twice the task's collision radius.
"""

from __future__ import annotations

import collections
import contextlib
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion.face_goal import DEFAULT_FACE_GOAL_S, add_face_goal_argument
from companion.flight_modes import (ARDUCOPTER_MODE_BY_NAME, PX4_MODE_BY_NAME)
from companion.runtime import FlightPhase
from companion.spec import CAMERA_PRESETS, DEFAULT_TASK_SPEC
from sitl.realtime.depth_bridge import ned_offset_m, shift_global
from sitl.realtime.mavlink_swarm import JsonLinesTail, ProcessGroup, _die_with_parent, companion_command

from pymavlink import mavutil  # noqa: E402  (after companion: MAVLink 2)

ARDUCOPTER, PX4 = "arducopter", "px4"
KINDS = (ARDUCOPTER, PX4)
#: Environment variables naming the SITL binaries, and where the build scripts put them.
BINARY_ENV = {ARDUCOPTER: "SWARMNAV_ARDUCOPTER", PX4: "SWARMNAV_PX4"}
DEFAULT_BINARY = {ARDUCOPTER: "/tmp/ardupilot/build/sitl/bin/arducopter",
                  PX4: "/tmp/px4/build/px4_sitl_nodds/bin/px4"}
BUILD_SCRIPT = {ARDUCOPTER: "tools/arducopter-sitl/build.sh", PX4: "tools/px4-sitl/build.sh"}
#: Each autopilot's usual SITL home (ArduPilot's CMAC, PX4's Zurich): latitude, longitude deg, altitude m AMSL.
DEFAULT_HOME = {ARDUCOPTER: (-35.363261, 149.165230, 584.0), PX4: (47.397742, 8.545594, 488.0)}
PX4_SIH_AUTOSTART = "10040"  # sihsim_quadx
#: EKF2's IMU noise set to what PX4 SIH's simulated IMU gives in flight. SIH adds 0.14 / 0.07 / 0.03 rad/s of gyro and
#: 0.5 / 1.7 / 1.4 m/s^2 of accelerometer noise once the rotors turn (sih.cpp); its 250 Hz sensor_combined reads
#: 0.11 / 0.06 / 0.02 rad/s and 0.4 / 1.2 / 1.0 m/s^2. EKF2's defaults (0.015 rad/s, 0.35 m/s^2) are a real IMU's:
#: with them this build's heading estimate left the truth by 15-23 deg and Hold circled its point
#: (docs/real_autopilots.md, "The cause: EKF2 did not know SIH's IMU noise"). These describe the simulator, not a
#: vehicle; a --param of the same name wins.
PX4_SIH_PARAMS = {"EKF2_GYR_NOISE": 0.1, "EKF2_ACC_NOISE": 1.0}
MAV_COMP_ID_ONBOARD_COMPUTER = 191  # the companion's component id: goals go there
POSITION_MASK = 0b110111111000  # SET_POSITION_TARGET_LOCAL_NED: position only
STOPPED_MPS = 0.5  # horizontal speed under which a vehicle counts as stopped (PX4 Hold jitters at 0.1-0.5 m/s)
#: "Still moving at the end" is the net horizontal speed over this last window: Hold's jitter swings back and forth
#: (a single sample read 0.5 m/s in a Hold that moved 0.27 m in 2 s), a vehicle that flies on does not.
END_WINDOW_S = 2.0
GCS_SYSID = 245  # this module's ground-station link (the world is 250)
#: Vehicle i's depth frames go to this + i: not sitl.world's default (14640), where any other
#: sitl.vehicle or sitl.world on the machine sends its frames (a companion fed another's frames flies blind).
DEPTH_PORT_BASE = 24640
#: PX4: each instance gets a second ground-station link (local UDP 18600 + i) sending here, where the
#: world listens: PX4's own GCS link goes to 14550, where every simulator on the machine sends by default
#: (another process's PX4-flavoured stand-in with system id 1 would be taken for instance 0).
PX4_WORLD_GCS_PORT = 24550
PX4_EXTRA_LINK_BASE = 18600
DEFAULT_POLICY = Path(__file__).resolve().parents[2] / "models" / "policy.pt"


class SitlError(RuntimeError):
    """A real-autopilot run could not go on (a process died, something never came), with the reason."""


#: The companion's real-time priority on the vehicle (systemd/companion.service CPUSchedulingPriority).
COMPANION_FIFO_PRIORITY = 20


def realtime_unavailable() -> str | None:
    """Why companions cannot run under SCHED_FIFO here (no chrt, no permission), or None if they can."""
    if shutil.which("chrt") is None:
        return "chrt (util-linux) is not installed"
    done = subprocess.run(["chrt", "-f", str(COMPANION_FIFO_PRIORITY), "true"], capture_output=True, text=True)
    if done.returncode != 0:
        return f"SCHED_FIFO refused ({done.stderr.strip() or 'exit ' + str(done.returncode)}): run as root or grant CAP_SYS_NICE"
    return None


def find_autopilot(kind: str) -> tuple[Path | None, str]:
    """The SITL binary of ``kind`` (``$SWARMNAV_ARDUCOPTER`` / ``$SWARMNAV_PX4``, else the default
    path), or None and why not."""
    env = BINARY_ENV[kind]
    named = os.environ.get(env)
    path = Path(named or DEFAULT_BINARY[kind])
    if path.is_file() and os.access(path, os.X_OK):
        return path, ""
    if named:
        return None, f"${env}={named} is not an executable file"
    return None, (f"no {kind} SITL binary at {path}: build it with ../shared/{BUILD_SCRIPT[kind]} "
                  f"or set ${env}")


def circle_layout(n: int, radius_m: float, rotation_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Spawn points [n, 2] (north, east m) on a circle around (0, 0) and their antipodes (the goals)."""
    angles = np.radians(rotation_deg) + 2.0 * np.pi * np.arange(n) / n
    spawns = radius_m * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    return spawns, -spawns


@dataclass
class PoseTrace:
    """The world's ``--trace`` records: UNIX times [T], world positions [T, n, 3] (NaN: not placed),
    velocities [T, n, 3], modes and armed states [T][n], headings [T, n] (rad; NaN: not known, or a trace
    written before the world recorded them)."""

    t: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    mode: list
    armed: list
    yaw: np.ndarray | None = None  # None: the same NaNs

    def __post_init__(self) -> None:
        if self.yaw is None:
            self.yaw = np.full(self.pos.shape[:2], math.nan)

    @classmethod
    def from_records(cls, records: list[dict], n: int) -> PoseTrace:
        rows = [r for r in records if r.get("event") == "pose"]
        nan3 = [math.nan] * 3
        pos = np.array([[p if p is not None else nan3 for p in r["pos_ned"]] for r in rows]).reshape(-1, n, 3)
        vel = np.array([[v if v is not None else nan3 for v in r["vel_ned"]] for r in rows]).reshape(-1, n, 3)
        yaw = np.array([[math.nan if y is None else y for y in r.get("yaw_rad", [None] * n)] for r in rows],
                       dtype=float).reshape(-1, n)
        return cls(np.array([r["t"] for r in rows]), pos, vel, [r["mode"] for r in rows], [r["armed"] for r in rows],
                   yaw)

    def since(self, t0: float) -> PoseTrace:
        k = self.t >= t0
        idx = np.flatnonzero(k)
        return PoseTrace(self.t[k], self.pos[k], self.vel[k], [self.mode[i] for i in idx], [self.armed[i] for i in idx],
                         self.yaw[k])


def end_speed_mps(trace: PoseTrace, vehicle: int, window_s: float = END_WINDOW_S) -> float:
    """Vehicle ``vehicle``'s net horizontal speed (m/s) over the last ``window_s`` of ``trace`` in which it was
    placed: how far it got from where it was, over the time. A hold's jitter swings back and forth and reads
    near 0; a vehicle that flies on reads its speed. NaN when it was never placed."""
    seen = np.flatnonzero(np.isfinite(trace.pos[:, vehicle, :2]).all(axis=1))
    if seen.size == 0:
        return math.nan
    last = seen[-1]
    first = seen[np.searchsorted(trace.t[seen], trace.t[last] - window_s)]
    span_s = float(trace.t[last] - trace.t[first])
    if span_s <= 0.0:
        return float(np.linalg.norm(trace.vel[last, vehicle, :2]))  # one sample: what the autopilot reported
    return float(np.linalg.norm(trace.pos[last, vehicle, :2] - trace.pos[first, vehicle, :2]) / span_s)


def max_net_speed_mps(trace: PoseTrace, vehicle: int, window_s: float = END_WINDOW_S) -> float:
    """The largest net horizontal speed (m/s) of vehicle ``vehicle`` over any ``window_s`` of ``trace``: how far
    it got in that time, over the time (:func:`end_speed_mps` for every window, not only the last). The
    velocity an autopilot reports is its estimate: PX4 SIH's read 0.24 m/s on a vehicle standing on the ground
    and up to 1.15 m/s in a Hold that moved 0.3 m/s (session 58). NaN when the trace never spans a window."""
    seen = np.flatnonzero(np.isfinite(trace.pos[:, vehicle, :2]).all(axis=1))
    t, pos = trace.t[seen], trace.pos[seen, vehicle, :2]
    starts = np.searchsorted(t, t - window_s)  # for each sample, the first one within window_s before it
    full = t - t[starts] >= 0.9 * window_s  # windows the trace covers (samples come at ~10 Hz)
    if not full.any():
        return math.nan
    moved = np.linalg.norm(pos[full] - pos[starts[full]], axis=1)
    return float(np.max(moved / (t[full] - t[starts[full]])))


def _pythonpath() -> str:
    """This source tree first: the companions and the world run the code beside this module, not
    whatever copy the ``companion`` console script was installed from."""
    repo = str(Path(__file__).resolve().parents[2])
    rest = os.environ.get("PYTHONPATH")
    return repo + (os.pathsep + rest if rest else "")


class Children(ProcessGroup):
    """:class:`~sitl.realtime.mavlink_swarm.ProcessGroup` with a working directory and extra environment per child."""

    def start(self, name: str, argv: list[str], out_path: Path, cwd: Path | None = None,
              env: dict | None = None) -> subprocess.Popen:
        with open(out_path, "wb") as out:
            proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                    env=dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=_pythonpath(),
                                             **(env or {})), cwd=cwd,
                                    start_new_session=True, preexec_fn=_die_with_parent)
        self.procs[name] = proc
        self.started_s[name] = time.monotonic()
        return proc


class RealSwarm:
    """N real autopilot SITL instances, ``sitl.world`` and their companions; see the module docstring.

    Args:
        kind: ``arducopter`` or ``px4``.
        binary: the SITL binary (:func:`find_autopilot`).
        spawns_ne: [n, 2] each vehicle's home, north/east metres from ``home``.
        out: the run's folder (logs, traces, the instances' working directories).
        home: latitude, longitude deg, altitude m of the point ``spawns_ne`` are relative to.
        params: autopilot parameters set at boot (ArduPilot: a defaults file; PX4: ``PX4_PARAM_<NAME>``, over
            :data:`PX4_SIH_PARAMS`).
        camera_hz: the world's camera rate.
        policy: the policy file every companion flies (default: the bundled ``models/policy.pt``).
        camera: the depth sensor the world gives every vehicle (a ``companion.spec.CAMERA_PRESETS`` name;
            default: the world's own, the D435); it must cover the policy's view, or the companions refuse it.
    """

    def __init__(self, kind: str, binary: Path, spawns_ne: np.ndarray, out: Path,
                 home: tuple[float, float, float] | None = None, params: dict[str, float] | None = None,
                 camera_hz: float = 30.0, policy: Path = DEFAULT_POLICY, camera: str | None = None,
                 autopilot_nice: int = 0, companion_realtime: bool = False) -> None:
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
        self.kind, self.binary, self.out = kind, Path(binary), Path(out)
        self.spawns = np.asarray(spawns_ne, dtype=np.float64).reshape(-1, 2)
        self.n = len(self.spawns)
        self.home = home or DEFAULT_HOME[kind]
        self.params = dict(params or {})
        self.camera_hz = camera_hz
        self.policy, self.camera = Path(policy), camera
        # > 0: the autopilots run at a lower CPU priority than the companions and the world (on a real vehicle each
        # has its own processor; on one small machine they compete, and a companion that misses its tick holds)
        self.autopilot_nice = autopilot_nice
        # True: every companion under SCHED_FIFO priority COMPANION_FIFO_PRIORITY, as systemd/companion.service runs
        # it on the vehicle; the loop then preempts the autopilots and the world instead of waiting for a turn.
        self.companion_realtime = companion_realtime
        self.out.mkdir(parents=True, exist_ok=True)
        self.procs = Children()
        self.offsets: np.ndarray | None = None  # each vehicle's local origin in the world frame, from the world
        self.gcs: list = [None] * self.n
        self.world_log = self.out / "world.jsonl"
        self.trace_path = self.out / "trace.jsonl"
        self._trace_tail = JsonLinesTail(self.trace_path)
        self._trace_records: list[dict] = []

    # ------------------------------------------------------------------ ports
    def companion_connection(self, i: int) -> str:
        return f"tcp:127.0.0.1:{5762 + 10 * i}" if self.kind == ARDUCOPTER else f"udp:{14540 + i}"

    def world_source(self) -> list[str]:
        if self.kind == ARDUCOPTER:
            return [a for i in range(self.n) for a in ("--connect", f"tcp:127.0.0.1:{5760 + 10 * i}")]
        return ["--px4", str(self.n), "--gcs-port", str(PX4_WORLD_GCS_PORT), "--gcs-host", "127.0.0.1"]

    def gcs_connection(self, i: int) -> str:
        return f"tcp:127.0.0.1:{5763 + 10 * i}" if self.kind == ARDUCOPTER else f"udpin:127.0.0.1:{14030 + i}"

    # ------------------------------------------------------------------ starting
    def __enter__(self) -> RealSwarm:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def home_of(self, i: int) -> tuple[float, float, float]:
        return shift_global(self.home, float(self.spawns[i, 0]), float(self.spawns[i, 1]))

    def start_autopilots(self) -> None:
        """Start every instance at its own home (ArduPilot: then waits for the world on SERIAL0)."""
        for i in range(self.n):
            lat, lon, alt = self.home_of(i)
            folder = self.out / f"{self.kind}_{i}"
            folder.mkdir(exist_ok=True)
            if self.kind == ARDUCOPTER:
                root = self.binary.resolve().parents[3]  # build/sitl/bin/arducopter -> the source tree
                defaults = [root / "Tools" / "autotest" / "default_params" / "copter.parm"]
                if not defaults[0].is_file():
                    raise SitlError(f"ArduCopter defaults {defaults[0]} not found next to {self.binary}")
                if self.params:
                    extra = folder / "swarmnav.parm"
                    extra.write_text("".join(f"{k} {v:g}\n" for k, v in self.params.items()))
                    defaults.append(extra)
                argv = [str(self.binary), "-w", "--model", "+", "--speedup", "1", "-I", str(i),
                        "--sysid", str(i + 1), "--home", f"{lat:.8f},{lon:.8f},{alt:.1f},0",
                        "--defaults", ",".join(str(d) for d in defaults)]
                self._start(f"autopilot_{i}", self._niced(argv), cwd=folder)
            else:
                etc = self.binary.resolve().parent.parent / "etc"
                argv = [str(self.binary), "-d", "-i", str(i), "-w", str(folder), str(etc)]
                self._start(f"autopilot_{i}", self._niced(argv), env=self.px4_env(i))

    def px4_env(self, i: int) -> dict[str, str]:
        """The environment PX4 SIH instance ``i`` boots with: SIH, its home, and its parameters."""
        lat, lon, alt = self.home_of(i)
        env = {"PX4_SYS_AUTOSTART": PX4_SIH_AUTOSTART, "PX4_SIM_MODEL": "sihsim_quadx", "PX4_SIMULATOR": "sihsim",
               "PX4_HOME_LAT": f"{lat:.8f}", "PX4_HOME_LON": f"{lon:.8f}", "PX4_HOME_ALT": f"{alt:.1f}"}
        # rcS sets PX4_PARAM_<NAME>=<value> as parameters at boot, before the modules start
        params = {**PX4_SIH_PARAMS, **self.params}
        env.update({f"PX4_PARAM_{name}": f"{value:g}" for name, value in params.items()})
        return env

    def _niced(self, argv: list[str]) -> list[str]:
        return ["nice", "-n", str(self.autopilot_nice), *argv] if self.autopilot_nice else argv

    def _start(self, name: str, argv: list[str], cwd: Path | None = None, env: dict | None = None) -> None:
        self.procs.start(name, argv, self.out / f"{name}.out", cwd=cwd, env=env)

    def add_px4_world_links(self, timeout_s: float = 90.0) -> None:
        """PX4: start a ground-station link on every instance to :data:`PX4_WORLD_GCS_PORT` (its
        ``px4-mavlink`` client), once the instance's start-up script has run."""
        client = self.binary.parent / "px4-mavlink"
        deadline = time.monotonic() + timeout_s
        for i in range(self.n):
            booted = self.out / f"autopilot_{i}.out"
            while "Startup script returned" not in booted.read_text(errors="replace"):
                if time.monotonic() > deadline:
                    raise SitlError(f"PX4 instance {i} did not finish its start-up script in {timeout_s:g} s; "
                                    f"see {booted}")
                self.check_alive()
                time.sleep(0.5)
            done = subprocess.run([str(client), "--instance", str(i), "start", "-u", str(PX4_EXTRA_LINK_BASE + i),
                                   "-o", str(PX4_WORLD_GCS_PORT), "-r", "4000000"], capture_output=True,
                                  text=True, timeout=20, cwd=self.out / f"{self.kind}_{i}")
            if done.returncode != 0:
                raise SitlError(f"PX4 instance {i} refused a second MAVLink link (rc {done.returncode}): "
                                f"{(done.stdout + done.stderr).strip()[-300:]}")

    def start_world(self, *extra: str) -> None:
        """``python -m sitl.world`` on every vehicle's telemetry, with ``--trace`` (PX4: on the links it adds first)."""
        if self.kind == PX4:
            self.add_px4_world_links()
        argv = [sys.executable, "-m", "sitl.world", *self.world_source(), "--log", str(self.world_log),
                "--depth-port", str(DEPTH_PORT_BASE),
                "--trace", str(self.trace_path), "--camera-hz", f"{self.camera_hz:g}",
                *(["--camera", self.camera] if self.camera else []), *extra]
        self.procs.start("world", argv, self.out / "world.out")

    def wait_tracking(self, timeout_s: float, origin_wait_s: float = 12.0) -> np.ndarray:
        """Until the world draws every vehicle (the autopilots' estimators have a position and an
        origin) and, for up to ``origin_wait_s`` more, until every origin is a GPS_GLOBAL_ORIGIN
        (not the HOME_POSITION stand-in); returns each vehicle's origin offset in the world frame [n, 3]."""
        deadline = time.monotonic() + timeout_s
        tail = JsonLinesTail(self.world_log)
        tracking: set[int] = set()
        origins: dict[int, dict] = {}
        settle_until = math.inf
        while time.monotonic() < deadline:
            for r in tail.read():
                if r.get("event") == "tracking":
                    tracking.add(int(r["vehicle"]))
                elif r.get("event") == "origin":
                    origins[int(r["vehicle"])] = r
            if len(tracking) == self.n:
                settle_until = min(settle_until, time.monotonic() + origin_wait_s)
                fixed = all(origins.get(i, {}).get("source") == "GPS_GLOBAL_ORIGIN" for i in range(self.n))
                if fixed or time.monotonic() > settle_until:
                    break
            self.check_alive()
            time.sleep(0.2)
        else:
            raise SitlError(f"the world did not track every vehicle within {timeout_s:g} s "
                            f"(tracking: {sorted(tracking)}); logs in {self.out}")
        if len(origins) == self.n and all(o.get("used", True) for o in origins.values()):  # the world's offsets now
            ref = (origins[0]["lat_deg"], origins[0]["lon_deg"], 0.0)
            self.offsets = np.array([ned_offset_m(ref, (origins[i]["lat_deg"], origins[i]["lon_deg"], 0.0))
                                     for i in range(self.n)])
        else:
            self.offsets = np.array([r["origin_offset_ned"] for r in self._tracking_events()], dtype=np.float64)
        return self.offsets

    def _tracking_events(self) -> list[dict]:
        last = {int(r["vehicle"]): r for r in JsonLinesTail(self.world_log).read() if r.get("event") == "tracking"}
        return [last[i] for i in range(self.n)]

    def local_goal(self, i: int, goal_world_ned: np.ndarray) -> np.ndarray:
        """A world-frame point in vehicle ``i``'s own local frame (what its companion's --goal means)."""
        assert self.offsets is not None, "wait_tracking first"
        return np.asarray(goal_world_ned, dtype=np.float64) - self.offsets[i]

    def start_companion(self, i: int, *extra: str, takeoff_m: float = 8.0) -> None:
        fifo = ["chrt", "-f", str(COMPANION_FIFO_PRIORITY)] if self.companion_realtime else []
        argv = [*fifo, *companion_command(), "--connect", self.companion_connection(i), "--camera",
                f"sitl:{DEPTH_PORT_BASE + i}:{i}", "--model", str(self.policy), "--arm", "--takeoff", f"{takeoff_m:g}",
                "--heartbeat-timeout", "60", "--log", str(self.companion_log(i)), *extra]
        self.procs.start(f"companion_{i}", argv, self.out / f"companion_{i}.out")

    def companion_log(self, i: int) -> Path:
        return self.out / f"companion_{i}.jsonl"

    # ------------------------------------------------------------------ watching
    def check_alive(self, allowed: tuple[str, ...] = ()) -> None:
        for name, code in self.procs.dead():
            if name in allowed or name.startswith("companion_") and code == 0:
                continue
            tail = ""
            with contextlib.suppress(OSError, IndexError):
                tail = (self.out / f"{name}.out").read_text(errors="replace").strip().splitlines()[-1][:300]
            raise SitlError(f"{name} exited with code {code} ({tail or 'no output'}); logs in {self.out}")

    def trace(self) -> PoseTrace:
        self._trace_records += self._trace_tail.read()
        return PoseTrace.from_records(self._trace_records, self.n)

    def phases(self, i: int) -> list[dict]:
        return [r for r in JsonLinesTail(self.companion_log(i)).read() if r.get("event") == "phase"]

    def wait_phase(self, names: list[int], phase: str, timeout_s: float, allowed_dead: tuple[str, ...] = ()) -> None:
        """Until each companion in ``names`` has logged ``phase``."""
        deadline = time.monotonic() + timeout_s
        tails = {i: JsonLinesTail(self.companion_log(i)) for i in names}
        seen: dict[int, str] = dict.fromkeys(names, "starting")
        while time.monotonic() < deadline:
            for i, tail in tails.items():
                for r in tail.read():
                    if r.get("event") == "phase" and r.get("to"):
                        seen[i] = r["to"] if seen[i] != phase else phase
            if all(p == phase for p in seen.values()):
                return
            self.check_alive(allowed_dead)
            time.sleep(0.1)
        raise SitlError(f"not every companion reached {phase} within {timeout_s:g} s: {seen}; logs in {self.out}")

    # ------------------------------------------------------------------ the ground station
    def _gcs(self, i: int):
        if self.gcs[i] is None:
            with contextlib.redirect_stdout(sys.stderr):
                conn = mavutil.mavlink_connection(self.gcs_connection(i), source_system=GCS_SYSID,
                                                  source_component=190, dialect="common")
            conn.mav.robust_parsing = True
            self.gcs[i] = conn
        conn = self.gcs[i]
        # Learn PX4's address from its first heartbeat, once: pymavlink's udpin keeps no last_address, and
        # waiting on every call held each goal up to a second (the heartbeat is 1 Hz).
        if self.kind == PX4 and not getattr(conn, "clients", None) and getattr(conn, "last_address", None) is None:
            conn.recv_match(type="HEARTBEAT", blocking=True, timeout=10)
        return conn

    def connect_ground_station(self) -> None:
        """Open every vehicle's ground-station link now (on PX4 each waits for a heartbeat, up to a second), so that
        goals sent afterwards go out together: opened one by one while sending, they reached the vehicles 3-5 s
        apart (sessions 49-51)."""
        for i in range(self.n):
            self._gcs(i)

    def send_goal(self, i: int, goal_local_ned: np.ndarray) -> None:
        """A run-time goal for companion ``i``, through its autopilot (routed to component 191)."""
        conn = self._gcs(i)
        conn.mav.set_position_target_local_ned_send(0, i + 1, MAV_COMP_ID_ONBOARD_COMPUTER,
                                                    mavutil.mavlink.MAV_FRAME_LOCAL_NED, POSITION_MASK,
                                                    *map(float, goal_local_ned), 0, 0, 0, 0, 0, 0, math.nan, math.nan)

    def set_mode(self, i: int, mode: str) -> None:
        """Switch vehicle ``i`` to ``mode`` (an ArduCopter or PX4 name, as in companion.flight_modes), as a pilot would."""
        conn = self._gcs(i)
        if self.kind == ARDUCOPTER:
            main, sub = ARDUCOPTER_MODE_BY_NAME[mode], 0
        else:
            main, sub = PX4_MODE_BY_NAME[mode]
        conn.mav.command_long_send(i + 1, 1, mavutil.mavlink.MAV_CMD_DO_SET_MODE, 0,
                                   mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, sub, 0, 0, 0, 0)

    def drain_gcs(self) -> None:
        for conn in self.gcs:
            if conn is not None:
                with contextlib.suppress(OSError), contextlib.redirect_stdout(sys.stderr):
                    while conn.recv_msg() is not None:
                        pass

    def signal_companion(self, i: int, sig: int) -> None:
        proc = self.procs.procs[f"companion_{i}"]
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)

    # ------------------------------------------------------------------ stopping
    def close(self) -> None:
        """Stop everything: companions, the world, then the autopilots (SIGKILL whoever stays)."""
        for conn in self.gcs:
            if conn is not None:
                with contextlib.suppress(OSError):
                    conn.close()
        names = list(self.procs.procs)
        self.procs.stop([n for n in names if n.startswith("companion_")])
        self.procs.stop([n for n in names if n == "world"])
        autopilots = [n for n in names if n.startswith("autopilot_")]
        for name in autopilots:  # PX4 and ArduPilot SITL stop on SIGTERM; SIGINT is ignored by px4 -d
            proc = self.procs.procs[name]
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGTERM)
        self.procs.stop(autopilots, grace_s=5.0)


# --------------------------------------------------------------------------- measurements


def pairwise_min_distance(pos: np.ndarray) -> tuple[float, tuple[int, int]]:
    """Closest approach of any two vehicles over a trace [T, n, 3] (NaN rows skipped)."""
    best, pair = math.inf, (-1, -1)
    n = pos.shape[1]
    for a in range(n):
        for b in range(a + 1, n):
            d = np.linalg.norm(pos[:, a] - pos[:, b], axis=1)
            d = d[np.isfinite(d)]
            if d.size and d.min() < best:
                best, pair = float(d.min()), (a, b)
    return best, pair


def fly_circle(kind: str, binary: Path, n: int, out: Path, radius_m: float = 12.0, altitude_m: float = 8.0,
               rotation_deg: float = 0.0, time_limit_s: float = 60.0, ready_timeout_s: float = 240.0,
               settle_s: float = 10.0, params: dict[str, float] | None = None, status=print,
               policy: Path = DEFAULT_POLICY, camera: str | None = None, face_goal_s: float | None = None,
               autopilot_nice: int = 0, companion_realtime: bool = False) -> dict:
    """A circle of ``n`` vehicles flying to their antipodes together; the measured results.

    The vehicles spawn facing north, as SITL spawns them; with ``face_goal_s`` every companion turns to face its goal
    first and flies that long after the goals were sent (``companion --face-goal``).

    Arrival is the first time within the task's arrival radius of the goal; the settled error is
    the distance to the goal ``settle_s`` after arrival; a collision is two vehicles closer than
    twice the task's collision radius at any time after the goals were sent.
    """
    spawns, goals_ne = circle_layout(n, radius_m, rotation_deg)
    spawns_rel = spawns - spawns[0]  # the world frame is vehicle 0's local frame
    goals = np.concatenate([goals_ne - spawns[0], np.full((n, 1), -altitude_m)], axis=1)
    started = time.monotonic()
    with RealSwarm(kind, binary, spawns_rel, out, params=params, policy=policy, camera=camera,
                   autopilot_nice=autopilot_nice, companion_realtime=companion_realtime) as swarm:
        swarm.start_autopilots()
        swarm.start_world()
        offsets = swarm.wait_tracking(ready_timeout_s)
        status(f"{kind}: world tracks all {n} after {time.monotonic() - started:.0f} s; starting companions")
        for i in range(n):
            swarm.start_companion(i, *(() if face_goal_s is None else ("--face-goal", f"{face_goal_s:g}")),
                                  takeoff_m=altitude_m)
        swarm.wait_phase(list(range(n)), FlightPhase.FLYING_TO_GOAL.value, ready_timeout_s)
        ready_s = time.monotonic() - started
        swarm.connect_ground_station()
        status(f"{kind}: all {n} airborne after {ready_s:.0f} s; sending the goals")
        t0 = time.time()
        first_sent_s = np.full(n, math.nan)  # when each vehicle's first copy went out, after t0
        for copy in range(3):  # copies: a lost datagram must not cost a vehicle its flight
            for i in range(n):
                swarm.send_goal(i, swarm.local_goal(i, goals[i]))
                if copy == 0:
                    first_sent_s[i] = time.time() - t0
            time.sleep(0.05)
        arrived_t = np.full(n, math.nan)
        while time.time() - t0 < time_limit_s:
            swarm.drain_gcs()
            swarm.check_alive()
            tr = swarm.trace().since(t0)
            if len(tr.t):
                dist = np.linalg.norm(tr.pos - goals[None], axis=2)
                for i in range(n):
                    hits = np.flatnonzero(dist[:, i] < DEFAULT_TASK_SPEC.arrival_radius_m)
                    if math.isnan(arrived_t[i]) and hits.size:
                        arrived_t[i] = tr.t[hits[0]]
            if np.all(np.isfinite(arrived_t)) and time.time() > np.nanmax(arrived_t) + settle_s + 0.5:
                break
            time.sleep(0.2)
        tr = swarm.trace().since(t0)
        world_status = [r for r in JsonLinesTail(swarm.world_log).read() if r.get("event") == "world_status"]
    summary = _circle_summary(kind, n, radius_m, altitude_m, rotation_deg, tr, goals, offsets, arrived_t, t0,
                              settle_s, ready_s, world_status)
    # Where each vehicle stood when the goals went out: how far from its point on the ring (the takeoff's and
    # the wait's drift), and how high.
    at_goals = tr.pos[0] if len(tr.t) else np.full((n, 3), math.nan)
    summary |= {"start_offset_m": np.round(np.linalg.norm(at_goals[:, :2] - spawns_rel, axis=1), 2).tolist(),
                "start_altitude_m": np.round(-at_goals[:, 2], 2).tolist()}
    summary |= {"policy": str(policy), "camera": camera or "the world's default", "face_goal_s": face_goal_s,
                "goals_sent_within_s": round(float(first_sent_s.max()), 4), "autopilot_nice": autopilot_nice,
                "companion_scheduling": f"SCHED_FIFO {COMPANION_FIFO_PRIORITY}" if companion_realtime else "default",
                "goal_sent_s": np.round(first_sent_s, 4).tolist()}
    summary["response_fit"] = _fit_or_why(out)
    logs = companion_logs(out, n)
    summary["companion_stalls"] = companion_stalls(logs, t0)
    summary["late_policy_answers"] = late_policy_answers(logs, t0)
    summary["held_share"] = shares = held_shares(logs, t0)
    summary["held_reasons"] = held_reasons(logs, t0)
    mean_held = mean_held_share(shares)
    summary["starved"] = starved = mean_held is not None and mean_held > STARVED_HELD_SHARE
    if starved:
        status(f"{kind}: warning: the companions held {mean_held:.0%} of their "
               f"ticks in flight ({', '.join(summary['held_reasons'])}): the machine starved them, so this run "
               "does not measure the policy; fly it again on an idle machine (docs/real_autopilots.md)")
    summary["autopilot_failsafes"] = failsafes = _failsafes_or_why(out, t0)
    # A vehicle the autopilot took from its companion before it arrived did not fly the policy: the run does not
    # measure the policy for it (on a 2-core machine, mostly PX4's offboard-loss failsafe after a stall).
    summary["vehicles_failsafe_before_arrival"] = None if isinstance(failsafes, str) else sorted({
        f["vehicle"] for f in failsafes if f.get("t_after_s") is not None and 0.0 <= f["t_after_s"] <= (
            time_limit_s if summary["flight_s"][f["vehicle"]] is None else summary["flight_s"][f["vehicle"]])})
    write_summary(out, summary)
    return summary


def _fit_or_why(out: Path) -> dict | str:
    """Each vehicle's fitted velocity response (sitl.realtime.response_fit), or why there is none."""
    from sitl.realtime.response_fit import FitError, fit_run, fit_summary

    try:
        return fit_summary(fit_run(out))
    except FitError as err:
        return f"not fitted: {err}"


def companion_logs(out: Path, n: int) -> list[list[dict]]:
    """Every companion's log records (``companion_I.jsonl`` in run folder ``out``), read once for the summaries."""
    return [JsonLinesTail(out / f"companion_{i}.jsonl").read() for i in range(n)]


def companion_stalls(logs: list[list[dict]], since_unix_s: float) -> list[dict]:
    """Every companion's logged stalls (``stall``: its loop went more than 0.5 s without a setpoint), with the time
    after ``since_unix_s``: a stall near a close encounter means the policy was not flying then."""
    stalls = [{"vehicle": i, "t_after_s": round(r["t"] - since_unix_s, 2), "gap_s": r.get("gap_s")}
              for i, records in enumerate(logs) for r in records if r.get("event") == "stall"]
    return sorted(stalls, key=lambda r: r["t_after_s"])


def late_policy_answers(logs: list[list[dict]], since_unix_s: float) -> list[int]:
    """Per companion, the policy answers it discarded as late (``policy_late``: each a tick it held instead of flying)
    from ``since_unix_s`` on. On a starved machine these run into the hundreds (docs/real_autopilots.md)."""
    return [sum(1 for r in records if r.get("event") == "policy_late" and r["t"] >= since_unix_s)
            for records in logs]


#: A circle run whose companions held more than this mean share of their ticks in flight did not fly the policy: the
#: machine starved them. Session 55 called its runs above 5 % starved; of session 59's 21 PX4 SIH circles of 8 the five
#: it flew again read 15-46 %, the others 0-3 % and one 5.8 % (docs/real_autopilots.md, "Telling a starved run").
STARVED_HELD_SHARE = 0.05


def _held_in_flight(logs: list[list[dict]], since_unix_s: float):
    """Per companion, the ``hold`` field of each control tick from ``since_unix_s`` on in which it flew to a goal it
    had (phase ``flying_to_goal``, goal known): None where it sent the policy's command."""
    flying = FlightPhase.FLYING_TO_GOAL.value
    return [[r.get("hold") for r in records if r.get("kind") == "step" and r["t"] >= since_unix_s
             and r.get("phase") == flying and r.get("goal_ned") is not None] for records in logs]


def held_shares(logs: list[list[dict]], since_unix_s: float) -> list[float | None]:
    """Per companion, the share of its control ticks in flight to its goal (from ``since_unix_s`` on) in which it held
    instead of sending the policy's command, for any reason (late policy answer, stale depth or odometry); None for
    a companion with no such tick."""
    return [round(sum(h is not None for h in holds) / len(holds), 3) if holds else None
            for holds in _held_in_flight(logs, since_unix_s)]


def held_reasons(logs: list[list[dict]], since_unix_s: float) -> dict[str, int]:
    """Why the companions held in flight (the ticks of :func:`held_shares`), all companions together, most first:
    the reason's words before its details (``policy inference late``, ``depth stale``, ...)."""
    counts = collections.Counter(h.split(" (")[0] for holds in _held_in_flight(logs, since_unix_s)
                                 for h in holds if h is not None)
    return dict(counts.most_common())


def mean_held_share(shares: list[float | None]) -> float | None:
    """The companions' mean of :func:`held_shares` (None where no companion flew to a goal)."""
    known = [s for s in shares if s is not None]
    return round(sum(known) / len(known), 3) if known else None


def _failsafes_or_why(out: Path, since_unix_s: float) -> list[dict] | str:
    """Every autopilot failsafe of the run with its reason (sitl.realtime.autopilot_events), or why they are unknown.

    Each record's ``t_after_s`` counts from ``since_unix_s`` (the goals, or the signal)."""
    from sitl.realtime.autopilot_events import EventsError, failsafe_summary, run_failsafes

    try:
        return failsafe_summary(run_failsafes(out), since_unix_s)
    except EventsError as err:
        return f"not read: {err}"


#: The modes in which an autopilot follows its companion's setpoints (PX4, ArduPilot): the policy flies only there.
COMPANION_MODES = ("OFFBOARD", "GUIDED")


def under_companion(tr: PoseTrace) -> np.ndarray:
    """[T, n] True where the vehicle's autopilot was in its companion mode: not taken by a failsafe or a pilot."""
    return np.array([[m in COMPANION_MODES for m in row] for row in tr.mode], dtype=bool).reshape(tr.pos.shape[:2])


def _when_closest(tr: PoseTrace, flown: np.ndarray, pair: tuple[int, int], t0: float) -> float | None:
    """Seconds after ``t0`` at which ``pair`` came closest while both flew their companions' setpoints."""
    a, b = pair
    if a < 0 or not len(tr.t):
        return None
    d = np.where(flown[:, a] & flown[:, b], np.linalg.norm(tr.pos[:, a] - tr.pos[:, b], axis=1), np.inf)
    d = np.where(np.isfinite(d), d, np.inf)
    return round(float(tr.t[int(np.argmin(d))] - t0), 2) if np.isfinite(d).any() else None


def _circle_summary(kind, n, radius_m, altitude_m, rotation_deg, tr: PoseTrace, goals, offsets, arrived_t, t0,
                    settle_s, ready_s, world_status) -> dict:
    # The policy's closest pair: only while both vehicles fly their companions' setpoints. Once an autopilot's
    # failsafe takes a vehicle (RTL, Hold), the autopilot flies it, not the policy (session 55: a 0.41 m pair
    # between two vehicles both in AUTO.RTL, 86 s after the goals).
    flown = under_companion(tr) if len(tr.t) else np.zeros(tr.pos.shape[:2], dtype=bool)
    closest, pair = pairwise_min_distance(np.where(flown[:, :, None], tr.pos, math.nan))
    closest_any, pair_any = pairwise_min_distance(tr.pos)
    settled = []
    for i in range(n):
        if math.isnan(arrived_t[i]):
            settled.append(None)
            continue
        k = np.flatnonzero(tr.t >= arrived_t[i] + settle_s)
        settled.append(round(float(np.linalg.norm(tr.pos[k[0], i] - goals[i])), 3) if k.size else None)
    cpu = [w["cpu_percent"] for w in world_status]
    skipped = max((w["skipped_frames"] for w in world_status), default=0)
    return {
        "autopilot": kind, "n": n, "radius_m": radius_m, "altitude_m": altitude_m, "rotation_deg": rotation_deg,
        "arrived": int(np.isfinite(arrived_t).sum()),
        "collisions": int(closest < 2 * DEFAULT_TASK_SPEC.collision_radius_m),
        "closest_pair_m": round(closest, 3), "closest_pair": list(pair),
        "closest_pair_t_after_s": _when_closest(tr, flown, pair, t0),
        "closest_pair_any_mode_m": round(closest_any, 3), "closest_pair_any_mode": list(pair_any),
        "flight_s": [None if math.isnan(a) else round(a - t0, 1) for a in arrived_t],
        "settled_error_m": settled, "settle_s": settle_s,
        "origin_offsets_ned": np.round(offsets, 3).tolist(), "ready_s": round(ready_s, 1),
        "world_cpu_percent_median": float(np.median(cpu)) if cpu else None, "world_skipped_frames": skipped,
    }


def fly_and_stop(kind: str, binary: Path, out: Path, sig: int, distance_m: float = 30.0, altitude_m: float = 8.0,
                 trigger_speed_mps: float = 1.5, watch_s: float = 12.0, ready_timeout_s: float = 240.0,
                 params: dict[str, float] | None = None, status=print, policy: Path = DEFAULT_POLICY,
                 camera: str | None = None) -> dict:
    """One vehicle flies towards a goal ``distance_m`` north; once faster than ``trigger_speed_mps``
    its companion gets ``sig``. Measures how far and how long the vehicle went on, and its mode after."""
    goal = np.array([distance_m, 0.0, -altitude_m])
    with RealSwarm(kind, binary, np.zeros((1, 2)), out, params=params, policy=policy, camera=camera) as swarm:
        swarm.start_autopilots()
        swarm.start_world()
        swarm.wait_tracking(ready_timeout_s)
        swarm.start_companion(0, "--goal", ",".join(f"{c:g}" for c in goal), takeoff_m=altitude_m)
        swarm.wait_phase([0], FlightPhase.FLYING_TO_GOAL.value, ready_timeout_s)
        deadline = time.monotonic() + 60.0
        while True:
            swarm.check_alive()
            tr = swarm.trace()
            if len(tr.t) and np.linalg.norm(tr.vel[-1, 0, :2]) > trigger_speed_mps:
                break
            if time.monotonic() > deadline:
                raise SitlError(f"the vehicle never flew faster than {trigger_speed_mps} m/s; logs in {out}")
            time.sleep(0.05)
        t_sig = time.time()
        pos_sig, speed_sig = tr.pos[-1, 0].copy(), float(np.linalg.norm(tr.vel[-1, 0, :2]))
        swarm.signal_companion(0, sig)
        status(f"{kind}: {signal.Signals(sig).name} at {speed_sig:.2f} m/s")
        time.sleep(watch_s)
        tr = swarm.trace().since(t_sig)
        exit_code = swarm.procs.procs["companion_0"].poll()
    horizontal = np.linalg.norm(tr.pos[:, 0, :2] - pos_sig[:2], axis=1)
    speed = np.linalg.norm(tr.vel[:, 0, :2], axis=1)
    slow = np.flatnonzero(speed < STOPPED_MPS)
    stop_k = int(slow[0]) if slow.size else len(tr.t) - 1  # the first moment it had stopped
    drift = np.linalg.norm(tr.pos[stop_k:, 0, :2] - tr.pos[stop_k, 0, :2], axis=1)
    end_speed = end_speed_mps(tr, 0)
    summary = {
        "autopilot": kind, "signal": signal.Signals(sig).name, "speed_at_signal_mps": round(speed_sig, 2),
        "stop_distance_m": round(float(np.nanmax(horizontal[:stop_k + 1])), 2),
        "stopped_after_s": round(float(tr.t[stop_k] - t_sig), 2) if slow.size else None,
        "moved_after_stop_m": round(float(np.nanmax(drift)), 2),
        "end_speed_mps": round(end_speed, 2), "still_moving_at_end": bool(end_speed > STOPPED_MPS),
        "climb_m": round(float(-(np.nanmin(tr.pos[:, 0, 2]) - pos_sig[2])), 2),
        "modes_after": list(dict.fromkeys(m[0] for m in tr.mode)), "companion_exit": exit_code,
        "params": params or {}, "watch_s": watch_s, "policy": str(policy), "camera": camera or "the world's default",
        "autopilot_failsafes": _failsafes_or_why(out, t_sig),
    }
    write_summary(out, summary)
    return summary


def write_summary(out: Path, summary: dict) -> None:
    (Path(out) / "summary.json").write_text(json.dumps(summary, indent=1))


# --------------------------------------------------------------------------- command line


def _param(text: str) -> tuple[str, float]:
    import argparse

    name, sep, value = text.partition("=")
    try:
        number = float(value)
    except ValueError:
        number = math.nan
    if not sep or not name.strip() or not math.isfinite(number):
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE with a finite number, got {text!r}")
    return name.strip().upper(), number


def _policy_file(text: str) -> Path:
    """A policy file the companions can fly (checked here, so that a bad one fails before anything starts)."""
    import argparse

    from companion.policy import PolicyFileError, load_policy

    try:
        load_policy(text)
    except PolicyFileError as err:  # what the companion would refuse it for, in one line
        raise argparse.ArgumentTypeError(f"cannot use the model: {err}") from None
    return Path(text)


def _fit_main(runs: list[Path], plot: Path | None = None) -> int:
    """``fit``: every run's vehicles, a table per run on stderr, one JSON line on stdout (the spec spanning all);
    ``plot``: a figure of every vehicle's fit."""
    from sitl.realtime.response_fit import FitError, fit_run, fit_summary, format_fits, response_spec

    everything, per_run = [], {}
    for run in runs:
        try:
            fits = fit_run(run, progress=lambda f: print(f"{run}: vehicle {f.vehicle} fitted", file=sys.stderr,
                                                         flush=True))
            per_run[str(run)] = fit_summary(fits)
            (run / "response_fit.json").write_text(json.dumps(per_run[str(run)], indent=1))
        except (FitError, OSError) as err:
            print(f"sitl.real_autopilots fit: error: {err}", file=sys.stderr)
            return 2
        print(f"{run}:\n{format_fits(fits)}\n  --response {per_run[str(run)]['response']}", file=sys.stderr)
        everything += fits
    if plot is not None:
        from sitl.eval.plots import plot_response_fits

        plot_response_fits({str(run): per_run[str(run)]["vehicles"] for run in runs}, plot,
                           "each vehicle's fitted velocity response")
        print(f"wrote {plot}", file=sys.stderr)
    print(json.dumps({"runs": per_run, "response": response_spec(everything)}))
    return 0


def _events_main(runs: list[Path]) -> int:
    """``events``: every run's autopilot failsafes with their reasons on stderr, one JSON line on stdout;
    each run's also in RUN/autopilot_failsafes.json."""
    from sitl.realtime.autopilot_events import EventsError, failsafe_summary, format_failsafes, run_failsafes

    per_run = {}
    for run in runs:
        try:
            failsafes = run_failsafes(run)
            per_run[str(run)] = failsafe_summary(failsafes)
            (run / "autopilot_failsafes.json").write_text(json.dumps(per_run[str(run)], indent=1))
        except (EventsError, OSError) as err:
            print(f"sitl.real_autopilots events: error: {err}", file=sys.stderr)
            return 2
        print(f"{run}:\n{format_failsafes(failsafes)}", file=sys.stderr)
    print(json.dumps({"runs": per_run}))
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m sitl.real_autopilots circle|stop|fit|events``: run (or fit) and print the measured results as JSON."""
    import argparse

    from sitl.cli_args import ArgumentParser, finite_float, int_range, output_dir, output_file_in_new_dir, positive_float

    parser = ArgumentParser(prog="python -m sitl.real_autopilots", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="what", required=True)
    circle = sub.add_parser("circle", help="a circle of N vehicles flying to their antipodes together")
    stop = sub.add_parser("stop", help="one vehicle in flight; its companion gets a signal: how far does it go on?")
    fit = sub.add_parser("fit", help="fit each vehicle's velocity response from finished runs' logs (the simulator's "
                                     "kinematic law: lag, drag, integral, delay) and print the --response ranges "
                                     "that span them (sitl.realtime.response_fit)")
    fit.add_argument("runs", nargs="+", type=Path, metavar="RUN",
                     help="a run folder of circle or stop (companion_I.jsonl, trace.jsonl); writes RUN/response_fit.json")
    fit.add_argument("--plot", type=output_file_in_new_dir, default=None, metavar="PNG",
                     help="also draw every vehicle's fit, one colour per run (lag against drag and quick gain)")
    events = sub.add_parser("events", help="every autopilot failsafe of finished runs, with its reason (PX4: decoded "
                                           "from its ULog with pyulog; ArduCopter: its STATUSTEXT in the companions' "
                                           "logs); writes RUN/autopilot_failsafes.json")
    events.add_argument("runs", nargs="+", type=Path, metavar="RUN", help="a run folder of circle or stop")
    for p in (circle, stop):
        p.add_argument("--autopilot", choices=KINDS, required=True)
        p.add_argument("--out", type=output_dir, required=True, metavar="DIR", help="logs, traces and summary.json")
        p.add_argument("--altitude", type=positive_float, default=8.0, help="flight altitude in metres (default 8)")
        p.add_argument("--param", type=_param, action="append", default=[], metavar="NAME=VALUE",
                       help="an autopilot parameter set before flight, repeatable (e.g. GUID_TIMEOUT=0.5); PX4 SIH "
                            "always gets " + " ".join(f"{k}={v:g}" for k, v in PX4_SIH_PARAMS.items())
                            + " (its IMU's noise) unless given here")
        p.add_argument("--ready-timeout", type=positive_float, default=240.0, metavar="S",
                       help="start-up limit: boot, EKF position, arming and takeoff (default 240 s)")
        p.add_argument("--model", type=_policy_file, default=DEFAULT_POLICY, metavar="PATH",
                       help="the policy file every companion flies (default: the bundled models/policy.pt)")
        p.add_argument("--camera", choices=sorted(CAMERA_PRESETS), default=None,
                       help="the depth sensor the world gives every vehicle (default: sitl.world's, realsense_d435); "
                            "it must cover the policy's view")
    circle.add_argument("--n", type=int_range(2, 16), default=8)
    circle.add_argument("--radius", type=positive_float, default=12.0, help="circle radius in metres (default 12)")
    circle.add_argument("--rotation", type=finite_float, default=0.0, metavar="DEG",
                        help="bearing of vehicle 0's spawn point from the centre (default 0)")
    circle.add_argument("--time-limit", type=positive_float, default=60.0, metavar="S",
                        help="after the goals are sent (default 60 s)")
    circle.add_argument("--autopilot-nice", type=int_range(0, 19), default=0, metavar="N",
                        help="run the autopilots at CPU niceness N (default 0): on a small machine, lower than the "
                             "companions and the world, as each has its own processor on a real vehicle")
    circle.add_argument("--companion-realtime", action="store_true",
                        help=f"run every companion under SCHED_FIFO priority {COMPANION_FIFO_PRIORITY} (chrt), as "
                             "systemd/companion.service does on the vehicle: on a small machine a companion that "
                             "waits for the CPU sends no setpoint, and PX4's offboard-loss failsafe takes the vehicle "
                             "after 1 s (needs root or CAP_SYS_NICE)")
    add_face_goal_argument(circle, help="every companion turns to face its goal first and flies SECONDS after the goals "
                                        f"(companion --face-goal; {DEFAULT_FACE_GOAL_S:g} s alone)")
    stop.add_argument("--signal", choices=("TERM", "KILL", "INT"), default="TERM")
    stop.add_argument("--distance", type=positive_float, default=30.0, help="goal distance north in metres (default 30)")
    args = parser.parse_args(argv)
    if args.what == "fit":
        return _fit_main(args.runs, args.plot)
    if args.what == "events":
        return _events_main(args.runs)

    binary, why = find_autopilot(args.autopilot)
    if binary is None:
        print(f"sitl.real_autopilots: error: {why}", file=sys.stderr)
        return 1
    if getattr(args, "companion_realtime", False) and (why := realtime_unavailable()):
        print(f"sitl.real_autopilots: error: --companion-realtime: {why}", file=sys.stderr)
        return 2
    params = dict(args.param)

    def status(text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    try:
        if args.what == "circle":
            summary = fly_circle(args.autopilot, binary, args.n, args.out, args.radius, args.altitude, args.rotation,
                                 args.time_limit, args.ready_timeout, params=params, status=status,
                                 policy=args.model, camera=args.camera, face_goal_s=args.face_goal,
                                 autopilot_nice=args.autopilot_nice, companion_realtime=args.companion_realtime)
        else:
            summary = fly_and_stop(args.autopilot, binary, args.out, getattr(signal, f"SIG{args.signal}"),
                                   args.distance, args.altitude, ready_timeout_s=args.ready_timeout, params=params,
                                   status=status, policy=args.model, camera=args.camera)
    except SitlError as err:
        print(f"sitl.real_autopilots: error: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("sitl.real_autopilots: interrupted; every process stopped", file=sys.stderr)
        return 130
    write_summary(args.out, summary)
    print(json.dumps(summary))
    return 0
