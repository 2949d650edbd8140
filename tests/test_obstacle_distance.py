"""OBSTACLE_DISTANCE: bins computed from known depth frames, and received by ``sitl.vehicle`` at the camera rate.

The unit tests place single obstacles at pixels whose bearing and distance follow from the
camera geometry; the end-to-end test flies the real ``companion`` (with the bundled ONNX
policy) next to a real ``sitl.vehicle`` hovering 10 m in front of a pole, over loopback UDP.
"""

from __future__ import annotations

import math
import os
import signal
import time

import numpy as np
import pytest

from companion.obstacle_distance import BIN_COUNT, MIN_DISTANCE_CM, UNKNOWN_CM, ObstacleBins
from companion.spec import CameraSpec
from tests.companion_helpers import REPO, Processes, Rig

CAM = CameraSpec(width=32, height=32, hfov_deg=90.0, max_range_m=20.0)  # spelled out: the bin arithmetic below is for it
NONE_CM = 2001  # max_distance (20 m) + 1: "no obstacle"


def _frame(cam: CameraSpec = CAM) -> np.ndarray:
    return np.full((cam.height, cam.width), cam.max_range_m, np.float32)


def _horizontal_cm(depth_m: float, column: int, cam: CameraSpec = CAM) -> int:
    tan_u = (2.0 * column + 1.0 - cam.width) / cam.width * math.tan(math.radians(cam.hfov_deg / 2))
    return int(math.floor(depth_m * math.sqrt(1.0 + tan_u**2) * 100.0))


def test_an_empty_frame_reports_no_obstacle_in_the_field_of_view_and_unknown_elsewhere():
    msg = ObstacleBins(CAM).compute(_frame())
    assert msg.distances_cm.shape == (BIN_COUNT,) and msg.increment_deg == 5.0
    assert msg.angle_offset_deg == -42.5  # bin 0 centred 42.5 deg left of the nose: 18 bins span the 90 deg
    assert msg.min_distance_cm == MIN_DISTANCE_CM and msg.max_distance_cm == 2000
    assert msg.distances_cm[:18].tolist() == [NONE_CM] * 18
    assert msg.distances_cm[18:].tolist() == [UNKNOWN_CM] * (BIN_COUNT - 18)


@pytest.mark.parametrize("column, bins", [(31, [17]), (0, [0]), (16, [9]), (15, [8])])
def test_a_single_pixel_obstacle_lands_in_the_bin_of_its_bearing_at_its_horizontal_distance(column, bins):
    # Column 31's directions span atan(30/32)..atan(32/32) = 43.2..45 deg: bin 17 (40..45 deg);
    # column 16 spans 0..3.6 deg (bin 9, 0..5), column 15 -3.6..0 deg (bin 8).
    frame = _frame()
    frame[16, column] = 3.0  # just below the optical axis: 0.09 m below the camera, inside the band
    msg = ObstacleBins(CAM).compute(frame)
    expected = [NONE_CM] * 18
    for b in bins:
        expected[b] = _horizontal_cm(3.0, column)
    assert msg.distances_cm[:18].tolist() == expected
    assert msg.distances_cm[18:].tolist() == [UNKNOWN_CM] * (BIN_COUNT - 18)


def test_a_wall_reads_nearest_at_the_nose_and_farther_towards_the_edges():
    frame = _frame()
    frame[:, :] = 4.0  # a wall 4 m ahead, perpendicular to the axis
    bins = ObstacleBins(CAM).compute(frame).distances_cm[:18]
    assert bins[8] == bins[9] == _horizontal_cm(4.0, 16)  # the columns next to the axis
    assert bins[0] == bins[17] and bins[0] > bins[4] > bins[8]  # symmetric, 4 m / cos(bearing)
    assert abs(int(bins[0]) - 400 / math.cos(math.radians(40))) < 10  # the bin's inner edge is 40 deg


def test_the_ground_below_and_obstacles_above_the_band_are_not_obstacles_and_near_ones_clamp():
    frame = _frame()
    frame[31, 10] = 3.0  # bottom row: 2.9 m below the camera (the ground while hovering at 3 m)
    frame[0, 20] = 3.0  # top row: 2.9 m above
    assert ObstacleBins(CAM).compute(frame).distances_cm[:18].tolist() == [NONE_CM] * 18
    frame[31, 10] = 0.8  # the same pixel 0.8 m away is 0.78 m below: inside the 1 m band
    frame[16, 16] = 0.05  # nearer than the sensor's minimum: reported at the minimum
    bins = ObstacleBins(CAM).compute(frame).distances_cm
    assert bins[9] == MIN_DISTANCE_CM
    column_10_bins = [i for i in range(18) if bins[i] != NONE_CM and i != 9]
    assert column_10_bins and all(bins[i] == _horizontal_cm(0.8, 10) for i in column_10_bins)


def test_a_field_of_view_that_is_not_a_multiple_of_5_degrees_still_covers_every_bin_it_spans():
    cam = CameraSpec(width=48, height=32, hfov_deg=87.0)
    frame = _frame(cam)
    frame[:, :] = 5.0
    msg = ObstacleBins(cam).compute(frame)
    assert msg.angle_offset_deg == -42.5  # ceil(87 / 5) = 18 bins
    assert all(20 < d < NONE_CM for d in msg.distances_cm[:18]) and msg.distances_cm[18] == UNKNOWN_CM


@pytest.mark.timeout(200)
def test_sitl_vehicle_receives_the_bins_at_the_camera_rate_and_the_option_turns_them_off(tmp_path):
    """Companion (bundled ONNX policy, no goal: it streams holds) beside a vehicle hovering 10 m before a pole."""
    camera_hz = 30.0
    with Processes(tmp_path / "on") as on_procs, Processes(tmp_path / "off") as off_procs:
        rigs = {}
        for name, procs, extra in (("on", on_procs, ()), ("off", off_procs, ("--no-obstacle-distance",))):
            (tmp_path / name).mkdir()
            rig = Rig(procs, tmp_path / name)
            rig.start_vehicle("--airborne", "--start", "0,0,-3", "--cylinder", "10,0,0.5", "--camera-hz", str(camera_hz))
            rig.start_companion(REPO / "models" / "policy.onnx", "--heartbeat-timeout", "90", *extra)
            rigs[name] = rig
        for rig in rigs.values():
            rig.wait_for_event(lambda r: r.get("kind") == "step" and r.get("phase") == "streaming_hold", 100,
                               "a hold streamed with fresh depth")
        time.sleep(4.0)
        for rig in rigs.values():
            os.killpg(rig.companion.pid, signal.SIGTERM)
            assert rig.wait_companion(15) == 0
    on, off = rigs["on"], rigs["off"]
    model = [r for r in on.companion_records() if r.get("event") == "model"][0]
    assert model["runtime"] == "onnxruntime" and model["providers"] == ["CPUExecutionProvider"]
    sent = [r for r in on.companion_records() if r["kind"] == "summary"][-1]["obstacle_distance_sent"]
    windows = [r for r in on.vehicle_records() if r["event"] == "obstacle_distance"]
    assert len(windows) >= 3, f"the vehicle logged {len(windows)} one-second windows of OBSTACLE_DISTANCE"
    received = sum(w["messages"] for w in windows)
    assert sent - 2 * camera_hz <= received <= sent  # the last window is still open when the companion stops
    rate = float(np.median([w["rate_hz"] for w in windows]))
    assert 0.85 * camera_hz <= rate <= 1.1 * camera_hz, f"OBSTACLE_DISTANCE at {rate} Hz, camera at {camera_hz} Hz"
    last = windows[-1]
    assert last["frame"] == 12 and last["angle_offset_deg"] == -42.5 and last["increment_deg"] == 5.0
    bins, none_cm = last["distances_cm"], last["max_distance_cm"] + 1
    fov_bins = round(-2 * last["angle_offset_deg"] / 5.0) + 1  # 18 for a 90 or 87 deg policy camera
    centre = (fov_bins // 2 - 1, fov_bins // 2)  # the two sectors either side of the nose
    # The pole (radius 0.5 m, 10 m ahead) subtends +-2.9 deg: the sectors -5..0 and 0..5 deg, at ~9.5 m.
    assert all(900 <= bins[b] <= 1000 for b in centre), bins[:fov_bins]
    assert [bins[b] for b in range(fov_bins) if b not in centre] == [none_cm] * (fov_bins - 2)  # not the ground 3 m below
    assert bins[fov_bins:] == [UNKNOWN_CM] * (BIN_COUNT - fov_bins)
    assert [r for r in off.companion_records() if r["kind"] == "summary"][-1]["obstacle_distance_sent"] == 0
    assert not [r for r in off.vehicle_records() if r["event"] == "obstacle_distance"]
