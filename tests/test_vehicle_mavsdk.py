"""MAVSDK, an independent MAVLink implementation, reads the simulated vehicle's telemetry.

If our vehicle's heartbeat, custom modes or telemetry messages were malformed, MAVSDK would
not discover it as an autopilot or would decode other modes and positions.
"""

from __future__ import annotations

import time

import pytest

from tests.companion_helpers import Processes, Rig

pytestmark = pytest.mark.timeout(60)


def _poll(getter, ok, timeout_s: float = 8.0):
    deadline = time.monotonic() + timeout_s
    value = getter()
    while not ok(value) and time.monotonic() < deadline:
        time.sleep(0.1)
        value = getter()
    return value


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_mavsdk_discovers_the_vehicle_and_reads_its_telemetry(tmp_path, autopilot):
    from mavsdk import ComponentType, Configuration, Mavsdk
    from mavsdk.plugins.telemetry import Telemetry

    with Processes(tmp_path) as procs:
        rig = Rig(procs, tmp_path)
        sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        try:
            assert int(sdk.add_any_connection(f"udpin://127.0.0.1:{rig.gcs_port}")) == 0  # SUCCESS
            rig.start_vehicle("--autopilot", autopilot, "--airborne", "--start", "4,-2,-6", "--yaw-deg", "90")
            system = sdk.first_autopilot(20.0)
            assert system is not None, "MAVSDK did not discover the simulated autopilot"
            telemetry = Telemetry(system)
            pv = _poll(telemetry.position_velocity_ned, lambda v: abs(v.position.north_m - 4.0) < 0.05)
            assert (pv.position.north_m, pv.position.east_m, pv.position.down_m) == pytest.approx((4.0, -2.0, -6.0), abs=0.05)
            assert _poll(telemetry.armed, bool) is True
            assert _poll(telemetry.in_air, bool) is True
            heading = _poll(telemetry.heading, lambda h: abs(h.heading_deg - 90.0) < 1.0)
            assert heading.heading_deg == pytest.approx(90.0, abs=1.0)
            mode = _poll(telemetry.flight_mode, lambda m: m.name != "UNKNOWN")
            assert mode.name == "HOLD"  # MAVSDK's name for PX4's AUTO.LOITER and ArduCopter's LOITER
            if autopilot == "px4":
                odom = _poll(telemetry.odometry, lambda o: abs(o.position_body.z_m + 6.0) < 0.05)
                assert odom.position_body.x_m == pytest.approx(4.0, abs=0.05)
        finally:
            sdk.destroy()
