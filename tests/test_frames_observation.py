"""Frame conventions and the shared observation code (companion.observation)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from companion.frames import frd_to_ned, ned_to_frd, wrap_angle_rad
from companion.observation import (
    DepthFrameError,
    DepthFrameStack,
    RememberedDepth,
    build_state,
    crop_to_hfov,
    min_pool_depth,
    validate_depth_frame,
)
from companion.spec import (DEFAULT_ACTION_SPEC, REALSENSE_D435, STATE_NAMES, CameraSpec, MemorySpec, state_dim_for,
                            state_names_for)
from sitl.sim.dynamics import KinematicDynamics


def test_heading_frame_rotation():
    # Facing east (yaw +90 deg), north is to the left and east is straight ahead.
    east_frd = ned_to_frd(np.array([0.0, 1.0, 0.0]), math.pi / 2)
    north_frd = ned_to_frd(np.array([1.0, 0.0, 0.0]), math.pi / 2)
    np.testing.assert_allclose(east_frd, [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(north_frd, [0, -1, 0], atol=1e-12)
    rng = np.random.default_rng(0)
    vec, yaw = rng.normal(size=(50, 3)), rng.uniform(-4, 4, 50)
    np.testing.assert_allclose(frd_to_ned(ned_to_frd(vec, yaw), yaw), vec, atol=1e-12)
    assert wrap_angle_rad(3 * math.pi / 2) == pytest.approx(-math.pi / 2)


def test_forward_command_with_yaw_90_moves_east():
    dyn = KinematicDynamics(1)
    dyn.reset(np.array([0]), np.array([[0.0, 0.0, -10.0]]), np.array([math.pi / 2]))
    for _ in range(50):  # 5 s
        dyn.step(np.array([[2.0, 0.0, 0.0]]), 0.1, np.array([True]))
    north, east, down = dyn.pos_ned[0]
    assert east > 8.0 and abs(north) < 1e-6 and down == pytest.approx(-10.0)
    np.testing.assert_allclose(dyn.vel_ned[0], [0.0, 2.0, 0.0], atol=1e-3)


def test_positive_yaw_rate_turns_right_and_down_command_descends():
    dyn = KinematicDynamics(1)
    dyn.reset(np.array([0]), np.array([[0.0, 0.0, -10.0]]), np.array([0.0]))
    for _ in range(30):
        dyn.step(np.array([[0.0, 0.5, 0.5]]), 0.1, np.array([True]))
    assert 1.2 < dyn.yaw_rad[0] < 1.5  # ~0.5 rad/s for 3 s minus the spin-up, towards east
    assert dyn.pos_ned[0, 2] > -9.0  # z down grew: it descended
    state = build_state(dyn.pos_ned, dyn.yaw_rad, dyn.vel_ned, dyn.yaw_rate_rad_s, np.array([[0.0, 0.0, -10.0]]))
    assert state[0, 4] == pytest.approx(0.5, abs=1e-3)  # vel_down_m_s
    assert state[0, 5] == pytest.approx(0.5, abs=1e-3)  # yaw_rate_rad_s


def test_kinematic_response_has_lag_and_acceleration_limit():
    dyn = KinematicDynamics(1)
    dyn.reset(np.array([0]), np.array([[0.0, 0.0, -10.0]]), np.array([0.0]))
    dyn.step(np.array([[2.0, 0.0, 0.0]]), 0.1, np.array([True]))
    assert 0.0 < dyn.vel_ned[0, 0] <= 3.0 * 0.1 + 1e-9  # capped at 3 m/s^2
    frozen = dyn.pos_ned.copy()
    dyn.step(np.array([[2.0, 0.0, 0.0]]), 0.1, np.array([False]))
    np.testing.assert_array_equal(dyn.pos_ned, frozen)


def test_state_is_goal_in_body_frame_then_velocity():
    # UAV at the origin facing east, goal 3 m east, 4 m north, 1 m above it.
    state = build_state(np.array([[0.0, 0.0, -5.0]]), np.array([math.pi / 2]),
                        np.array([[0.0, 1.5, -0.2]]), np.array([0.1]), np.array([[4.0, 3.0, -6.0]]))
    np.testing.assert_allclose(state[0], [3.0, -4.0, -1.0, 1.5, -0.2, 0.1], atol=1e-6)
    assert state.dtype == np.float32


def test_min_pool_keeps_nearest_valid_pixel():
    frame = np.full((4, 6), 9.0, dtype=np.float32)
    frame[0, 0] = 2.0
    frame[3, 5] = 0.0  # a stereo camera's "no data"
    frame[2, 4] = np.nan
    frame[1, 3] = 50.0  # beyond max range
    pooled = min_pool_depth(frame, 2, 3, max_range_m=20.0)
    np.testing.assert_array_equal(pooled, [[2.0, 9.0, 9.0], [9.0, 9.0, 9.0]])
    empty = min_pool_depth(np.zeros((4, 4), np.float32), 2, 2, 20.0)
    assert np.all(empty == 20.0)  # nothing valid: no obstacle known
    odd = min_pool_depth(np.arange(35, dtype=np.float32).reshape(5, 7) + 1, 2, 3, 100.0)
    assert odd.shape == (2, 3) and odd[0, 0] == 1.0
    with pytest.raises(DepthFrameError, match="smaller"):
        min_pool_depth(frame, 8, 8, 20.0)


def test_crop_to_policy_field_of_view():
    target = CameraSpec(width=4, height=4, hfov_deg=90.0)
    wide = np.arange(12 * 16, dtype=np.float32).reshape(12, 16)
    # A 126.87 deg camera (tan half = 2) keeps the central half of its width.
    crop = crop_to_hfov(wide, math.degrees(2 * math.atan(2.0)), target)
    assert crop.shape == (8, 8) and crop[0, 0] == wide[2, 4]
    with pytest.raises(DepthFrameError, match="narrower"):
        crop_to_hfov(wide, 60.0, target)


def test_validate_depth_frame_rejects_malformed_frames():
    spec = CameraSpec(width=4, height=3)
    good = validate_depth_frame(np.full((3, 4), 3.0), spec)
    assert good.dtype == np.float32
    with pytest.raises(DepthFrameError, match="shape"):
        validate_depth_frame(np.zeros((4, 3)), spec)
    with pytest.raises(DepthFrameError, match="dtype"):
        validate_depth_frame(np.zeros((3, 4), dtype=np.uint16), spec)
    with pytest.raises(DepthFrameError, match="depth blinded: 100 % of pixels invalid"):
        validate_depth_frame(np.full((3, 4), np.nan), spec)


def test_frame_stack_is_oldest_first():
    spec = CameraSpec(width=2, height=2, frames=3)
    stack = DepthFrameStack(2, spec)
    stack.reset(np.full((2, 2, 2), 1.0))
    stack.push(np.full((2, 2, 2), 2.0))
    stack.push(np.full((1, 2, 2), 3.0), np.array([1]))
    assert stack.frames[0, :, 0, 0].tolist() == [1.0, 1.0, 2.0]
    assert stack.frames[1, :, 0, 0].tolist() == [1.0, 2.0, 3.0]
    assert stack.latest[1, 0, 0] == 3.0


def test_frame_stack_with_a_stride_spans_longer():
    spec = CameraSpec(width=2, height=2, frames=3, frame_stride=3)
    assert spec.history_frames == 7
    stack = DepthFrameStack(1, spec)
    stack.reset(np.full((2, 2), 0.0))
    for value in range(1, 9):
        stack.push(np.full((2, 2), float(value)))
        # The newest frame, the one 3 pushes before it and the one 6 before (0: the first frame).
        assert stack.frames[0, :, 0, 0].tolist() == [max(value - 6, 0), max(value - 3, 0), value]
    assert stack.frames.shape == (1, 3, 2, 2) and stack.latest[0, 0, 0] == 8.0
    with pytest.raises(ValueError, match="frame_stride"):
        CameraSpec(frame_stride=0)


def test_frame_stack_at_listed_ages():
    """frame_ages (6, 1, 0): the newest frame, the one before it and the one 6 pushes back."""
    spec = CameraSpec(width=2, height=2, frames=3, frame_ages=(6, 1, 0))
    assert spec.history_frames == 7 and spec.describe_stack() == " at ticks t-6, t-1, t"
    stack = DepthFrameStack(1, spec)
    stack.reset(np.full((2, 2), 0.0))
    for value in range(1, 9):
        stack.push(np.full((2, 2), float(value)))
        assert stack.frames[0, :, 0, 0].tolist() == [max(value - 6, 0), value - 1, value]
    for ages, reason in [((1, 0), "one age per stacked frame"), ((1, 2, 0), "decrease strictly"),
                         ((2, 1, 1), "decrease strictly"), ((99, 1, 0), "oldest at most")]:
        with pytest.raises(ValueError, match=reason):
            CameraSpec(frames=3, frame_ages=ages)
    with pytest.raises(ValueError, match="replace frame_stride"):
        CameraSpec(frames=3, frame_ages=(6, 1, 0), frame_stride=2)


def test_action_spec_clips_and_rejects_nan():
    spec = DEFAULT_ACTION_SPEC
    clipped = spec.validate(np.array([[3.0, -1.0, 0.7], [-1.0, 0.2, -0.9]]))
    np.testing.assert_allclose(clipped, [[2.0, -0.5, 0.5], [0.0, 0.2, -0.5]])
    with pytest.raises(ValueError, match="non-finite"):
        spec.validate(np.array([[np.nan, 0.0, 0.0]]))
    with pytest.raises(ValueError, match="out of bounds"):
        spec.validate(np.array([[3.0, 0.0, 0.0]]), clip=False)
    with pytest.raises(ValueError, match="shape"):
        spec.validate(np.zeros((2, 2)))


def test_clean_depth_is_the_one_invalid_pixel_conversion():
    from companion.observation import clean_depth

    raw = np.array([[0.0, -1.0, np.nan, np.inf], [0.3, 9.99, 10.0, 42.0]], dtype=np.float32)
    np.testing.assert_array_equal(clean_depth(raw, 10.0),
                                  np.float32([[10.0, 10.0, 10.0, 10.0], [0.3, 9.99, 10.0, 10.0]]))
    # The companion's path (min-pool, validate) gives the same values as the simulator's.
    spec = CameraSpec(width=4, height=2, max_range_m=10.0)
    np.testing.assert_array_equal(validate_depth_frame(raw, spec, max_invalid_fraction=1.0), clean_depth(raw, 10.0))


def test_crop_to_both_fields_of_view_of_a_realsense():
    from companion.spec import REALSENSE_D435, REALSENSE_D435_SENSOR

    sensor = np.arange(90 * 160, dtype=np.float32).reshape(90, 160) + 1
    crop = crop_to_hfov(sensor, REALSENSE_D435_SENSOR.hfov_deg, REALSENSE_D435)
    # 87 of 90 deg wide (tan ratio 0.949 -> 152 of 160 columns), 58 of 58.7 deg high (89 of 90 rows).
    assert crop.shape == (89, 152) and crop[0, 0] == sensor[0, 4]
    assert min_pool_depth(crop, 32, 48, 10.0).shape == (32, 48)
    # A sensor with the right width but a narrower vertical field is refused in one line.
    with pytest.raises(DepthFrameError, match=r"^camera vfov 48\.5 deg is narrower than the policy's 58\.0 deg$"):
        crop_to_hfov(np.ones((72, 160), np.float32), 90.0, REALSENSE_D435)
    # An explicit source vfov overrides the square-pixel assumption.
    assert crop_to_hfov(np.ones((72, 160), np.float32), 90.0, REALSENSE_D435, source_vfov_deg=60.0).shape[0] == 69


def test_preset_for_camera_names_the_sensor_a_policy_needs():
    import dataclasses

    from companion.spec import CAMERA_PRESETS, WIDE_STEREO, preset_for_camera

    for name, preset in CAMERA_PRESETS.items():
        assert preset_for_camera(preset) == name
    # Another grid, stack or mount pitch is the same sensor; another field of view or range is not.
    assert preset_for_camera(dataclasses.replace(WIDE_STEREO, width=48, height=32, frames=4,
                                                 mount_pitch_deg=5.0)) == "wide_stereo"
    with pytest.raises(ValueError, match=r"^no camera preset has a 110 x 80\.0 deg field of view with a 12 m range"):
        preset_for_camera(dataclasses.replace(WIDE_STEREO, vfov_deg=80.0))


def test_blinded_check_default_is_off_for_a_real_sensor_only():
    from companion.observation import default_max_invalid_fraction
    from companion.spec import MAX_INVALID_DEPTH_FRACTION, REALSENSE_D435

    assert default_max_invalid_fraction(CameraSpec()) == MAX_INVALID_DEPTH_FRACTION
    assert default_max_invalid_fraction(REALSENSE_D435) == 1.0
    # Off means an all-invalid frame (open sky above the sensor's range) is not a fault.
    validate_depth_frame(np.zeros((REALSENSE_D435.height, REALSENSE_D435.width), np.float32), REALSENSE_D435,
                         max_invalid_fraction=1.0)


def _one_surface_frame(camera: CameraSpec, depth_m: float, rows: slice, cols: slice) -> np.ndarray:
    frame = np.full((1, camera.height, camera.width), camera.max_range_m, np.float32)
    frame[0, rows, cols] = depth_m
    return frame


def test_remembered_depth_keeps_a_surface_that_left_the_view_in_the_right_sector():
    """A surface seen 2 m ahead stays in the memory, in the sector it lies in from wherever the vehicle
    is now (odometry moves it), until it is older than the memory."""
    memory = MemorySpec(steps=4, every_steps=2, range_m=5.0, pool=2)
    names = memory.state_names()
    remembered = RememberedDepth(1, REALSENSE_D435, memory)
    centre = _one_surface_frame(REALSENSE_D435, 2.0, slice(9, 11), slice(15, 17))
    empty = _one_surface_frame(REALSENSE_D435, 2.0, slice(0, 0), slice(0, 0))
    still = (np.zeros((1, 3)), np.zeros(1))
    remembered.reset(centre, *still)
    ranges = dict(zip(names, remembered.sector_ranges(*still)[0]))
    assert ranges["memory_level_az000_m"] == pytest.approx(2.0, abs=0.05)
    assert all(v == 5.0 for k, v in ranges.items() if k != "memory_level_az000_m")
    # Turned 90 deg right and 1 m up: the surface is now on the left, 2.2 m away, slightly below.
    moved = (np.array([[0.0, 0.0, -1.0]]), np.array([math.pi / 2]))
    remembered.push(empty, *moved)
    ranges = dict(zip(names, remembered.sector_ranges(*moved)[0]))
    near = {k: v for k, v in ranges.items() if v < 5.0}
    assert set(near) == {"memory_low_az270_m"} and near["memory_low_az270_m"] == pytest.approx(math.hypot(2, 1), abs=0.1)
    # Straight above it, the surface is in the down cap; far from it, nothing is near.
    assert remembered.sector_ranges(np.array([[2.0, 0.0, -1.5]]), np.zeros(1))[0][names.index("memory_down_m")] < 1.6
    assert np.all(remembered.sector_ranges(np.array([[20.0, 0.0, 0.0]]), np.zeros(1)) == 5.0)
    # Forgotten once older than `steps`: 4 more empty frames push it out of the 2 slots.
    for _ in range(4):
        remembered.push(empty, *moved)
    assert np.all(remembered.sector_ranges(*moved) == 5.0)


def test_remembered_depth_unprojects_with_the_mount_pitch_and_resets_per_row():
    pitched = dataclasses.replace(REALSENSE_D435, mount_pitch_deg=30.0)
    memory = MemorySpec(steps=2, every_steps=1, range_m=5.0, pool=1)
    remembered = RememberedDepth(2, pitched, memory)
    frame = _one_surface_frame(pitched, 2.0, slice(9, 11), slice(15, 17))  # the optical axis, 30 deg up
    remembered.reset(np.repeat(frame, 2, axis=0), np.zeros((2, 3)), np.zeros(2))
    names = memory.state_names()
    ranges = remembered.sector_ranges(np.zeros((2, 3)), np.zeros(2))
    assert ranges[0, names.index("memory_high_az000_m")] == pytest.approx(2.0, abs=0.15)  # 15-45 deg up
    remembered.reset(_one_surface_frame(pitched, 2.0, slice(0, 0), slice(0, 0)), np.zeros((1, 3)), np.zeros(1),
                     index=np.array([1]))
    ranges = remembered.sector_ranges(np.zeros((2, 3)), np.zeros(2))
    assert ranges[0].min() < 2.1 and np.all(ranges[1] == 5.0)  # row 1 forgot, row 0 did not


def test_remembered_depth_outside_view_counts_only_what_the_camera_does_not_show_now():
    memory = MemorySpec(steps=4, every_steps=2, range_m=5.0, pool=2, outside_view=True)
    names = memory.state_names()
    remembered = RememberedDepth(1, REALSENSE_D435, memory)
    remembered.reset(_one_surface_frame(REALSENSE_D435, 2.0, slice(9, 11), slice(15, 17)), np.zeros((1, 3)), np.zeros(1))
    assert np.all(remembered.sector_ranges(np.zeros((1, 3)), np.zeros(1)) == 5.0)  # in view: the image has it
    turned = remembered.sector_ranges(np.zeros((1, 3)), np.array([math.pi / 2]))[0]  # out of view on the left
    assert {k for k, v in zip(names, turned) if v < 5.0} == {"memory_level_az270_m"}


def test_memory_spec_names_its_state_and_refuses_bad_settings():
    memory = MemorySpec()
    assert memory.slots == 5 and len(memory.state_names()) == memory.num_sectors == 26
    assert state_names_for(None) == STATE_NAMES and state_names_for(memory)[len(STATE_NAMES):] == memory.state_names()
    assert state_dim_for(None) == 6 and state_dim_for(memory) == len(state_names_for(memory)) == 32
    for bad in ({"steps": 0}, {"every_steps": 11}, {"range_m": 0.0}, {"pool": 0}, {"outside_view": 1}):
        with pytest.raises(ValueError, match="memory"):
            MemorySpec(**bad)
