"""Kinematic quadrotor: velocity commands tracked by a first-order lag with acceleration limits.

This is what a multicopter's velocity controller looks like from outside: the commanded
body-frame velocity is rotated into NED with the current heading, and the NED velocity
approaches it with time constant ``tau`` while its acceleration is capped (horizontal and
vertical separately), as PX4's ``MPC_ACC_HOR`` / ``MPC_ACC_UP_MAX`` do. Velocity lives in
NED, so a UAV that turns keeps part of its old velocity for a moment — it slides through
turns as a real multicopter does. Yaw rate follows the same law with its own limits.

Optionally the horizontal loop is a PI controller flying against linear air drag, which is how
PX4's velocity controller (P, I on the velocity error) meets a real airframe: with drag
``kd`` (1/s) and integral gain ``ki`` (1/s^2), the acceleration is
``clip((v_cmd - v) / tau + ki z) - kd v`` with ``z`` the integrated error (frozen while the
controller output is capped). A step then gets only ``1 / (1 + kd tau)`` of the commanded speed
quickly and the rest slowly, as the integrator builds up (time constant ~``(1/tau + kd) / ki``).
PX4 SIH's default airframe flies like this (fit in docs/real_autopilots.md); ``kd = ki = 0``
(the default) is the plain lag.

A pure command delay ``command_delay_s`` (0: none) makes each UAV act on the command it was sent that
long ago, rounded up to the integration sub-step (zero-order hold between control periods; ``step`` must then be
called with the same ``dt_s`` every time, as the env and ``sitl.vehicle`` do): the time a real airframe needs to tilt before it
accelerates, and the link's latency. A JSBSim F450 behaves like ~0.15 s of it from rest, PX4 SIH's
vehicles fit 0-0.25 s (docs/results.md "Why JSBSim costs points"). Before its first command a UAV holds
(a zero command), as an autopilot does before its first setpoint.
Integration is explicit Euler on ``substep_s`` sub-steps of each control period.

Every UAV has its own response (arrays in the backend): nominal :class:`KinematicParams` by
default; :meth:`KinematicDynamics.randomize` draws each UAV's time constants and acceleration
limits from a :class:`KinematicRandomization` (training: a policy must not rely on one airframe).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numba
import numpy as np

from sitl.sim.dynamics.base import Dynamics


#: The longest command delay a response may have, s (the command history kept grows with it: ceil(delay / dt_s) + 1
#: periods).
MAX_COMMAND_DELAY_S = 1.0


@dataclass(frozen=True)
class KinematicParams:
    """Response of the velocity controller (defaults close to PX4's multicopter defaults)."""

    tau_horizontal_s: float = 0.25
    tau_vertical_s: float = 0.25
    tau_yaw_s: float = 0.15
    max_acc_horizontal_m_s2: float = 3.0
    max_acc_vertical_m_s2: float = 2.0
    max_yaw_acc_rad_s2: float = 3.0
    drag_horizontal_per_s: float = 0.0  # linear air drag over mass, 1/s (0: none)
    integral_horizontal_per_s2: float = 0.0  # the velocity loop's integral gain, 1/s^2 (0: none)
    command_delay_s: float = 0.0  # each command acts this long after it was sent (up to a sub-step later), s (0: none)
    substep_s: float = 0.02

    def __post_init__(self) -> None:
        if not 0.0 <= self.command_delay_s <= MAX_COMMAND_DELAY_S:  # NaN fails too
            raise ValueError(f"command_delay_s must be in [0, {MAX_COMMAND_DELAY_S:g}] s, got {self.command_delay_s}")


@dataclass(frozen=True)
class KinematicRandomization:
    """Ranges (low, high) from which each UAV's response is drawn uniformly, per UAV and episode.

    Based on real multicopters: PX4's velocity-mode acceleration ``MPC_ACC_HOR_MAX`` defaults to
    5 m/s^2 and ``MPC_ACC_HOR`` to 3 (hobby setups lower it to ~2), ``MPC_ACC_UP_MAX`` 4 and
    ``MPC_ACC_DOWN_MAX`` 3; ArduPilot's ``WPNAV_ACCEL`` 2.5 m/s^2. The velocity loop's lag: the
    JSBSim F450 (``sitl.sim.dynamics.jsbsim_quad``) rises 10-90 % in 0.61 s, a first-order lag of
    ~0.28 s; a stiffly tuned 250-class racer is near 0.15 s, a loaded 5 kg hexacopter near 0.5 s.
    """

    tau_horizontal_s: tuple[float, float] = (0.15, 0.5)
    tau_vertical_s: tuple[float, float] = (0.15, 0.5)
    tau_yaw_s: tuple[float, float] = (0.1, 0.3)
    max_acc_horizontal_m_s2: tuple[float, float] = (2.0, 5.0)
    max_acc_vertical_m_s2: tuple[float, float] = (1.0, 4.0)
    max_yaw_acc_rad_s2: tuple[float, float] = (2.0, 4.0)
    drag_horizontal_per_s: tuple[float, float] = (0.0, 0.0)
    integral_horizontal_per_s2: tuple[float, float] = (0.0, 0.0)
    command_delay_s: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        for name in _RESPONSE_FIELDS:
            lo, hi = getattr(self, name)
            may_be_zero = name in _MAY_BE_ZERO
            most = MAX_COMMAND_DELAY_S if name == "command_delay_s" else 1000.0
            if not ((lo >= 0.0) if may_be_zero else (lo > 0.0)) or not lo <= hi <= most:
                least = "0 <= low" if may_be_zero else "0 < low"
                raise ValueError(f"{name} must be (low, high) with {least} <= high <= {most:g}, got {(lo, hi)}")
            object.__setattr__(self, name, (float(lo), float(hi)))


#: The per-UAV fields of the velocity law, in the order :func:`_integrate` takes them.
_LAW_FIELDS = ("tau_horizontal_s", "tau_vertical_s", "tau_yaw_s", "max_acc_horizontal_m_s2",
               "max_acc_vertical_m_s2", "max_yaw_acc_rad_s2", "drag_horizontal_per_s",
               "integral_horizontal_per_s2")
#: The per-UAV response fields shared by KinematicParams and KinematicRandomization: the law's, then the
#: command delay (applied before the law, in :meth:`KinematicDynamics.step`). A range that is off (high 0) draws
#: nothing, so runs without a delay fly the episodes they did; new fields go last, so that the others' draws keep
#: their order when one is drawn.
_RESPONSE_FIELDS = (*_LAW_FIELDS, "command_delay_s")
#: The fields that may be 0 (off); the others are time constants and limits, > 0.
_MAY_BE_ZERO = ("drag_horizontal_per_s", "integral_horizontal_per_s2", "command_delay_s")


#: Named per-UAV response ranges for ``--response`` (:func:`parse_response`).
#: ``px4-sih``: PX4 SIH's default quadrotor (sihsim_quadx) as fitted in five circles of 8 flown by
#: ``sitl.real_autopilots`` on an idle machine (``python -m sitl.real_autopilots fit``; docs/real_autopilots.md
#: "Fitting each vehicle's response"): 38-39 of the 40 vehicle fits lie inside each range (all of them: lag
#: 0.7-1.05 s, drag 0.15-0.8 /s, integral 0-0.4 /s^2, vertical lag 0.05-0.3 s). Flown again in session 59 with PX4's
#: heading estimate corrected (``PX4_SIH_PARAMS``), the 128 fits of 16 runs whose companions kept up spanned lag
#: 0.7-1.05 s, drag 0.35-0.85 /s, integral 0.1-0.3 /s^2, vertical lag 0.05-0.35 s: the same ranges.
#: The preset leaves out the delay those fits also found (0-0.25 s, ``command_delay_s``): its cell
#: (``circle-n8-px4-sih``) and the runs trained with it keep the response they were measured with; add
#: ``command_delay_s=0:0.2`` to the specification to fly it.
RESPONSE_PRESETS: dict[str, dict[str, tuple[float, float]]] = {
    "px4-sih": {"tau_horizontal_s": (0.7, 1.0), "drag_horizontal_per_s": (0.3, 0.8),
                "integral_horizontal_per_s2": (0.1, 0.3), "tau_vertical_s": (0.1, 0.3)},
}


def nominal_ranges(params: KinematicParams = KinematicParams()) -> KinematicRandomization:
    """Ranges that draw every UAV at ``params`` (the base an evaluation's ``--response`` is layered over)."""
    return KinematicRandomization(**{name: (getattr(params, name),) * 2 for name in _RESPONSE_FIELDS})


def parse_response(text: str, base: KinematicRandomization) -> KinematicRandomization:
    """``base`` with the ranges named in ``text`` replaced: comma-separated items, each a preset of
    :data:`RESPONSE_PRESETS` or ``FIELD=LOW:HIGH`` / ``FIELD=VALUE`` with FIELD a :class:`KinematicRandomization`
    field (e.g. ``px4-sih`` or ``tau_horizontal_s=0.5:1,drag_horizontal_per_s=0.4``); later items win.
    Raises ValueError with a one-line message naming the bad item."""
    values: dict[str, tuple[float, float]] = {}
    for item in (part.strip() for part in text.split(",")):
        if not item:
            continue
        if item in RESPONSE_PRESETS:
            values |= RESPONSE_PRESETS[item]
            continue
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or name not in _RESPONSE_FIELDS:
            raise ValueError(f"response item {item!r}: expected a preset ({', '.join(RESPONSE_PRESETS)}) or FIELD=LOW:HIGH "
                             f"with FIELD one of {', '.join(_RESPONSE_FIELDS)}")
        try:
            bounds = [float(v) for v in value.split(":")]
        except ValueError:
            bounds = []
        if len(bounds) not in (1, 2) or not all(math.isfinite(b) for b in bounds):
            raise ValueError(f"response item {item!r}: expected {name}=LOW:HIGH or {name}=VALUE with finite numbers")
        values[name] = (bounds[0], bounds[-1])
    if not values:
        raise ValueError(f"response {text!r} names nothing: give a preset ({', '.join(RESPONSE_PRESETS)}) or FIELD=LOW:HIGH")
    return dataclasses.replace(base, **values)  # KinematicRandomization checks each range


def _differing(ranges: KinematicRandomization, base: KinematicRandomization) -> dict[str, tuple[float, float]]:
    """The ranges of ``ranges`` that differ from ``base``, in field order."""
    return {name: getattr(ranges, name) for name in _RESPONSE_FIELDS if getattr(ranges, name) != getattr(base, name)}


def describe_response(ranges: KinematicRandomization, base: KinematicRandomization) -> str:
    """The ranges that differ from ``base``, as a ``--response`` specification (``nominal`` when none)."""
    parts = [f"{name}={lo:g}:{hi:g}" if lo != hi else f"{name}={lo:g}"
             for name, (lo, hi) in _differing(ranges, base).items()]
    return ",".join(parts) or "nominal"


def layer_response(own: KinematicRandomization | None, extra: KinematicRandomization) -> KinematicRandomization:
    """``own`` (the nominal response if None) with every range that ``extra`` sets away from the nominal one."""
    nominal = nominal_ranges()
    return dataclasses.replace(own or nominal, **_differing(extra, nominal))


class KinematicDynamics(Dynamics):
    """Fast vectorized kinematic model of M quadrotors (numba kernel), each UAV with its own response."""

    def __init__(self, num_uavs: int, params: KinematicParams = KinematicParams()) -> None:
        super().__init__(num_uavs)
        self.params = params
        #: [M] per-UAV response, one array per field of _RESPONSE_FIELDS (nominal: ``params``).
        self.response = {name: np.full(num_uavs, float(getattr(params, name))) for name in _RESPONSE_FIELDS}
        #: [M, 2] the horizontal velocity loop's integrated error (NED, m/s * s); used when its gain is > 0.
        self.vel_error_int_ne = np.zeros((num_uavs, 2))
        #: [M, K, 3] the last K commands sent to each UAV, newest first (zeros before its first one: hold);
        #: kept and read only while some UAV has ``command_delay_s`` > 0 (its delay is drawn after its reset, which
        #: clears its row). K grows with the longest delay (:meth:`_push_command`).
        self.cmd_history_frd = np.zeros((num_uavs, 2, 3))

    def randomize(self, index: np.ndarray, ranges: KinematicRandomization | None, rng: np.random.Generator) -> None:
        """Draw the response of UAVs ``index`` from ``ranges`` (None: back to the nominal ``params``)."""
        for name in _RESPONSE_FIELDS:
            if ranges is None:
                self.response[name][index] = getattr(self.params, name)
                continue
            lo, hi = getattr(ranges, name)
            if name in _MAY_BE_ZERO and hi == 0.0:
                # Off: no draw, so runs without drag consume the generator (and fly the episodes) they did before.
                self.response[name][index] = 0.0
            else:
                self.response[name][index] = rng.uniform(lo, hi, len(index))

    def reset(self, index: np.ndarray, pos_ned: np.ndarray, yaw_rad: np.ndarray) -> None:
        self.pos_ned[index] = pos_ned
        self.yaw_rad[index] = yaw_rad
        self.vel_ned[index] = 0.0
        self.yaw_rate_rad_s[index] = 0.0
        self.vel_error_int_ne[index] = 0.0
        self.cmd_history_frd[index] = 0.0

    def step(self, cmd_frd: np.ndarray, dt_s: float, active: np.ndarray) -> None:
        """Advance every active UAV by ``dt_s`` (see :meth:`Dynamics.step`); where a UAV has a command delay, the
        command it flies comes from its history, counted in calls, so ``dt_s`` must not change between calls."""
        p = self.params
        n_sub = max(1, int(round(dt_s / p.substep_s)))
        h = dt_s / n_sub
        cmd = np.ascontiguousarray(cmd_frd, dtype=np.float64)
        active = np.ascontiguousarray(active, dtype=np.bool_)
        state = (self.pos_ned, self.vel_ned, self.yaw_rad, self.yaw_rate_rad_s, self.vel_error_int_ne)
        law = [self.response[name] for name in _LAW_FIELDS]
        delay_s = self.response["command_delay_s"]
        if not delay_s.any():
            _integrate(*state, cmd, active, h, n_sub, *law)
            return
        self._push_command(cmd, float(delay_s.max()), dt_s)
        rows = np.arange(self.num_uavs)
        for j in range(n_sub):
            # At time j*h of this period a UAV acts on the newest command sent at least delay_s earlier; the
            # commands were sent at 0, -dt, -2 dt, ... (-1e-9: a delay of exactly one period is one period back).
            periods_back = np.maximum(np.ceil((delay_s - j * h) / dt_s - 1e-9), 0).astype(np.int64)
            _integrate(*state, np.ascontiguousarray(self.cmd_history_frd[rows, periods_back]), active, h, 1, *law)

    def _push_command(self, cmd_frd: np.ndarray, longest_delay_s: float, dt_s: float) -> None:
        """Record this period's commands as the newest, keeping enough periods for ``longest_delay_s``."""
        needed = int(math.ceil(longest_delay_s / dt_s - 1e-9)) + 1
        if needed > self.cmd_history_frd.shape[1]:  # a longer delay drawn: older commands unknown, i.e. hold
            grown = np.zeros((self.num_uavs, needed, 3))
            grown[:, :self.cmd_history_frd.shape[1]] = self.cmd_history_frd
            self.cmd_history_frd = grown
        self.cmd_history_frd[:, 1:] = self.cmd_history_frd[:, :-1]  # numpy copies overlapping slices safely
        self.cmd_history_frd[:, 0] = cmd_frd


@numba.njit(cache=True)
def _integrate(pos, vel, yaw, yaw_rate, err_int, cmd, active, h, n_sub, tau_h_a, tau_v_a, tau_yaw_a, acc_h_a, acc_v_a,
               acc_yaw_a, drag_a, ki_a):
    for m in range(pos.shape[0]):
        if not active[m]:
            continue
        tau_h, tau_v, tau_yaw = tau_h_a[m], tau_v_a[m], tau_yaw_a[m]
        acc_h, acc_v, acc_yaw = acc_h_a[m], acc_v_a[m], acc_yaw_a[m]
        drag, ki = drag_a[m], ki_a[m]
        for _ in range(n_sub):
            c = math.cos(yaw[m])
            s = math.sin(yaw[m])
            # Desired NED velocity: the body command rotated by the current heading.
            target_n = c * cmd[m, 0]
            target_e = s * cmd[m, 0]
            err_n = target_n - vel[m, 0]
            err_e = target_e - vel[m, 1]
            acc_n = err_n / tau_h + ki * err_int[m, 0]
            acc_e = err_e / tau_h + ki * err_int[m, 1]
            norm = math.sqrt(acc_n * acc_n + acc_e * acc_e)
            if norm > acc_h:
                acc_n *= acc_h / norm
                acc_e *= acc_h / norm
            elif ki > 0.0:  # anti-windup: the integrator runs only while the output is not capped
                err_int[m, 0] += err_n * h
                err_int[m, 1] += err_e * h
            acc_n -= drag * vel[m, 0]  # air drag acts outside the controller's cap
            acc_e -= drag * vel[m, 1]
            acc_d = min(max((cmd[m, 1] - vel[m, 2]) / tau_v, -acc_v), acc_v)
            yaw_acc = min(max((cmd[m, 2] - yaw_rate[m]) / tau_yaw, -acc_yaw), acc_yaw)
            vel[m, 0] += acc_n * h
            vel[m, 1] += acc_e * h
            vel[m, 2] += acc_d * h
            yaw_rate[m] += yaw_acc * h
            pos[m, 0] += vel[m, 0] * h
            pos[m, 1] += vel[m, 1] * h
            pos[m, 2] += vel[m, 2] * h
            # companion.frames.wrap_angle_rad, spelled out: this loop is compiled by numba
            yaw[m] = (yaw[m] + yaw_rate[m] * h + math.pi) % (2.0 * math.pi) - math.pi
