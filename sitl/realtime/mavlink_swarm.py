"""The whole stack as a swarm: one SITL world, N real ``companion`` processes, real MAVLink.

``python -m sitl.swarm_test --n 8 --mavlink`` calls :func:`evaluate_over_mavlink`. Each
episode, in real time:

1. ``python -m sitl.vehicle`` simulates the N vehicles of the scenario's episode (PX4
   flavour; vehicle ``i`` talks MAVLink on UDP ``base_port + i``, streams its depth camera
   to ``depth_port + i``, sends its ground-station link to ``gcs_port``, and writes its true
   positions to a trace file at 10 Hz);
2. N ``companion`` processes (the installed console script), one per vehicle, each with
   only its own link and camera, arm their vehicle and — when the episode starts on the
   ground — take off to the episode's start altitude with ``--arm --takeoff``;
3. once every companion reports ``flying_to_goal`` (holding, no goal yet), this process,
   acting as the ground station, sends every vehicle its goal at the same moment
   (SET_POSITION_TARGET_LOCAL_NED to component 191, routed by the autopilot to its
   companion), so all UAVs start together as they do in the in-process evaluation;
4. the episode ends when every UAV has arrived (within the arrival radius) or crashed, or
   at the time limit; then every process is stopped (SIGINT, then SIGKILL).

Outcomes come from the world's ground truth with the in-process definitions: a UAV-UAV
collision is the vehicle simulator's continuous 2R check, a ground collision is altitude
below R, arrival is the first time within 0.5 m of the goal. Each companion's JSON log,
its stdout/stderr, the world's event log and trace stay in ``OUT/episodes/epNNN/``.

Every child is started in its own session and with a parent-death signal, so neither
Ctrl-C, a crashed child nor a killed evaluator leaves processes behind or ports taken.
"""

from __future__ import annotations

import ctypes
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from companion.spec import DEFAULT_CAMERA_SPEC, DEFAULT_TASK_SPEC, TaskSpec
from sitl.sim.metrics import OUTCOMES, UAVRecord
from sitl.realtime.camera_feed import DEFAULT_CAMERA_HZ
from sitl.realtime.depth_transport import DEPTH_BASE_PORT
from sitl.realtime.udp_endpoint import GCS_PORT, PX4_ONBOARD_BASE_PORT, MavlinkUdpEndpoint, mavlink
from sitl.sim.scenarios import ScenarioSample

START_MODES = ("ground", "airborne")


class MavlinkSwarmError(RuntimeError):
    """The MAVLink evaluation could not go on (a process died, never got ready, ...), with the reason."""


@dataclass(frozen=True)
class MavlinkSettings:
    """How the processes of a MAVLink episode are started and connected."""

    policy_path: str
    start: str = "ground"  # ground: companions arm and take off; airborne: vehicles start hovering
    base_port: int = PX4_ONBOARD_BASE_PORT  # companion i <-> vehicle i on base_port + i (PX4 SITL's onboard ports)
    depth_port: int = DEPTH_BASE_PORT  # vehicle i's depth frames to depth_port + i
    gcs_port: int = GCS_PORT  # every vehicle's ground-station link (this process)
    dynamics: str = "kinematic"
    camera_hz: float = DEFAULT_CAMERA_HZ
    camera_size: tuple[int, int] = (DEFAULT_CAMERA_SPEC.width, DEFAULT_CAMERA_SPEC.height)
    hfov_deg: float = DEFAULT_CAMERA_SPEC.hfov_deg
    max_range_m: float = DEFAULT_CAMERA_SPEC.max_range_m
    time_limit_s: float = 40.0  # after the goals are sent
    ready_timeout_s: float = 120.0  # start-up, arming and takeoff
    companion_threads: int = 1  # torch threads per companion: N of them share the machine
    governor: str | None = None  # companion --governor NAME (companion.governor.GOVERNOR_PRESETS); None: off
    face_goal_s: float | None = None  # companion --face-goal SECONDS (companion.face_goal); None: off
    task: TaskSpec = DEFAULT_TASK_SPEC  # collision and arrival radii the outcomes are scored with (the in-process run's)

    def __post_init__(self) -> None:
        if self.start not in START_MODES:
            raise ValueError(f"start must be one of {START_MODES}, got {self.start!r}")


@dataclass
class EpisodeResult:
    """One MAVLink episode: per-UAV records and what the processes cost."""

    records: list[UAVRecord]
    wall_s: float
    ready_s: float  # from starting the processes until all companions were ready
    companions: list[dict] = field(default_factory=list)  # per companion: CPU, deadline misses, latency
    world: dict = field(default_factory=dict)


def companion_command() -> list[str]:
    """The installed ``companion`` console script (the one next to this interpreter first)."""
    beside = Path(sys.executable).with_name("companion")
    if beside.is_file() and os.access(beside, os.X_OK):
        return [str(beside)]
    found = shutil.which("companion")
    if found:
        return [found]
    raise MavlinkSwarmError("the companion console script is not installed: run pip install -e . in this environment")


# --------------------------------------------------------------------------- processes

def _die_with_parent() -> None:
    """In the child: get SIGTERM when the evaluator dies, however it dies (Linux prctl)."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass  # not Linux: the finally-blocks still stop every child on a normal exit or Ctrl-C


def _cpu_seconds(pid: int) -> float | None:
    """User + system CPU time of a running process (Linux /proc), None where unavailable."""
    try:
        fields_ = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields_[11]) + int(fields_[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


class ProcessGroup:
    """Children started in their own sessions, watched, and always stopped."""

    def __init__(self) -> None:
        self.procs: dict[str, subprocess.Popen] = {}
        self.started_s: dict[str, float] = {}
        self.cpu_s: dict[str, float | None] = {}

    def start(self, name: str, argv: list[str], out_path: Path) -> subprocess.Popen:
        with open(out_path, "wb") as out:
            env = dict(os.environ, PYTHONUNBUFFERED="1")
            proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                                    start_new_session=True, preexec_fn=_die_with_parent)
        self.procs[name] = proc
        self.started_s[name] = time.monotonic()
        return proc

    def dead(self) -> list[tuple[str, int]]:
        """Children that have exited, with their exit codes."""
        return [(name, proc.returncode) for name, proc in self.procs.items() if proc.poll() is not None]

    def stop(self, names: list[str] | None = None, grace_s: float = 5.0) -> None:
        """SIGINT (a companion holds and exits cleanly), then SIGKILL whoever is still there."""
        names = list(self.procs) if names is None else names
        for name in names:
            proc = self.procs[name]
            if proc.poll() is None:
                self.cpu_s[name] = _cpu_seconds(proc.pid)
                self._signal(proc, signal.SIGINT)
        deadline = time.monotonic() + grace_s
        for name in names:
            proc = self.procs[name]
            try:
                proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self._signal(proc, signal.SIGKILL)
                proc.wait(timeout=5)

    def cpu_fraction(self, name: str) -> float | None:
        cpu = self.cpu_s.get(name)
        if cpu is None:
            return None
        return cpu / max(1e-6, time.monotonic() - self.started_s[name])

    @staticmethod
    def _signal(proc: subprocess.Popen, sig: int) -> None:
        try:
            os.killpg(proc.pid, sig)  # the whole session: nothing the child started survives it
        except ProcessLookupError:
            pass


# --------------------------------------------------------------------------- ground station

class GroundStationLink:
    """The evaluator's ground-station end: every vehicle's GCS link arrives on one UDP port.

    It learns each vehicle's address from its heartbeats (system id ``i + 1``) and sends
    run-time goals to the companion behind it (component 191), as a GCS operator would.
    """

    def __init__(self, port: int) -> None:
        self.mavlink = mavlink
        try:
            self.endpoint = MavlinkUdpEndpoint("gcs", ("127.0.0.1", port), 255, 190)
        except OSError as err:
            raise MavlinkSwarmError(f"ground-station port {port} is taken ({err}); choose another --gcs-port") from None

    @property
    def address(self) -> dict[int, tuple[str, int]]:
        """Where each system talks from (system id -> address)."""
        return self.endpoint.address_of

    def poll(self) -> None:
        """Read whatever arrived; remember where each system talks from."""
        self.endpoint.receive()

    def send_goal(self, vehicle: int, goal_ned: np.ndarray) -> None:
        self.endpoint.encoder_for(vehicle + 1).set_position_target_local_ned_send(
            0, vehicle + 1, 191, self.mavlink.MAV_FRAME_LOCAL_NED, 0b110111111000,
            float(goal_ned[0]), float(goal_ned[1]), float(goal_ned[2]), 0, 0, 0, 0, 0, 0, math.nan, math.nan)

    def close(self) -> None:
        self.endpoint.close()


# --------------------------------------------------------------------------- logs

class JsonLinesTail:
    """Read the records appended to a JSON-lines file since the last call."""

    def __init__(self, path: Path) -> None:
        self.path, self.offset, self.partial = path, 0, b""

    def read(self) -> list[dict]:
        try:
            with open(self.path, "rb") as f:
                f.seek(self.offset)
                chunk = f.read()
        except FileNotFoundError:
            return []
        self.offset += len(chunk)
        lines = (self.partial + chunk).split(b"\n")
        self.partial = lines.pop()
        out = []
        for line in lines:
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                continue
        return out


def _companion_stats(log_path: Path, groups: ProcessGroup, name: str) -> dict:
    """CPU share, deadline misses and latency from a companion's final summary line."""
    summary: dict = {}
    for record in JsonLinesTail(log_path).read():
        if record.get("kind") == "summary" or "missed_ticks" in record:
            summary = record
    cpu = groups.cpu_fraction(name)
    return {"name": name, "cpu_fraction": None if cpu is None else round(cpu, 4),
            "missed_ticks": summary.get("missed_ticks"), "overruns": summary.get("overruns"),
            "policy_steps": summary.get("policy_steps"), "holds": summary.get("holds"),
            "frame_to_setpoint_ms": summary.get("frame_to_setpoint_ms"),
            "tick_late_ms": summary.get("tick_late_ms"), "exit_code": groups.procs[name].returncode}


# --------------------------------------------------------------------------- one episode

def fly_episode(sample: ScenarioSample, episode: int, settings: MavlinkSettings, folder: Path,
                status=lambda text: None) -> EpisodeResult:
    """Fly one episode of ``sample`` with N real processes in real time; see the module docstring."""
    n = len(sample.start_ned)
    folder.mkdir(parents=True, exist_ok=True)
    starts = sample.start_ned.copy()
    if settings.start == "ground":
        starts[:, 2] = 0.0
    (folder / "starts.json").write_text(json.dumps(
        [{"ned": s.tolist(), "yaw_deg": math.degrees(float(y))} for s, y in zip(starts, sample.yaw_rad)]))
    groups = ProcessGroup()
    gcs = GroundStationLink(settings.gcs_port)
    started = time.monotonic()
    try:
        world_args = [sys.executable, "-m", "sitl.vehicle", "--n", str(n), "--starts", str(folder / "starts.json"),
                      "--base-port", str(settings.base_port), "--depth-port", str(settings.depth_port),
                      "--gcs-port", str(settings.gcs_port), "--log", str(folder / "vehicle.jsonl"),
                      "--trace", str(folder / "trace.jsonl"), "--dynamics", settings.dynamics,
                      "--camera-hz", f"{settings.camera_hz:g}",
                      "--camera-size", f"{settings.camera_size[0]}x{settings.camera_size[1]}",
                      "--hfov", f"{settings.hfov_deg:g}", "--max-range", f"{settings.max_range_m:g}"]
        if settings.start == "airborne":
            world_args.append("--airborne")
        groups.start("world", world_args, folder / "vehicle.out")
        _wait_world_ready(groups, folder, settings.ready_timeout_s)

        names = [f"companion_{i}" for i in range(n)]
        for i, name in enumerate(names):
            args = [*companion_command(), "--connect", f"udpin:127.0.0.1:{settings.base_port + i}",
                    "--model", settings.policy_path, "--camera", f"sitl:{settings.depth_port + i}",
                    "--log", str(folder / f"{name}.jsonl"), "--heartbeat-timeout", "60", "--arm",
                    # the climb from the ground (the companion skips it for a vehicle already airborne,
                    # --start airborne, but its command line asks for the altitude with every --arm)
                    "--takeoff", f"{-sample.start_ned[i, 2]:.2f}"]
            if settings.governor:
                args += ["--governor", settings.governor]
            if settings.face_goal_s is not None:
                args += ["--face-goal", f"{settings.face_goal_s:g}"]
            groups.start(name, args, folder / f"{name}.out")
        status(f"episode {episode}: {n} companions starting")
        _wait_companions_ready(groups, gcs, folder, names, started + settings.ready_timeout_s, status, episode)
        ready_s = time.monotonic() - started

        t0 = time.time()
        for _ in range(3):  # three copies 50 ms apart: a lost datagram must not cost a UAV its episode
            for i in range(n):
                gcs.send_goal(i, sample.goal_ned[i])
            time.sleep(0.05)
        status(f"episode {episode}: goals sent, flying")
        trace = _follow_flight(groups, gcs, folder, sample, t0, settings.time_limit_s, names, settings.task)
    except KeyboardInterrupt:
        status("interrupted: stopping every process")
        raise
    finally:
        groups.stop([name for name in groups.procs if name != "world"])
        groups.stop(["world"] if "world" in groups.procs else [])
        gcs.close()
    crashes = {int(r["vehicle"]): (float(r["t"]), str(r.get("outcome", "")))
               for r in JsonLinesTail(folder / "vehicle.jsonl").read() if r.get("event") == "crash"}
    records = _records_from_trace(trace, crashes, sample, t0, episode, settings.time_limit_s, settings.task)
    companions = [_companion_stats(folder / f"{name}.jsonl", groups, name) for name in names]
    world = {"cpu_fraction": groups.cpu_fraction("world"),
             "physics_overruns": sum(1 for r in JsonLinesTail(folder / "vehicle.jsonl").read()
                                     if r.get("event") == "overrun")}
    return EpisodeResult(records, time.monotonic() - started, ready_s, companions, world)


def _check_alive(groups: ProcessGroup, folder: Path, allowed: tuple[str, ...] = ()) -> None:
    for name, code in groups.dead():
        if name in allowed:
            continue
        log = folder / f"{'vehicle' if name == 'world' else name}.out"
        tail = ""
        try:
            tail = log.read_text(errors="replace").strip().splitlines()[-1][:300]
        except (OSError, IndexError):
            pass
        raise MavlinkSwarmError(f"{name} exited with code {code} ({tail or 'no output'}); logs in {folder}")


def _wait_world_ready(groups: ProcessGroup, folder: Path, timeout_s: float) -> None:
    tail = JsonLinesTail(folder / "vehicle.jsonl")
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if any(r.get("event") == "ready" for r in tail.read()):
            return
        _check_alive(groups, folder)
        time.sleep(0.1)
    raise MavlinkSwarmError(f"the SITL world did not get ready within {timeout_s:g} s; logs in {folder}")


def _wait_companions_ready(groups: ProcessGroup, gcs: GroundStationLink, folder: Path, names: list[str],
                           deadline: float, status, episode: int) -> None:
    """Until every companion flies (holding without a goal) and every vehicle's GCS address is known."""
    tails = {name: JsonLinesTail(folder / f"{name}.jsonl") for name in names}
    phase = dict.fromkeys(names, "starting")
    last_note = 0.0
    while True:
        gcs.poll()
        for name, tail in tails.items():
            for record in tail.read():
                if record.get("event") == "phase" and record.get("to"):
                    phase[name] = record["to"]
        _check_alive(groups, folder)
        waiting = [name for name in names if phase[name] != "flying_to_goal"]
        unknown = [i for i in range(len(names)) if i + 1 not in gcs.address]
        if not waiting and not unknown:
            return
        now = time.monotonic()
        if now > deadline:
            detail = ", ".join(f"{name}: {phase[name]}" for name in waiting) or \
                     f"no ground-station link from vehicles {unknown}"
            raise MavlinkSwarmError(f"episode {episode}: not ready in time ({detail}); logs in {folder}")
        if now - last_note > 2.0:
            counts: dict[str, int] = {}
            for p in phase.values():
                counts[p] = counts.get(p, 0) + 1
            status(f"episode {episode}: " + ", ".join(f"{c} {p}" for p, c in sorted(counts.items())))
            last_note = now
        time.sleep(0.05)


def _follow_flight(groups: ProcessGroup, gcs: GroundStationLink, folder: Path, sample: ScenarioSample, t0: float,
                   time_limit_s: float, names: list[str], task: TaskSpec = DEFAULT_TASK_SPEC) -> list[dict]:
    """Watch the ground truth until every UAV has arrived or crashed, or the time limit."""
    tail = JsonLinesTail(folder / "trace.jsonl")
    trace: list[dict] = []
    n = len(names)
    done = np.zeros(n, dtype=bool)
    while True:
        gcs.poll()  # keep the socket drained
        for record in tail.read():
            trace.append(record)
            if record["t"] < t0:
                continue
            pos = np.asarray(record["pos_ned"])
            arrived = np.linalg.norm(pos - sample.goal_ned, axis=1) < task.arrival_radius_m
            done |= arrived | np.asarray(record["crashed"]) | (-pos[:, 2] < task.collision_radius_m)
        _check_alive(groups, folder)
        if done.all() or time.time() - t0 > time_limit_s + 0.2:
            return trace
        time.sleep(0.05)


def _records_from_trace(trace: list[dict], crashes: dict[int, tuple[float, str]], sample: ScenarioSample,
                        t0: float, episode: int, time_limit_s: float,
                        task: TaskSpec = DEFAULT_TASK_SPEC) -> list[UAVRecord]:
    """Per-UAV outcomes and paths from the world's ground truth, with the in-process definitions.

    ``crashes`` maps a vehicle to the time and outcome code (``collision_uav`` or
    ``collision_ground``) of its crash event in the world's log.
    """
    flight = [r for r in trace if t0 <= r["t"] <= t0 + time_limit_s]
    n = len(sample.goal_ned)
    if not flight:
        raise MavlinkSwarmError(f"episode {episode}: the world's trace has no samples after the goals were sent")
    before = [r for r in trace if r["t"] < t0]
    start = np.asarray((before[-1] if before else flight[0])["pos_ned"])
    records = []
    for i in range(n):
        path = [start[i]]
        outcome, end_t = "timeout", flight[-1]["t"]
        for r in flight:
            p = np.asarray(r["pos_ned"][i])
            path.append(p)
            if r["crashed"][i]:
                crash_t, outcome = crashes.get(i, (r["t"], "collision_ground"))
                if outcome not in OUTCOMES:
                    raise MavlinkSwarmError(f"episode {episode}: vehicle {i}'s crash has no outcome code ({outcome!r})")
                end_t = min(crash_t, r["t"])
                break
            if -p[2] < task.collision_radius_m:
                outcome, end_t = "collision_ground", r["t"]
                break
            if np.linalg.norm(p - sample.goal_ned[i]) < task.arrival_radius_m:
                outcome, end_t = "arrived", r["t"]
                break
        path_arr = np.asarray(path)
        records.append(UAVRecord(
            episode=episode, uav=i, start_ned=start[i].tolist(), goal_ned=sample.goal_ned[i].tolist(),
            outcome=outcome, path_length_m=float(np.linalg.norm(np.diff(path_arr, axis=0), axis=1).sum()),
            straight_distance_m=float(np.linalg.norm(sample.goal_ned[i] - start[i])),
            duration_s=float(end_t - t0), path_ned=path_arr.round(3).tolist()))
    return records


# --------------------------------------------------------------------------- many episodes

@dataclass
class MavlinkEvaluation:
    """Every episode of a MAVLink evaluation."""

    records: list[UAVRecord]
    episodes: list[EpisodeResult]
    wall_s: float

    def costs(self) -> dict:
        """What the stack cost per episode: CPU per companion, deadline misses, latency, start-up."""
        comps = [c for e in self.episodes for c in e.companions]
        cpu = [c["cpu_fraction"] for c in comps if c["cpu_fraction"] is not None]
        p99 = [c["frame_to_setpoint_ms"]["p99"] for c in comps
               if c.get("frame_to_setpoint_ms") and c["frame_to_setpoint_ms"].get("p99") is not None]
        missed = [c["missed_ticks"] for c in comps if c["missed_ticks"] is not None]
        steps = [c["policy_steps"] for c in comps if c["policy_steps"] is not None]
        world_cpu = [e.world["cpu_fraction"] for e in self.episodes if e.world.get("cpu_fraction") is not None]
        return {
            "companion_cpu_fraction_median": _median(cpu),
            "companion_cpu_fraction_max": max(cpu) if cpu else None,
            "missed_ticks_total": int(sum(missed)), "policy_steps_total": int(sum(steps)),
            "missed_tick_fraction": (sum(missed) / max(1, sum(missed) + sum(steps))) if steps else None,
            "frame_to_setpoint_p99_ms_median": _median(p99),
            "frame_to_setpoint_p99_ms_max": max(p99) if p99 else None,
            "world_cpu_fraction_median": _median(world_cpu),
            "world_physics_overruns": int(sum(e.world.get("physics_overruns", 0) for e in self.episodes)),
            "ready_s_median": _median([e.ready_s for e in self.episodes]),
            "episode_wall_s_median": _median([e.wall_s for e in self.episodes]),
        }


def _median(values: list[float]) -> float | None:
    return round(float(np.median(values)), 4) if values else None


def evaluate_over_mavlink(samples: list[ScenarioSample], settings: MavlinkSettings, out: Path,
                          progress: bool = True) -> MavlinkEvaluation:
    """Fly each sample as one real-time MAVLink episode; logs go to ``out/episodes/epNNN``."""
    from tqdm import tqdm

    companion_command()  # fail before starting anything if the console script is missing
    started = time.monotonic()
    records: list[UAVRecord] = []
    episodes: list[EpisodeResult] = []
    with tqdm(total=len(samples), unit="episode", desc="MAVLink", disable=not progress, file=sys.stderr,
              dynamic_ncols=True) as bar:
        for k, sample in enumerate(samples):
            result = fly_episode(sample, k, settings, out / "episodes" / f"ep{k:03d}",
                                 status=lambda text: bar.set_postfix_str(text[-60:]))
            episodes.append(result)
            records += result.records
            bar.update(1)
    return MavlinkEvaluation(records, episodes, time.monotonic() - started)
