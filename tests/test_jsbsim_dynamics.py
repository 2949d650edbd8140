"""The JSBSim backend: step responses of its velocity controller, resets, frames, independence.

Run with ``-s`` to see the measured rise times, steady-state errors and cost.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

pytest.importorskip("jsbsim")

from sitl.sim.dynamics import make_dynamics  # noqa: E402
from sitl.sim.dynamics.jsbsim_quad import JSBSimDynamics  # noqa: E402

_trapezoid = getattr(np, "trapezoid", None) or np.trapz  # numpy < 2 has only trapz

SAMPLE_S = 0.01  # stepping at 10 ms changes nothing (the controller runs every 5 ms JSBSim step) but samples finely
HOVER_NED = np.array([0.0, 0.0, -10.0])


@pytest.fixture(scope="module")
def dyn() -> JSBSimDynamics:
    return JSBSimDynamics(3)


def _fly(dyn: JSBSimDynamics, cmd: np.ndarray, duration_s: float, dt_s: float = SAMPLE_S) -> dict[str, np.ndarray]:
    """Step all UAVs of ``dyn`` with constant ``cmd`` [M, 3]; return time series (UAV 0)."""
    active = np.ones(dyn.num_uavs, dtype=bool)
    n = int(round(duration_s / dt_s))
    out = {"t": np.arange(1, n + 1) * dt_s, "pos": np.empty((n, 3)), "vel": np.empty((n, 3)),
           "yaw": np.empty(n), "yaw_rate": np.empty(n)}
    for k in range(n):
        dyn.step(cmd, dt_s, active)
        out["pos"][k] = dyn.pos_ned[0]
        out["vel"][k] = dyn.vel_ned[0]
        out["yaw"][k] = dyn.yaw_rad[0]
        out["yaw_rate"][k] = dyn.yaw_rate_rad_s[0]
    return out


def _step_metrics(t: np.ndarray, y: np.ndarray, target: float, settle_window_s: float = 2.0) -> tuple[float, float, float]:
    """(10-90 % rise time, |steady-state error| = |mean over the last window - target|, overshoot) of a 0 -> target step."""
    frac = y / target
    t10 = np.interp(0.1, frac[: np.argmax(frac >= 0.1) + 1], t[: np.argmax(frac >= 0.1) + 1])
    i90 = np.argmax(frac >= 0.9)
    assert frac[i90] >= 0.9, "response never reached 90 % of the step"
    t90 = np.interp(0.9, frac[: i90 + 1], t[: i90 + 1])
    steady = y[t > t[-1] - settle_window_s].mean()
    overshoot = max(0.0, (np.max(frac) - 1.0) * abs(target))
    return t90 - t10, abs(steady - target), overshoot


def _reset_hover(dyn: JSBSimDynamics, yaw_rad: float = 0.0) -> None:
    m = dyn.num_uavs
    pos = HOVER_NED + np.arange(m)[:, None] * np.array([0.0, 5.0, 0.0])
    dyn.reset(np.arange(m), pos, np.full(m, yaw_rad))


def test_make_dynamics_builds_jsbsim() -> None:
    dyn = make_dynamics("jsbsim", 2)
    assert isinstance(dyn, JSBSimDynamics)
    assert dyn.pos_ned.shape == (2, 3) and dyn.yaw_rate_rad_s.dtype == np.float64


def test_reset_places_uavs_hovering(dyn: JSBSimDynamics) -> None:
    # Fly first, so the reset has to undo motion, tilt and propeller speeds.
    _reset_hover(dyn)
    _fly(dyn, np.tile([2.0, 0.5, 0.5], (3, 1)), 1.5, 0.1)
    pos = np.array([[3.0, -4.0, -5.0], [250.0, -400.0, -30.0], [-1.0, 2.0, -1.5]])
    yaw = np.array([0.3, -2.5, 3.0])
    dyn.reset(np.arange(3), pos, yaw)
    np.testing.assert_allclose(dyn.pos_ned, pos, atol=1e-3)
    np.testing.assert_allclose(dyn.vel_ned, 0.0, atol=1e-9)
    np.testing.assert_allclose(dyn.yaw_rad, yaw, atol=1e-9)
    _fly(dyn, np.zeros((3, 3)), 1.0, 0.1)
    drift = np.linalg.norm(dyn.pos_ned - pos, axis=1)
    print(f"\n[jsbsim] drift after reset + 1 s zero command: {np.array2string(drift, precision=4)} m")
    assert np.all(drift < 0.2)
    assert np.all(np.abs(dyn.vel_ned) < 0.05)


def test_forward_step_east(dyn: JSBSimDynamics) -> None:
    _reset_hover(dyn, np.pi / 2)
    start = dyn.pos_ned[0].copy()
    cmd = np.zeros((3, 3))
    cmd[:, 0] = 2.0
    r = _fly(dyn, cmd, 10.0)
    v_along = r["vel"][:, 1]  # heading is east
    rise, err, overshoot = _step_metrics(r["t"], v_along, 2.0)
    alt_dev = np.max(np.abs(r["pos"][:, 2] - start[2]))
    moved = r["pos"][-1] - start
    print(f"\n[jsbsim] forward 0->2 m/s at yaw 90 deg: rise(10-90%) {rise:.3f} s, steady-state error {err:.4f} m/s, "
          f"overshoot {overshoot:.3f} m/s, max altitude deviation {alt_dev:.3f} m, moved N/E {moved[0]:.2f}/{moved[1]:.2f} m")
    assert rise < 2.0
    assert err < 0.1
    assert alt_dev < 0.3
    assert moved[1] > 15.0 and abs(moved[0]) < 0.2
    assert abs(r["vel"][-1, 0]) < 0.05 and abs(r["yaw"][-1] - np.pi / 2) < 0.02


def test_climb_step(dyn: JSBSimDynamics) -> None:
    _reset_hover(dyn)
    start = dyn.pos_ned[0].copy()
    cmd = np.zeros((3, 3))
    cmd[:, 1] = -0.5
    r = _fly(dyn, cmd, 8.0)
    rise, err, overshoot = _step_metrics(r["t"], r["vel"][:, 2], -0.5)
    horiz = np.linalg.norm(r["pos"][-1, :2] - start[:2])
    print(f"\n[jsbsim] climb 0->-0.5 m/s (down velocity): rise(10-90%) {rise:.3f} s, steady-state error {err:.4f} m/s, "
          f"overshoot {overshoot:.3f} m/s, climbed {start[2] - r['pos'][-1, 2]:.2f} m, horizontal drift {horiz:.3f} m")
    # 10 % of the step: the vertical loop must cope with the propellers' inflow at climb speed.
    assert err < 0.05
    assert rise < 1.0
    assert start[2] - r["pos"][-1, 2] > 3.0 and horiz < 0.2


def test_yaw_rate_step(dyn: JSBSimDynamics) -> None:
    _reset_hover(dyn)
    start = dyn.pos_ned[0].copy()
    cmd = np.zeros((3, 3))
    cmd[:, 2] = 0.5
    r = _fly(dyn, cmd, 8.0)
    rise, err, overshoot = _step_metrics(r["t"], r["yaw_rate"], 0.5)
    drift = np.linalg.norm(r["pos"][-1] - start)
    # The heading advances by the integral of the yaw rate (wrapping handled by unwrap).
    turned = np.unwrap(np.r_[0.0, r["yaw"]])[-1]
    print(f"\n[jsbsim] yaw rate 0->0.5 rad/s: rise(10-90%) {rise:.3f} s, steady-state error {err:.4f} rad/s, "
          f"overshoot {overshoot:.3f} rad/s, turned {turned:.2f} rad, position drift {drift:.3f} m")
    assert err < 0.05  # 10 % of the step
    assert rise < 1.0
    assert abs(turned - _trapezoid(np.r_[0.0, r["yaw_rate"]], dx=SAMPLE_S)) < 0.01
    assert np.all((r["yaw"] >= -np.pi) & (r["yaw"] < np.pi))
    assert drift < 0.2


def test_positions_follow_velocities(dyn: JSBSimDynamics) -> None:
    """The lat/lon <-> NED mapping agrees with JSBSim's NED velocities (units and signs)."""
    _reset_hover(dyn, np.deg2rad(30.0))
    start = dyn.pos_ned[0].copy()
    cmd = np.zeros((3, 3))
    cmd[:, 0] = 2.0
    cmd[:, 1] = 0.3
    r = _fly(dyn, cmd, 6.0, 0.05)
    integrated = start + _trapezoid(np.vstack([np.zeros(3), r["vel"]]), dx=0.05, axis=0)
    np.testing.assert_allclose(r["pos"][-1], integrated, atol=0.03)
    assert r["pos"][-1, 0] > 0 and r["pos"][-1, 1] > 0  # heading 30 deg: north-east
    assert r["pos"][-1, 2] > start[2] + 1.0  # positive down velocity descends


def test_inactive_and_independent_uavs(dyn: JSBSimDynamics) -> None:
    _reset_hover(dyn)
    start = dyn.pos_ned.copy()
    cmd = np.array([[2.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, -0.5, 0.5]])
    active = np.array([True, False, True])
    for _ in range(30):
        dyn.step(cmd, 0.1, active)
    np.testing.assert_array_equal(dyn.pos_ned[1], start[1])
    np.testing.assert_array_equal(dyn.vel_ned[1], 0.0)
    moved = dyn.pos_ned - start
    assert moved[0, 0] > 3.0 and abs(moved[0, 2]) < 0.3  # forward (north)
    assert moved[2, 2] < -0.8 and np.linalg.norm(moved[2, :2]) < 0.2  # climbing on the spot
    assert dyn.yaw_rate_rad_s[2] > 0.4 and abs(dyn.yaw_rate_rad_s[0]) < 0.01
    # Inactive UAV 1, once activated with UAV 0's command, behaves as UAV 0 did (up to the
    # sub-rpm propeller-speed differences a reset leaves).
    _reset_hover(dyn)
    start = dyn.pos_ned.copy()
    for _ in range(30):
        dyn.step(cmd, 0.1, np.ones(3, dtype=bool))
    np.testing.assert_allclose(dyn.pos_ned[1] - start[1], dyn.pos_ned[0] - start[0], atol=1e-3)


def test_cost_per_uav_second() -> None:
    dyn = JSBSimDynamics(8)
    _reset_hover(dyn)
    cmd = np.tile([1.0, 0.1, 0.2], (8, 1))
    dyn.step(cmd, 0.1, np.ones(8, dtype=bool))
    t0 = time.perf_counter()
    for _ in range(20):
        dyn.step(cmd, 0.1, np.ones(8, dtype=bool))
    per_uav_s = (time.perf_counter() - t0) / (2.0 * 8)
    t0 = time.perf_counter()
    dyn.reset(np.arange(8), np.tile(HOVER_NED, (8, 1)), np.zeros(8))
    per_reset = (time.perf_counter() - t0) / 8
    print(f"\n[jsbsim] wall-clock per UAV per simulated second: {per_uav_s * 1e3:.2f} ms; reset from flight: {per_reset * 1e3:.2f} ms/UAV")
    assert per_uav_s < 0.1
