"""Fit each vehicle's velocity response from a real-autopilot flight: which kinematic model flew it?

``python -m sitl.real_autopilots fit RUN_DIR`` (docs/real_autopilots.md "Fitting each vehicle's response").

A run of ``sitl.real_autopilots circle`` (or ``stop``) leaves, per vehicle, the companion's log of the
body-frame velocity commands it sent (``companion_I.jsonl``, one ``step`` record per control tick) and the
world's trace of where the vehicle flew (``trace.jsonl``: position, velocity and heading at ~10 Hz). This
module replays the commands through the simulator's own kinematic law (:func:`sitl.sim.dynamics.kinematic.
_integrate`, one grid point per "UAV") and keeps, per vehicle, the parameters whose simulated velocity is
closest to the measured one:

* horizontal: the lag ``tau_horizontal_s``, the PI loop against drag (``drag_horizontal_per_s``,
  ``integral_horizontal_per_s2``; docs/simulator.md) and a pure command delay ``delay_s`` (the simulator's
  ``command_delay_s``: how much of the response is latency);
* vertical: ``tau_vertical_s``.

The fit runs over each stretch of at least :data:`MIN_SEGMENT_S` in which the companion streamed velocity
setpoints (position targets, e.g. the station-keeping hold before the goals, break the stretch), each
started from the measured velocity with the integrator at 0 (after a hold the vehicle's may have wound up:
a small error the fit cannot remove). The acceleration caps are the simulator's nominal ones.

The result is also a ``--response`` specification (:func:`sitl.sim.dynamics.kinematic.parse_response`)
spanning the vehicles' fits: the ranges to evaluate (``swarm_test --response``) and train with.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from sitl.realtime.autopilot_sitl import PoseTrace
from sitl.realtime.mavlink_swarm import JsonLinesTail
from sitl.sim.dynamics.kinematic import _LAW_FIELDS, KinematicParams, _integrate

#: The grid searched (seconds, 1/s, 1/s^2): wide enough for a stiff racer and for PX4 SIH's default airframe.
TAU_GRID_S = np.round(np.arange(0.15, 1.501, 0.05), 3)
DRAG_GRID_PER_S = np.round(np.arange(0.0, 1.001, 0.05), 3)
INTEGRAL_GRID_PER_S2 = np.round(np.arange(0.0, 0.601, 0.1), 3)
DELAY_GRID_S = np.round(np.arange(0.0, 0.301, 0.05), 3)
TAU_VERTICAL_GRID_S = np.round(np.arange(0.05, 1.001, 0.05), 3)
#: The law's integration step (the simulator's sub-step).
STEP_S = KinematicParams().substep_s
#: Stretches of velocity setpoints shorter than this are not fitted (too little to tell a lag from a delay).
MIN_SEGMENT_S = 3.0
#: Two control ticks further apart than this end a stretch (the companion skipped or held).
MAX_TICK_GAP_S = 0.35


class FitError(ValueError):
    """The run folder cannot be fitted (missing or empty logs); the message says which file."""


@dataclass(frozen=True)
class VehicleFit:
    """One vehicle's best-fitting response, with the error that measures how well it fits."""

    vehicle: int
    tau_horizontal_s: float
    drag_horizontal_per_s: float
    integral_horizontal_per_s2: float
    delay_s: float
    tau_vertical_s: float
    rms_error_m_s: float  # horizontal velocity, best fit
    lag_only_rms_error_m_s: float  # horizontal velocity, best with drag = integral = 0 (a plain lag + delay)
    fitted_s: float  # seconds of flight fitted
    quick_gain: float  # 1 / (1 + drag * tau): the share of a step's speed reached quickly, before the integrator


@dataclass
class _Series:
    t_cmd: np.ndarray  # [K] s, the companion's step times from its first velocity setpoint
    cmd: np.ndarray  # [K, 3] forward m/s, down m/s, yaw rate rad/s
    t: np.ndarray  # [T] s, the trace's times on the same clock
    vel: np.ndarray  # [T, 3] NED m/s
    yaw: np.ndarray  # [T] rad, unwrapped


def _read_jsonl(path: Path) -> list[dict]:
    """The records of a JSON-lines log (a line cut short by a kill is left out, as the harness reads them)."""
    if not path.is_file():
        raise FitError(f"{path}: no such file (is this a sitl.real_autopilots run folder?)")
    return JsonLinesTail(path).read()


def vehicles_in(run: Path) -> int:
    """How many vehicles a run folder has logs for (``companion_0.jsonl`` ...)."""
    n = 0
    while (Path(run) / f"companion_{n}.jsonl").is_file():
        n += 1
    if n == 0:
        raise FitError(f"{run}: no companion_0.jsonl (is this a sitl.real_autopilots run folder?)")
    return n


def _series(run: Path, vehicle: int, trace: PoseTrace) -> _Series:
    steps = [s for s in _read_jsonl(Path(run) / f"companion_{vehicle}.jsonl")
             if s.get("kind") == "step" and s.get("sent") and s.get("cmd") is not None
             and s.get("hold_point_ned") is None]  # velocity setpoints only; a position target is another law
    rows = np.isfinite(trace.vel[:, vehicle]).all(axis=1) & np.isfinite(trace.yaw[:, vehicle])
    if len(steps) < 2 or rows.sum() < 2:
        raise FitError(f"{run}: vehicle {vehicle} has no velocity setpoints or no trace with its heading to fit")
    t_cmd = np.array([s["t"] for s in steps])
    origin = t_cmd[0]  # times from the first command: UNIX seconds in float64 keep only ~0.2 us
    return _Series(t_cmd - origin, np.array([s["cmd"] for s in steps], float), trace.t[rows] - origin,
                   trace.vel[rows, vehicle], np.unwrap(trace.yaw[rows, vehicle]))


def _segments(t_cmd: np.ndarray) -> list[tuple[int, int]]:
    """Index ranges [a, b) of the steps in stretches of velocity setpoints at least MIN_SEGMENT_S long."""
    breaks = np.flatnonzero(np.diff(t_cmd) > MAX_TICK_GAP_S) + 1
    edges = [0, *breaks.tolist(), len(t_cmd)]
    return [(a, b) for a, b in zip(edges[:-1], edges[1:]) if t_cmd[b - 1] - t_cmd[a] >= MIN_SEGMENT_S]


def _replay(s: _Series, a: int, b: int, params: dict[str, np.ndarray], delay_s: np.ndarray):
    """Fly steps [a, b) through the kinematic law for every row of ``params`` (one row per candidate);
    the squared horizontal / vertical velocity errors summed over the trace samples inside, and their count."""
    rows = len(delay_s)
    t0, t1 = s.t_cmd[a], s.t_cmd[b - 1]
    inside = np.flatnonzero((s.t > t0) & (s.t <= t1))
    grid = t0 + STEP_S * np.arange(int(round((t1 - t0) / STEP_S)) + 1)
    v0 = np.array([np.interp(t0, s.t, s.vel[:, k]) for k in range(3)])
    pos, vel = np.zeros((rows, 3)), np.tile(v0, (rows, 1))
    yaw, yaw_rate, err_int = np.zeros(rows), np.zeros(rows), np.zeros((rows, 2))
    cmd, active = np.zeros((rows, 3)), np.ones(rows, dtype=np.bool_)
    arrays = [np.ascontiguousarray(params[name], dtype=np.float64) for name in _LAW_FIELDS]
    yaw_at = np.interp(grid, s.t, s.yaw)
    delays, row_delay = np.unique(delay_s, return_inverse=True)  # few distinct delays: look each up once a step
    sample_step = np.clip(np.round((s.t[inside] - t0) / STEP_S).astype(int), 0, len(grid) - 1)
    wanted = np.zeros(len(grid), dtype=bool)
    wanted[sample_step] = True
    measured = {k: s.vel[i] for k, i in zip(sample_step.tolist(), inside.tolist())}
    err_h, err_v = np.zeros(rows), np.zeros(rows)
    for k, tk in enumerate(grid):
        # each row's command is the one the companion had sent delay_s before (zero-order hold)
        # (+1 us: a command logged at exactly tk counts as sent)
        idx = np.clip(np.searchsorted(s.t_cmd, tk - delays + 1e-6, side="right") - 1, a, b - 1)[row_delay]
        cmd[:, 0] = s.cmd[idx, 0]
        cmd[:, 1] = s.cmd[idx, 1]
        yaw[:] = yaw_at[k]  # the heading as flown; the fit is about the velocity loop
        yaw_rate[:] = 0.0
        _integrate(pos, vel, yaw, yaw_rate, err_int, cmd, active, STEP_S, 1, *arrays)
        if wanted[k]:
            m = measured[k]
            err_h += (vel[:, 0] - m[0]) ** 2 + (vel[:, 1] - m[1]) ** 2
            err_v += (vel[:, 2] - m[2]) ** 2
    return err_h, err_v, len(measured)


def fit_vehicle(run: Path, vehicle: int, trace: PoseTrace) -> VehicleFit:
    """The best-fitting response of ``vehicle`` in the run folder ``run`` (``trace``: the world's trace of it)."""
    s = _series(run, vehicle, trace)
    segments = _segments(s.t_cmd)
    if not segments:
        raise FitError(f"{run}: vehicle {vehicle} never streamed velocity setpoints for {MIN_SEGMENT_S:g} s")
    nominal = KinematicParams()
    tau, drag, ki, delay = (g.ravel() for g in np.meshgrid(TAU_GRID_S, DRAG_GRID_PER_S, INTEGRAL_GRID_PER_S2,
                                                          DELAY_GRID_S, indexing="ij"))
    params = {name: np.full(len(tau), float(getattr(nominal, name))) for name in _LAW_FIELDS}
    params |= {"tau_horizontal_s": tau, "drag_horizontal_per_s": drag, "integral_horizontal_per_s2": ki}
    err_h, samples = np.zeros(len(tau)), 0
    for a, b in segments:
        e, _, n = _replay(s, a, b, params, delay)
        err_h += e
        samples += n
    best = int(np.argmin(err_h))
    plain = (drag == 0.0) & (ki == 0.0)
    lag_only = float(np.sqrt(err_h[plain].min() / samples))
    # Vertical: its law does not depend on the horizontal one; a second, small grid at the best delay.
    vparams = {name: np.full(len(TAU_VERTICAL_GRID_S), float(getattr(nominal, name))) for name in _LAW_FIELDS}
    vparams["tau_vertical_s"] = TAU_VERTICAL_GRID_S.astype(float)
    err_v = np.zeros(len(TAU_VERTICAL_GRID_S))
    for a, b in segments:
        err_v += _replay(s, a, b, vparams, np.full(len(TAU_VERTICAL_GRID_S), delay[best]))[1]
    fitted_s = sum(float(s.t_cmd[b - 1] - s.t_cmd[a]) for a, b in segments)
    return VehicleFit(vehicle=vehicle, tau_horizontal_s=float(tau[best]), drag_horizontal_per_s=float(drag[best]),
                      integral_horizontal_per_s2=float(ki[best]), delay_s=float(delay[best]),
                      tau_vertical_s=float(TAU_VERTICAL_GRID_S[int(np.argmin(err_v))]),
                      rms_error_m_s=round(float(np.sqrt(err_h[best] / samples)), 4),
                      lag_only_rms_error_m_s=round(lag_only, 4), fitted_s=round(fitted_s, 1),
                      quick_gain=round(1.0 / (1.0 + float(drag[best]) * float(tau[best])), 3))


def fit_run(run: Path, vehicles: list[int] | None = None, progress=None) -> list[VehicleFit]:
    """Every vehicle's fit in a ``sitl.real_autopilots`` run folder (``progress``: called with each fit)."""
    run = Path(run)
    records = _read_jsonl(run / "trace.jsonl")
    n = vehicles_in(run)
    trace = PoseTrace.from_records(records, n)
    fits = []
    for i in vehicles if vehicles is not None else range(n):
        fits.append(fit_vehicle(run, i, trace))
        if progress is not None:
            progress(fits[-1])
    return fits


#: The fitted fields that are simulator parameters (the rest describe the fit).
FITTED_FIELDS = ("tau_horizontal_s", "drag_horizontal_per_s", "integral_horizontal_per_s2", "tau_vertical_s")
#: Fitted fields with another name in the simulator's response (KinematicRandomization).
_RESPONSE_NAME = {"delay_s": "command_delay_s"}


def response_spec(fits: list[VehicleFit]) -> str:
    """The ``--response`` specification spanning ``fits``: each fitted field (and the delay, as
    ``command_delay_s``) from its smallest to its largest value."""
    return ",".join(f"{_RESPONSE_NAME.get(name, name)}={min(getattr(f, name) for f in fits):g}:"
                    f"{max(getattr(f, name) for f in fits):g}" for name in (*FITTED_FIELDS, "delay_s"))


def fit_summary(fits: list[VehicleFit]) -> dict:
    """What ``fit`` prints and stores: every vehicle's fit, the spread and the ``--response`` spec."""
    return {"vehicles": [asdict(f) for f in fits], "response": response_spec(fits),
            "spread": {name: [min(getattr(f, name) for f in fits), max(getattr(f, name) for f in fits)]
                       for name in (*FITTED_FIELDS, "delay_s", "quick_gain")}}


def format_fits(fits: list[VehicleFit]) -> str:
    """A table a person reads."""
    lines = ["vehicle  tau_h s  drag /s  ki /s^2  delay s  tau_v s  quick gain  rms m/s (lag only)  fitted s"]
    for f in fits:
        lines.append(f"{f.vehicle:7d}  {f.tau_horizontal_s:7.2f}  {f.drag_horizontal_per_s:7.2f}  "
                     f"{f.integral_horizontal_per_s2:7.2f}  {f.delay_s:7.2f}  {f.tau_vertical_s:7.2f}  "
                     f"{f.quick_gain:10.2f}  {f.rms_error_m_s:.3f} ({f.lag_only_rms_error_m_s:.3f})  {f.fitted_s:8.1f}")
    return "\n".join(lines)


__all__ = ["FitError", "VehicleFit", "fit_run", "fit_summary", "fit_vehicle", "format_fits", "response_spec",
           "vehicles_in"]
