"""Shared pieces of the companion and vehicle tests: test policies, processes, a ground station.

Every process a test starts goes through :class:`Processes`, which stops them all (SIGTERM,
then SIGKILL) when the test ends, passed or failed. Ports are picked free per test, on
127.0.0.1 only, so tests can run in parallel.
"""

from __future__ import annotations

import json
import math
import os
import random
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

os.environ["MAVLINK20"] = "1"

import torch  # noqa: E402
from torch import nn  # noqa: E402

from companion.governor import GovernorSpec  # noqa: E402
from companion.policy import build_metadata, save_policy  # noqa: E402
from companion.spec import REALSENSE_D435, ActionSpec, CameraSpec, MemorySpec, state_names_for  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CONTROL_PERIOD_S = 0.1


# --------------------------------------------------------------------------- test policies


class GoalSeeker(nn.Module):
    """Flies at the goal using only ``state``: turn towards it, slow down near it. Clamped to bounds."""

    def __init__(self, low: list[float], high: list[float], nan_above_speed: float = 0.0,
                 brake_depth_m: float = 0.0) -> None:
        super().__init__()
        self.register_buffer("low", torch.tensor(low, dtype=torch.float32))
        self.register_buffer("high", torch.tensor(high, dtype=torch.float32))
        self.nan_above_speed = nan_above_speed  # != 0: output NaN once flying faster (NaN failsafe test)
        self.brake_depth_m = brake_depth_m  # > 0: stop when the image centre is nearer (uses depth)

    def forward(self, depth: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        goal_fwd, goal_right, goal_down = state[:, 0], state[:, 1], state[:, 2]
        bearing = torch.atan2(goal_right, goal_fwd)
        fwd = 0.8 * goal_fwd * torch.clamp(1.0 - bearing.abs(), min=0.0)
        yaw_rate = 1.5 * bearing
        down = 0.8 * goal_down
        if self.brake_depth_m > 0:
            h, w = depth.shape[2], depth.shape[3]
            centre = depth[:, -1, h // 4: 3 * h // 4, w // 4: 3 * w // 4].amin(dim=(1, 2))
            fwd = torch.where(centre < self.brake_depth_m, torch.zeros_like(fwd), fwd)
        action = torch.stack([fwd, down, yaw_rate], dim=1)
        action = torch.maximum(torch.minimum(action, self.high), self.low)
        if self.nan_above_speed != 0.0:
            action = torch.where(state[:, 3:4] > self.nan_above_speed, torch.full_like(action, float("nan")), action)
        return action


class RememberingTurner(nn.Module):
    """A policy with remembered depth (``MemorySpec``): forward at 1 m/s until something is remembered
    within ``turn_m`` at its own level (state columns ``level``), then it stops and turns right."""

    def __init__(self, low: list[float], high: list[float], level: tuple[int, int], turn_m: float) -> None:
        super().__init__()
        self.register_buffer("low", torch.tensor(low, dtype=torch.float32))
        self.register_buffer("high", torch.tensor(high, dtype=torch.float32))
        self.first, self.last = level
        self.turn_m = turn_m

    def forward(self, depth: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        near = state[:, self.first:self.last].amin(dim=1) < self.turn_m
        fwd = torch.where(near, torch.zeros_like(state[:, 0]), torch.ones_like(state[:, 0]))
        yaw_rate = torch.where(near, torch.full_like(fwd, 0.5), torch.zeros_like(fwd))
        action = torch.stack([fwd, 0.8 * state[:, 2], yaw_rate], dim=1)
        return torch.maximum(torch.minimum(action, self.high), self.low)


def make_policy(path: Path, *, period_s: float = CONTROL_PERIOD_S, camera: CameraSpec | None = None,
                nan_above_speed: float = 0.0, brake_depth_m: float = 0.0, governor: GovernorSpec | None = None,
                memory: MemorySpec | None = None, turn_m: float = 3.5) -> Path:
    """Save a contract-following TorchScript test policy at ``path`` (default camera: the D435 preset,
    what ``sitl.vehicle`` carries by default; ``governor``: declared as trained with it). With ``memory``
    the policy is a :class:`RememberingTurner` (turning within ``turn_m``), else a :class:`GoalSeeker`."""
    camera = camera or REALSENSE_D435
    action = ActionSpec()
    if memory is not None:
        names = state_names_for(memory)
        level = [i for i, name in enumerate(names) if name.startswith("memory_level_")]
        module = RememberingTurner(list(action.low), list(action.high), (level[0], level[-1] + 1), turn_m)
    else:
        module = GoalSeeker(list(action.low), list(action.high), nan_above_speed, brake_depth_m)
    provenance = {"method": "test goal seeker", "scenario": "none", "steps": 0, "wall_time_s": 0.0,
                  "git_commit": "test", "evaluation": {}}
    save_policy(module, build_metadata(camera, action, period_s, provenance, governor=governor, memory=memory), path)
    return path


# --------------------------------------------------------------------------- ports and processes


def _ephemeral_low() -> int:
    try:
        return int(open("/proc/sys/net/ipv4/ip_local_port_range").read().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 nobody listens on, below the ephemeral range."""
    rng = random.Random(os.getpid() ^ time.monotonic_ns())
    while True:
        port = rng.randrange(41000, 45000)
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
        return port


#: every port free_udp_ports has handed out in this process
_HANDED_OUT: set[int] = set()


def free_udp_ports(count: int) -> list[int]:
    """``count`` free UDP ports on 127.0.0.1, below the ephemeral range.

    Ports handed out by bind(0) could be taken again by another process's ephemeral socket
    (our vehicles bind several) before the companion binds them; ports below the ephemeral
    range are only ever taken on purpose.
    """
    rng = random.Random(os.getpid() ^ time.monotonic_ns())
    low, high = 20000, min(_ephemeral_low(), 32000)
    ports: list[int] = []
    while len(ports) < count:
        port = rng.randrange(low, high)
        # never the same port twice in one test session: a free port handed to one test's vehicle
        # is not bound until it starts, and another test must not be given it meanwhile
        if port in ports or port in _HANDED_OUT or port in (14540, 14550, 14640):
            continue
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
        ports.append(port)
    _HANDED_OUT.update(ports)
    return ports


def free_udp_blocks(*sizes: int, low: int = 33000, high: int = 40000) -> list[int]:
    """The first port of each of ``sizes`` runs of consecutive free UDP ports on 127.0.0.1.

    By default from 33000..39999, a range ``free_udp_ports`` (20000..32000) and the
    PX4 defaults (14540..14650) never use.
    """
    rng = random.Random(os.getpid() ^ time.monotonic_ns())
    taken: set[int] = set()
    firsts = []
    for size in sizes:
        while True:
            first = rng.randrange(low, high - size)
            block = set(range(first, first + size))
            if block & taken or not all(udp_port_free(p) for p in block):
                continue
            taken |= block
            firsts.append(first)
            break
    return firsts


def udp_port_free(port: int) -> bool:
    """Whether UDP ``port`` on 127.0.0.1 can be bound right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def env() -> dict:
    e = dict(os.environ)
    e["PYTHONPATH"] = str(REPO) + (os.pathsep + e["PYTHONPATH"] if e.get("PYTHONPATH") else "")
    e["OMP_NUM_THREADS"] = "1"
    e["NUMBA_NUM_THREADS"] = "1"
    e.pop("NOTIFY_SOCKET", None)
    return e


class Processes:
    """Starts processes for one test and guarantees they are stopped."""

    def __init__(self, tmp_path: Path) -> None:
        self.tmp_path = tmp_path
        self.procs: list[tuple[str, subprocess.Popen]] = []

    def start(self, name: str, args: list[str], extra_env: dict | None = None,
              prefix: tuple[str, ...] = ()) -> subprocess.Popen:
        """``python ARGS`` (after ``prefix``, e.g. ``chrt -f 20``) in its own process group; output in NAME.out/.err."""
        e = env()
        if extra_env:
            e.update(extra_env)
        out = open(self.tmp_path / f"{name}.out", "wb")  # noqa: SIM115
        err = open(self.tmp_path / f"{name}.err", "wb")  # noqa: SIM115
        proc = subprocess.Popen([*prefix, sys.executable, *args], cwd=REPO, env=e, stdout=out, stderr=err,
                                start_new_session=True)
        out.close()
        err.close()
        self.procs.append((name, proc))
        return proc

    def stderr(self, name: str) -> str:
        return (self.tmp_path / f"{name}.err").read_text(errors="replace")

    def stop_all(self, grace_s: float = 3.0, newest_first: bool = False) -> None:
        """SIGTERM every process group still running, SIGKILL what is left after ``grace_s``.

        By default all at once. ``newest_first``: one at a time from the last started, each
        given ``grace_s`` (a companion must hand its vehicle over before the vehicle goes).
        """
        if newest_first:
            for _name, proc in reversed(self.procs):
                self._terminate([proc], grace_s)
        else:
            self._terminate([proc for _name, proc in self.procs], grace_s)

    @staticmethod
    def _terminate(procs: list[subprocess.Popen], grace_s: float) -> None:
        for proc in procs:
            if proc.poll() is None:
                try:
                    os.killpg(proc.pid, signal.SIGTERM)
                except ProcessLookupError:
                    pass
        deadline = time.monotonic() + grace_s
        for proc in procs:
            try:
                proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                try:
                    os.killpg(proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                proc.wait(timeout=5)

    def __enter__(self) -> "Processes":
        return self

    def __exit__(self, *exc) -> None:
        self.stop_all()


class Rig:
    """One simulated vehicle + its companion, on free ports, with a ground station."""

    def __init__(self, procs: Processes, tmp_path: Path) -> None:
        self.procs, self.tmp_path = procs, tmp_path
        self.mav_port, self.depth_port, self.gcs_port = free_udp_ports(3)
        self.vehicle_log = tmp_path / "vehicle.jsonl"
        self.companion_log = tmp_path / "companion.jsonl"
        self.vehicle: subprocess.Popen | None = None
        self.companion: subprocess.Popen | None = None

    def start_vehicle(self, *extra: str, gcs: bool = True) -> subprocess.Popen:
        args = ["-m", "sitl.vehicle", "--n", "1", "--base-port", str(self.mav_port), "--depth-port", str(self.depth_port),
                "--gcs-port", str(self.gcs_port if gcs else 0), "--log", str(self.vehicle_log), "--duration", "180", *extra]
        self.vehicle = self.procs.start("vehicle", args)
        return self.vehicle

    def stop_vehicle(self) -> None:
        """SIGTERM the vehicle and wait for it (the same ports can then host a new one)."""
        if self.vehicle is not None and self.vehicle.poll() is None:
            os.killpg(self.vehicle.pid, signal.SIGTERM)
            self.vehicle.wait(timeout=10)

    def start_companion(self, model: Path, *extra: str, extra_env: dict | None = None) -> subprocess.Popen:
        args = ["-m", "companion.cli", "--connect", f"udpin:127.0.0.1:{self.mav_port}", "--model", str(model),
                "--camera", f"sitl:{self.depth_port}", "--log", str(self.companion_log), "--heartbeat-timeout", "20",
                *extra]
        self.companion = self.procs.start("companion", args, extra_env)
        return self.companion

    def companion_records(self) -> list[dict]:
        return read_jsonl(self.companion_log)

    def vehicle_records(self) -> list[dict]:
        return read_jsonl(self.vehicle_log)

    def wait_companion(self, timeout_s: float) -> int:
        try:
            return self.companion.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"companion did not exit within {timeout_s} s; stderr:\n{self.procs.stderr('companion')[-3000:]}") from None

    def wait_for_event(self, predicate, timeout_s: float, what: str) -> dict:
        """Poll the companion log until a record satisfies ``predicate``; return it."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for record in self.companion_records():
                if predicate(record):
                    return record
            if self.companion is not None and self.companion.poll() is not None:
                break
            time.sleep(0.1)
        steps = [r for r in self.companion_records() if r.get("kind") == "step"]
        raise AssertionError(f"companion never logged {what}; last step: {steps[-1] if steps else None}\n"
                             f"stderr:\n{self.procs.stderr('companion')[-3000:]}\n"
                             f"vehicle stderr:\n{self.procs.stderr('vehicle')[-2000:]}")

    def wait_flying(self, timeout_s: float = 30.0) -> dict:
        """Wait until the policy has sent a few steps of motion."""
        return self.wait_for_event(lambda r: r.get("kind") == "step" and r.get("phase") == "flying_to_goal"
                                   and r.get("sent") and not r.get("hold") and r.get("step", 0) > 0
                                   and (r.get("cmd") or [0])[0] > 0.3, timeout_s, "a policy step flying forward")


def read_jsonl(path: Path) -> list[dict]:
    if not path.exists():
        return []
    out = []
    for line in path.read_text(errors="replace").splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            pass  # a line being written
    return out


# --------------------------------------------------------------------------- a ground station


class GroundStation:
    """A minimal GCS on pymavlink: listens where the vehicle sends its ground-station link."""

    def __init__(self, port: int, signing_key: bytes | None = None) -> None:
        from pymavlink import mavutil

        mavutil.set_dialect("common")
        self.mavutil = mavutil
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255, source_component=190,
                                               dialect="common")
        if signing_key is not None:
            self.conn.setup_signing(signing_key, sign_outgoing=True, link_id=7)
        self.mav = self.conn.mav

    def wait_heartbeat(self, timeout_s: float = 20.0):
        msg = self.conn.wait_heartbeat(timeout=timeout_s)
        assert msg is not None, "no heartbeat from the vehicle on the ground-station link"
        return msg

    def drain(self) -> None:
        """Drop the telemetry queued while nobody read (a full socket buffer drops new datagrams)."""
        while self.conn.recv_match(blocking=False) is not None:
            pass

    def command(self, command: int, *params: float, attempts: int = 3) -> int:
        """Send COMMAND_LONG to the autopilot (1/1) and return its COMMAND_ACK result.

        Like a real ground station it resends after 1 s without an answer (UDP may drop).
        """
        padded = list(params) + [0.0] * (7 - len(params))
        self.drain()
        for attempt in range(attempts):
            self.mav.command_long_send(1, 1, command, attempt, *padded)
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline:
                msg = self.conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.2)
                if msg is not None and msg.command == command:
                    return msg.result
        raise AssertionError(f"no COMMAND_ACK for command {command} after {attempts} attempts")

    def send_goal(self, north: float, east: float, down: float) -> None:
        """The run-time goal: SET_POSITION_TARGET_LOCAL_NED to the companion (component 191)."""
        self.drain()
        self.mav.set_position_target_local_ned_send(0, 1, 191, 1, 0b110111111000, north, east, down,
                                                    0, 0, 0, 0, 0, 0, math.nan, math.nan)

    def close(self) -> None:
        self.conn.close()


# --------------------------------------------------------------------------- concurrent scenarios


def scenario(*names: str):
    """Mark a test as flying the pre-started scenarios ``names`` (see :class:`ScenarioPool`)."""
    def mark(fn):
        fn.scenarios = names
        return fn
    return mark


class ScenarioPool:
    """Starts the vehicle + companion of every selected test of a module at once.

    Real-time flights dominate these tests, so starting them together lets their start-up,
    engagement and flying overlap instead of adding up. Each scenario has its own processes,
    ports and folder; each test then drives and checks its own rig. :meth:`stop_all` (the
    module fixture's finalizer) stops every process, whatever happened in the tests.
    """

    def __init__(self, request, tmp_path_factory, starters: dict) -> None:
        module = request.module
        wanted = {name for item in request.session.items if item.module is module
                  for name in getattr(item.function, "scenarios", ())}
        self.rigs: dict[str, Rig] = {}
        self.procs: list[Processes] = []
        try:
            for name, start in starters.items():
                if name not in wanted:
                    continue
                tmp = tmp_path_factory.mktemp(name)
                procs = Processes(tmp)
                self.procs.append(procs)
                rig = Rig(procs, tmp)
                start(rig, tmp)
                self.rigs[name] = rig
        except BaseException:
            self.stop_all()
            raise

    def __getitem__(self, name: str) -> Rig:
        return self.rigs[name]

    def stop_all(self) -> None:
        for procs in self.procs:
            procs.stop_all()
