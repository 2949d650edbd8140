"""JSBSim quadrotor: one rigid-body F450 flight model per UAV under a cascaded velocity controller.

Model. Each UAV is a ``jsbsim.FGFDMExec`` flying the ``F450`` quadrotor shipped with the
jsbsim wheel: 1.4 kg, Ixx = Iyy = 0.019, Izz = 0.0252 kg m^2, four DJI E305 brushless
motors (``brushless_dc_motor``) turning 9.4" DJI 9450 propellers on 0.165 m arms (X
layout), ground contacts, a flat-plate drag term, WGS84 gravity over a rotating Earth.
The propellers' spin is simulated (inertia + motor torque), so thrust lags a throttle
change with a time constant of about 60 ms. Motors are driven through the model's
external ESC inputs ``fcs/cmd{FR,AL,FL,AR}_ext_nd``; its own rate loop stays disengaged
(``fcs/ScasEngage`` = 0). F450.xml is used unchanged: it loads and flies correctly in
JSBSim 1.3.3, but it declares format version 3.0 and its sensor systems fail to tie a
few properties, so loading prints about twenty warning lines — construction silences the
process's stdout/stderr while it loads the model.

Frames. Each FDM starts at a lat/lon computed from the requested NED position around a
fixed origin (:class:`JSBSimParams`) with :func:`companion.frames.ned_to_geodetic` (the
local tangent plane on WGS-84), and :func:`companion.frames.geodetic_to_ned` brings
positions back. Terrain is at sea level, so altitude above ground
(``position/h-agl-ft``) is exactly ``-z`` and JSBSim's ground is the plane z = 0.
Velocities are JSBSim's Earth-relative ``velocities/v-{north,east,down}-fps``; yaw is
``attitude/psi-rad`` wrapped to [-pi, pi) and the yaw rate ``velocities/psidot-rad_sec``.

Controller (a numba kernel over all active UAVs, run before every JSBSim step; ``step``
splits ``dt_s`` into equal steps of at most ``fdm_dt_s`` = 5 ms):

1. velocity: the heading-frame command is rotated into NED by the current yaw; a PI per
   axis gives the desired acceleration, capped like PX4's ``MPC_ACC_HOR`` /
   ``MPC_ACC_UP_MAX`` (integrators run only uncapped and within 0.2 m/s of the setpoint:
   they are for drag and propeller inflow, not to wind up during a step);
2. thrust vector: the acceleration minus gravity gives the desired roll/pitch (in the
   heading frame, capped at ``max_tilt_rad``) and the collective thrust, divided by the
   measured ``cos(roll) cos(pitch)`` so tilting does not cost altitude;
3. attitude: Euler-angle errors times ``att_kp`` plus the commanded yaw rate are Euler
   rates, converted into body-rate setpoints (exact kinematics, so turning while tilted
   is consistent);
4. rates: PI with derivative on the measured rate (the D term is a lead that cancels
   most of the motor lag), times the inertia, gives body torques;
5. mixer: the geometric 4x4 allocation (arm positions and propeller senses read from the
   model, torque/thrust ratio measured) gives each motor's thrust, yaw torque being cut
   first when a motor would saturate; a thrust-vs-throttle table measured from the
   model once per process (static propellers) turns thrust into ESC commands.

Reset re-uses the FDM: it sets ``ic/...`` and calls ``run_ic()`` (no reload). Propeller
speeds survive ``run_ic()``, so the propellers are then run at the hover throttle with the
airframe put back by ``run_ic()`` after every (20 ms) step until their speed settles, and
the UAV starts hovering with its propellers at hover speed (~0.35 ms per UAV from flight).

Measured step responses (``python -m pytest -s tests/test_jsbsim_dynamics.py``;
from hover, states sampled every 10 ms, steady state = mean over the last 2 s):

* forward 0 -> 2 m/s at yaw 90 deg: 10-90 % rise time 0.61 s, steady-state error 0.0003 m/s
  (10 s run), overshoot 0.005 m/s, altitude within 0.013 m, no northward drift;
* climb (down velocity 0 -> -0.5 m/s): rise time 0.63 s, steady-state error < 0.0001 m/s (8 s);
* yaw rate 0 -> 0.5 rad/s: rise time 0.37 s, steady-state error 0.002 rad/s (8 s).

Over a minute of random commands its velocities stay within 0.5 m/s of the kinematic
backend's (positions within 1.6 m). Cost: about 4.5 ms of wall-clock time per UAV per
simulated second (200 JSBSim steps of ~22 us, ~10 us of it ``FGFDMExec.run()``), flat
from 1 to 200 UAVs, i.e. 0.45 ms per UAV per 0.1 s control period; building one FDM takes
7-10 ms and ~0.45 MB (plus ~0.2 s once per process to measure the thrust curve).
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import sys
from dataclasses import dataclass

import jsbsim
import numba
import numpy as np

from companion.frames import geodetic_to_ned, ned_to_geodetic, wrap_angle_rad
from sitl.sim.dynamics.base import Dynamics

FT_TO_M = 0.3048
LBF_TO_N = 4.4482216152605
FTLBF_TO_NM = FT_TO_M * LBF_TO_N
SLUG_TO_KG = 14.593902937206364
SLUGFT2_TO_KGM2 = SLUG_TO_KG * FT_TO_M * FT_TO_M
INCH_TO_M = 0.0254
STANDARD_GRAVITY_M_S2 = 9.80665

# Motor order = JSBSim engine index = F450 ESC order (front-right, aft-left, front-left, aft-right).
_ESC_PROPS = ("fcs/cmdFR_ext_nd", "fcs/cmdAL_ext_nd", "fcs/cmdFL_ext_nd", "fcs/cmdAR_ext_nd")
# Columns of the per-UAV state cache, in this order.
_STATE_PROPS = (
    "velocities/v-north-fps", "velocities/v-east-fps", "velocities/v-down-fps",
    "attitude/phi-rad", "attitude/theta-rad", "attitude/psi-rad",
    "velocities/p-rad_sec", "velocities/q-rad_sec", "velocities/r-rad_sec",
    "velocities/psidot-rad_sec",
)


@dataclass(frozen=True)
class JSBSimParams:
    """Flight model, origin and controller gains of :class:`JSBSimDynamics`."""

    aircraft: str = "F450"  # aircraft directory under the jsbsim wheel's aircraft/
    fdm_dt_s: float = 0.005  # JSBSim integration step (controller runs every step)
    origin_lat_deg: float = 47.397742  # geodetic latitude of the NED origin (PX4 SITL home)
    origin_lon_deg: float = 8.545594  # longitude of the NED origin
    # Velocity loop (PI, output = desired acceleration).
    vel_kp_horizontal: float = 2.5  # 1/s
    vel_ki_horizontal: float = 0.6  # 1/s^2; removes drag-induced lag
    vel_kp_vertical: float = 3.0  # 1/s
    vel_ki_vertical: float = 1.5  # 1/s^2; removes thrust-model error
    vel_i_max_m_s2: float = 2.0  # integrator clamp, per axis
    vel_i_band_m_s: float = 0.2  # integrate only within this error (no windup during a step's rise)
    max_acc_horizontal_m_s2: float = 3.0  # as the kinematic backend / PX4 MPC_ACC_HOR
    max_acc_up_m_s2: float = 2.0  # upward acceleration cap
    max_acc_down_m_s2: float = 2.0  # downward acceleration cap (must stay well below g)
    max_tilt_rad: float = 0.6  # roll/pitch setpoint cap (~34 deg)
    # Attitude loop (P on Euler angles, output = Euler rates).
    att_kp: float = 8.0  # 1/s
    max_tilt_rate_rad_s: float = 4.0  # roll/pitch rate setpoint cap
    # Rate loop (PI + D on measurement, output = angular acceleration).
    rate_kp_roll_pitch: float = 20.0  # 1/s
    rate_ki_roll_pitch: float = 10.0  # 1/s^2
    rate_kd_roll_pitch: float = 1.0  # dimensionless (x angular acceleration); ~ motor lag * kp
    rate_kp_yaw: float = 8.0  # 1/s
    rate_ki_yaw: float = 0.5  # 1/s^2; yaw sees almost no steady torque
    rate_i_max_rad_s2: float = 5.0  # integrator clamp, per axis
    rate_i_band_rad_s: float = 0.2  # integrate only within this error
    min_motor_thrust_n: float = 0.6  # keep the propellers spinning (throttle ~0.15)
    # Reset: motor spin-up before the UAV is released.
    spinup_dt_s: float = 0.02  # step of the propeller-only spin-up run at reset
    spinup_max_s: float = 2.0  # longest spin-up run at reset
    spinup_tol_rpm: float = 0.2  # settled when no propeller changes more than this in one spin-up step


@contextlib.contextmanager
def _silenced_output():
    """Send the process's stdout/stderr (file descriptors, where JSBSim's C++ writes) to /dev/null.

    Process-wide while it lasts: another thread's output in that window (~10 ms per model
    load) is lost too.
    """
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, devnull):
            os.close(fd)


def _load_fdm(aircraft: str, dt_s: float) -> jsbsim.FGFDMExec:
    """One FDM with ``aircraft`` loaded, engines running, ground at sea level."""
    with _silenced_output():
        fdm = jsbsim.FGFDMExec(None)
        fdm.set_debug_level(0)
        if not fdm.load_model(aircraft):
            raise RuntimeError(f"JSBSim could not load aircraft {aircraft!r}")
    fdm.set_dt(dt_s)
    fdm["ic/terrain-elevation-ft"] = 0.0
    fdm["propulsion/set-running"] = -1
    return fdm


def _set_motors(fdm: jsbsim.FGFDMExec, throttle: float) -> None:
    for name in _ESC_PROPS:
        fdm[name] = throttle


@dataclass(frozen=True)
class _Airframe:
    """What the controller needs to know about the aircraft (measured from the model)."""

    mass_kg: float
    inertia_kgm2: np.ndarray  # [3] principal moments (products of inertia are zero for F450)
    mixer: np.ndarray  # [4, 4] motor thrusts = mixer @ (collective N, roll, pitch, yaw torque N m)
    thrust_table_n: np.ndarray  # static thrust per motor, increasing
    throttle_table: np.ndarray  # ESC command giving that thrust
    hover_throttle: float
    hover_rpm: float


@functools.lru_cache(maxsize=None)
def _measure_airframe(aircraft: str, dt_s: float) -> _Airframe:
    """Read geometry and inertia and measure the static thrust/torque-vs-throttle curve.

    The propellers are run to steady speed at each throttle while ``run_ic()`` before every
    step keeps the airframe still (zero inflow), which leaves the propeller speed alone.
    """
    fdm = _load_fdm(aircraft, dt_s)
    fdm["ic/h-agl-ft"] = 100.0
    fdm.run_ic()  # mass properties are only computed once the model has run
    n_eng = fdm.get_propulsion().get_num_engines()
    if n_eng != 4:
        raise ValueError(f"{aircraft} has {n_eng} engines; this controller flies quadrotors")
    mass = fdm["inertia/mass-slugs"] * SLUG_TO_KG
    inertia = np.array([fdm[f"inertia/i{a}{a}-slugs_ft2"] for a in "xyz"]) * SLUGFT2_TO_KGM2
    # Structural frame is x aft, y right, z up (inches); the body frame is FRD.
    x_fwd = np.array([-fdm[f"propulsion/engine[{i}]/x-position"] for i in range(4)]) * INCH_TO_M
    y_right = np.array([fdm[f"propulsion/engine[{i}]/y-position"] for i in range(4)]) * INCH_TO_M
    sense = np.array([fdm[f"propulsion/engine[{i}]/propeller-sense"] for i in range(4)])
    throttles, thrusts, torques = [], [], []
    for u in np.linspace(0.0, 1.0, 41):
        _set_motors(fdm, u)
        last = -1.0
        for _ in range(1000):
            fdm.run_ic()
            fdm.run()
            thrust = fdm["propulsion/engine/thrust-lbs"]
            if abs(thrust - last) < 1e-9:
                break
            last = thrust
        throttles.append(u)
        thrusts.append(thrust * LBF_TO_N)
        torques.append(abs(fdm["propulsion/engine/propeller-torque-ftlb"]) * FTLBF_TO_NM)
    thrusts_a = np.array(thrusts)
    spinning = thrusts_a > 1e-6
    # Below ~0.12 the motor does not turn; keep one zero-thrust point just before spin-up.
    first = max(int(np.argmax(spinning)) - 1, 0)
    thrust_table = thrusts_a[first:]
    throttle_table = np.array(throttles)[first:]
    if np.any(np.diff(thrust_table) <= 0):
        raise RuntimeError(f"{aircraft}: thrust is not increasing with throttle")
    hover_thrust = mass * STANDARD_GRAVITY_M_S2 / 4
    hover_throttle = float(np.interp(hover_thrust, thrust_table, throttle_table))
    torque_per_thrust = float(np.interp(hover_thrust, thrusts_a[spinning], np.array(torques)[spinning]) / hover_thrust)
    # A propeller's drag torque yaws the airframe towards +sense (checked: FR + AL faster => yaw right).
    allocation = np.vstack([np.ones(4), -y_right, x_fwd, sense * torque_per_thrust])
    _set_motors(fdm, hover_throttle)
    for _ in range(1000):
        fdm.run_ic()
        fdm.run()
    hover_rpm = fdm["propulsion/engine/propeller-rpm"]
    return _Airframe(
        mass_kg=mass, inertia_kgm2=inertia, mixer=np.linalg.inv(allocation),
        thrust_table_n=thrust_table, throttle_table=throttle_table,
        hover_throttle=hover_throttle, hover_rpm=hover_rpm,
    )


class JSBSimDynamics(Dynamics):
    """M JSBSim quadrotors, each flown by a cascaded velocity controller (see module docstring).

    Built hovering at NED (0, 0, -10) facing north until :meth:`reset` places them.
    """

    def __init__(self, num_uavs: int, params: JSBSimParams = JSBSimParams()) -> None:
        super().__init__(num_uavs)
        self.params = params
        self.airframe = _measure_airframe(params.aircraft, params.fdm_dt_s)
        self._dt_s = params.fdm_dt_s
        self._fdms = [_load_fdm(params.aircraft, params.fdm_dt_s) for _ in range(num_uavs)]
        self._state = np.zeros((num_uavs, len(_STATE_PROPS)))  # JSBSim units (ft/s, rad)
        self._ctrl = np.zeros((num_uavs, 9))  # controller memory: velocity integrators, rate integrators, last rates
        self._motor = np.zeros((num_uavs, 4))  # ESC commands
        af, p = self.airframe, params
        self._gains = np.array([
            af.mass_kg, *af.inertia_kgm2, max(p.min_motor_thrust_n, af.thrust_table_n[0]), STANDARD_GRAVITY_M_S2,
            p.vel_kp_horizontal, p.vel_ki_horizontal, p.vel_kp_vertical, p.vel_ki_vertical,
            p.vel_i_max_m_s2, p.vel_i_band_m_s,
            p.max_acc_horizontal_m_s2, p.max_acc_up_m_s2, p.max_acc_down_m_s2, p.max_tilt_rad,
            p.att_kp, p.max_tilt_rate_rad_s,
            p.rate_kp_roll_pitch, p.rate_ki_roll_pitch, p.rate_kd_roll_pitch,
            p.rate_kp_yaw, p.rate_ki_yaw, p.rate_i_max_rad_s2, p.rate_i_band_rad_s,
        ])  # the order _control unpacks
        for fdm in self._fdms:
            _set_motors(fdm, self.airframe.hover_throttle)
        self.reset(np.arange(num_uavs), np.zeros((num_uavs, 3)) + [0.0, 0.0, -10.0], np.zeros(num_uavs))

    # ------------------------------------------------------------------ frames
    def ned_to_geodetic(self, pos_ned: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """NED positions [k, 3] (m) -> (geodetic latitude deg, longitude deg, height above ground ft)."""
        geo = ned_to_geodetic(pos_ned, self.params.origin_lat_deg, self.params.origin_lon_deg)
        return geo[:, 0], geo[:, 1], geo[:, 2] / FT_TO_M

    def geodetic_to_ned(self, lat_deg: np.ndarray, lon_deg: np.ndarray, h_agl_ft: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`ned_to_geodetic`; returns [k, 3] metres."""
        geo = np.stack([np.asarray(lat_deg, dtype=np.float64), np.asarray(lon_deg, dtype=np.float64),
                        np.asarray(h_agl_ft, dtype=np.float64) * FT_TO_M], axis=-1)
        return geodetic_to_ned(geo, self.params.origin_lat_deg, self.params.origin_lon_deg)

    # ------------------------------------------------------------------ API
    def reset(self, index: np.ndarray, pos_ned: np.ndarray, yaw_rad: np.ndarray) -> None:
        index = np.asarray(index, dtype=np.int64).reshape(-1)
        pos_ned = np.asarray(pos_ned, dtype=np.float64).reshape(-1, 3)
        yaw_deg = np.degrees(np.broadcast_to(np.asarray(yaw_rad, dtype=np.float64), index.shape))
        lat, lon, h_ft = self.ned_to_geodetic(pos_ned)
        af = self.airframe
        for j, m in enumerate(index):
            fdm = self._fdms[m]
            fdm["ic/lat-geod-deg"] = lat[j]
            fdm["ic/long-gc-deg"] = lon[j]
            fdm["ic/h-agl-ft"] = h_ft[j]
            fdm["ic/psi-true-deg"] = yaw_deg[j]
            for name in ("ic/phi-rad", "ic/theta-rad", "ic/u-fps", "ic/v-fps", "ic/w-fps",
                         "ic/p-rad_sec", "ic/q-rad_sec", "ic/r-rad_sec"):
                fdm[name] = 0.0
            _set_motors(fdm, af.hover_throttle)
            fdm.run_ic()
            self._spin_up(fdm)
            self._read_state(m)
        self._ctrl[index, 0:6] = 0.0
        self._ctrl[index, 6:9] = self._state[index, 6:9]
        self._motor[index] = af.hover_throttle
        self._publish(index)

    def step(self, cmd_frd: np.ndarray, dt_s: float, active: np.ndarray) -> None:
        idx = np.flatnonzero(np.asarray(active, dtype=bool))
        if idx.size == 0 or dt_s <= 0.0:
            return
        n_sub = max(1, math.ceil(dt_s / self.params.fdm_dt_s - 1e-9))
        h = dt_s / n_sub
        if h != self._dt_s:  # keep every FDM on one step so the period is covered exactly
            for fdm in self._fdms:
                fdm.set_dt(h)
            self._dt_s = h
        cmd = np.ascontiguousarray(cmd_frd, dtype=np.float64)
        af = self.airframe
        state, ctrl, motor, gains = self._state, self._ctrl, self._motor, self._gains
        # UAV-major: one FDM's memory stays in cache for all its sub-steps (about twice as
        # fast as sweeping all FDMs each sub-step once there are more than a few dozen).
        for m in idx:
            fdm = self._fdms[m]
            u = motor[m]
            for _ in range(n_sub):
                _control(m, state, cmd, h, ctrl, gains, af.mixer, af.thrust_table_n, af.throttle_table, motor)
                fdm["fcs/cmdFR_ext_nd"] = u[0]
                fdm["fcs/cmdAL_ext_nd"] = u[1]
                fdm["fcs/cmdFL_ext_nd"] = u[2]
                fdm["fcs/cmdAR_ext_nd"] = u[3]
                fdm.run()
                state[m] = [fdm[name] for name in _STATE_PROPS]
        self._publish(idx)

    # ------------------------------------------------------------------ internals
    def _spin_up(self, fdm: jsbsim.FGFDMExec) -> None:
        """Run the propellers at hover throttle, airframe held still, until their speed settles.

        ``run_ic()`` keeps the propellers' speed, so after each step it puts the airframe back
        at its initial conditions: only the propellers move. The step is longer than in flight
        (the propeller speed, time constant ~60 ms, is all that is integrated).
        """
        p = self.params
        rpm = self._rpms(fdm)
        fdm.set_dt(p.spinup_dt_s)
        for _ in range(max(1, int(round(p.spinup_max_s / p.spinup_dt_s)))):
            fdm.run()
            fdm.run_ic()
            new = self._rpms(fdm)
            # Near hover speed (it varies a little with air density) and no longer changing;
            # a stopped motor does not move in its first step, hence the first test.
            settled = (np.max(np.abs(new - self.airframe.hover_rpm)) < 0.02 * self.airframe.hover_rpm
                       and np.max(np.abs(new - rpm)) < p.spinup_tol_rpm)
            rpm = new
            if settled:
                break
        fdm.set_dt(self._dt_s)

    @staticmethod
    def _rpms(fdm: jsbsim.FGFDMExec) -> np.ndarray:
        return np.array([fdm[f"propulsion/engine[{i}]/propeller-rpm"] for i in range(4)])

    def _read_state(self, m: int) -> None:
        fdm = self._fdms[m]
        self._state[m] = [fdm[name] for name in _STATE_PROPS]

    def _publish(self, index: np.ndarray) -> None:
        """Copy JSBSim's state of UAVs ``index`` into the public NED arrays."""
        fdms = self._fdms
        geo = np.array([
            (fdms[m]["position/lat-geod-deg"], fdms[m]["position/long-gc-deg"], fdms[m]["position/h-agl-ft"])
            for m in index
        ]).reshape(-1, 3)
        self.pos_ned[index] = self.geodetic_to_ned(geo[:, 0], geo[:, 1], geo[:, 2])
        st = self._state[index]
        self.vel_ned[index] = st[:, 0:3] * FT_TO_M
        self.yaw_rad[index] = wrap_angle_rad(st[:, 5])
        self.yaw_rate_rad_s[index] = st[:, 9]


@numba.njit(cache=True)
def _clip(x, lo, hi):
    return min(max(x, lo), hi)


@numba.njit(cache=True)
def _control(m, state, cmd, h, ctrl, gains, mixer, thrust_tab, throttle_tab, motor):
    """One controller update of UAV ``m``: ``state[m]`` (JSBSim units) -> ESC commands ``motor[m]``.

    ``ctrl[m]`` holds the velocity integrators (NED, m/s^2), the rate integrators (rad/s^2)
    and the previous body rates (for the D term); ``gains`` is packed by JSBSimDynamics.
    """
    (mass, ixx, iyy, izz, thrust_min, g,
     kp_h, ki_h, kp_v, ki_v, vel_i_max, vel_i_band,
     acc_h_max, acc_up_max, acc_down_max, max_tilt,
     att_kp, max_tilt_rate,
     kp_rp, ki_rp, kd_rp, kp_y, ki_y, rate_i_max, rate_i_band) = (
        gains[0], gains[1], gains[2], gains[3], gains[4], gains[5],
        gains[6], gains[7], gains[8], gains[9], gains[10], gains[11],
        gains[12], gains[13], gains[14], gains[15],
        gains[16], gains[17],
        gains[18], gains[19], gains[20], gains[21], gains[22], gains[23], gains[24])
    thrust_max = thrust_tab[-1]
    vn = state[m, 0] * 0.3048
    ve = state[m, 1] * 0.3048
    vd = state[m, 2] * 0.3048
    phi = state[m, 3]
    theta = state[m, 4]
    psi = state[m, 5]
    c = math.cos(psi)
    s = math.sin(psi)
    # 1. velocity PI -> desired NED acceleration
    en = c * cmd[m, 0] - vn
    ee = s * cmd[m, 0] - ve
    ed = cmd[m, 1] - vd
    an = kp_h * en + ctrl[m, 0]
    ae = kp_h * ee + ctrl[m, 1]
    ad = kp_v * ed + ctrl[m, 2]
    norm_h = math.sqrt(an * an + ae * ae)
    # Integrators act only near the setpoint and uncapped: they are there for small steady
    # forces (drag, propeller inflow), not to wind up during a step.
    if norm_h > acc_h_max:
        an *= acc_h_max / norm_h
        ae *= acc_h_max / norm_h
    elif en * en + ee * ee < vel_i_band * vel_i_band:
        ctrl[m, 0] = _clip(ctrl[m, 0] + ki_h * en * h, -vel_i_max, vel_i_max)
        ctrl[m, 1] = _clip(ctrl[m, 1] + ki_h * ee * h, -vel_i_max, vel_i_max)
    if -acc_up_max <= ad <= acc_down_max and abs(ed) < vel_i_band:
        ctrl[m, 2] = _clip(ctrl[m, 2] + ki_v * ed * h, -vel_i_max, vel_i_max)
    ad = _clip(ad, -acc_up_max, acc_down_max)
    # 2. thrust vector -> roll/pitch setpoints (heading frame) and collective thrust
    ax = c * an + s * ae
    ay = -s * an + c * ae
    lift = g - ad
    theta_sp = _clip(math.atan2(-ax, lift), -max_tilt, max_tilt)
    phi_sp = _clip(math.atan2(ay * math.cos(theta_sp), lift), -max_tilt, max_tilt)
    thrust = mass * lift / max(math.cos(phi) * math.cos(theta), 0.5)
    # 3. attitude P -> Euler rates -> body-rate setpoints
    phi_dot = _clip(att_kp * (phi_sp - phi), -max_tilt_rate, max_tilt_rate)
    theta_dot = _clip(att_kp * (theta_sp - theta), -max_tilt_rate, max_tilt_rate)
    psi_dot = cmd[m, 2]
    sphi = math.sin(phi)
    cphi = math.cos(phi)
    p_sp = phi_dot - psi_dot * math.sin(theta)
    q_sp = theta_dot * cphi + psi_dot * sphi * math.cos(theta)
    r_sp = -theta_dot * sphi + psi_dot * cphi * math.cos(theta)
    # 4. rate PI (+ D on the measured rate for roll/pitch) -> body torques
    p, q, r = state[m, 6], state[m, 7], state[m, 8]
    ep, eq, er = p_sp - p, q_sp - q, r_sp - r
    tx = ixx * (kp_rp * ep + ctrl[m, 3] - kd_rp * (p - ctrl[m, 6]) / h)
    ty = iyy * (kp_rp * eq + ctrl[m, 4] - kd_rp * (q - ctrl[m, 7]) / h)
    tz = izz * (kp_y * er + ctrl[m, 5])
    if abs(ep) < rate_i_band:
        ctrl[m, 3] = _clip(ctrl[m, 3] + ki_rp * ep * h, -rate_i_max, rate_i_max)
    if abs(eq) < rate_i_band:
        ctrl[m, 4] = _clip(ctrl[m, 4] + ki_rp * eq * h, -rate_i_max, rate_i_max)
    if abs(er) < rate_i_band:
        ctrl[m, 5] = _clip(ctrl[m, 5] + ki_y * er * h, -rate_i_max, rate_i_max)
    ctrl[m, 6] = p
    ctrl[m, 7] = q
    ctrl[m, 8] = r
    # 5. mixer: thrust, roll and pitch first, then as much yaw as the motors' range leaves
    thrust = _clip(thrust, 4.0 * thrust_min, 4.0 * thrust_max)
    lo = -1e300
    hi = 1e300
    for i in range(4):
        base = _clip(mixer[i, 0] * thrust + mixer[i, 1] * tx + mixer[i, 2] * ty, thrust_min, thrust_max)
        motor[m, i] = base  # thrust for now; throttle below
        w = mixer[i, 3]
        if w > 0.0:
            lo = max(lo, (thrust_min - base) / w)
            hi = min(hi, (thrust_max - base) / w)
        elif w < 0.0:
            lo = max(lo, (thrust_max - base) / w)
            hi = min(hi, (thrust_min - base) / w)
    tz = _clip(tz, lo, hi) if lo <= hi else 0.0
    for i in range(4):
        thrust_i = _clip(motor[m, i] + mixer[i, 3] * tz, thrust_min, thrust_max)
        motor[m, i] = np.interp(thrust_i, thrust_tab, throttle_tab)
