"""The raycast depth camera against a brute-force reference and against geometry by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.spec import CameraSpec
from sitl.sim.camera import EDGE_HOLE_MODELS, DepthCamera, SceneGeometry, StereoNoise
from tests.reference_camera import render_reference


def _random_scene(rng, worlds, per_world):
    pos = np.column_stack([
        rng.uniform(-4, 4, worlds * per_world),
        rng.uniform(-4, 4, worlds * per_world),
        rng.uniform(-6, -1, worlds * per_world),
    ])
    yaw = rng.uniform(-math.pi, math.pi, worlds * per_world)
    visible = rng.random(worlds * per_world) > 0.15
    boxes = np.zeros((worlds, 2, 6))
    boxes[:, 0] = [3.0, 1.0, -3.0, 0.5, 1.0, 1.5]
    boxes[:, 1, :3] = rng.uniform(-5, 5, (worlds, 3)) * [1, 1, 0.3] - [0, 0, 3]
    boxes[:, 1, 3:] = rng.uniform(0.2, 1.0, (worlds, 3))
    cylinders = np.zeros((worlds, 2, 5))
    cylinders[:, 0] = [-3.0, 2.0, 0.6, -7.0, 0.0]  # a pole standing on the ground
    cylinders[:, 1] = [0.0, -4.0, 0.4, -5.0, -2.0]  # a floating one: its caps are visible
    return pos, yaw, visible, boxes, cylinders


@pytest.mark.parametrize("supersample", [1, 3])
def test_kernel_matches_reference(supersample):
    rng = np.random.default_rng(7)
    spec = CameraSpec(width=10, height=7, hfov_deg=100.0, max_range_m=12.0)
    geom = SceneGeometry(body_radius_m=0.6, body_half_height_m=0.3)  # large bodies: many pixels hit
    pos, yaw, visible, boxes, cylinders = _random_scene(rng, worlds=2, per_world=5)
    fast = DepthCamera(spec, supersample, geom).render(pos, yaw, 5, visible, boxes, cylinders)
    slow = render_reference(spec, supersample, pos, yaw, 5, visible, geom.body_radius_m,
                            geom.body_half_height_m, boxes, cylinders)
    assert fast.shape == (10, 7, 10) and fast.dtype == np.float32
    np.testing.assert_allclose(fast, slow, atol=2e-4)
    # The scene is not trivially empty: UAVs, obstacles and the ground all show up.
    assert (fast < spec.max_range_m).mean() > 0.3


def test_parallel_kernel_matches_serial():
    rng = np.random.default_rng(3)
    spec = CameraSpec(width=16, height=16)
    pos, yaw, visible, boxes, cylinders = _random_scene(rng, worlds=3, per_world=4)
    serial = DepthCamera(spec, 2).render(pos, yaw, 4, visible, boxes, cylinders)
    parallel = DepthCamera(spec, 2, parallel=True).render(pos, yaw, 4, visible, boxes, cylinders)
    np.testing.assert_array_equal(serial, parallel)


def test_uav_straight_ahead_reads_distance_minus_radius():
    spec = CameraSpec(width=32, height=32)
    pos = np.array([[0.0, 0.0, -100.0], [0.0, 5.0, -100.0]])  # 5 m apart, high above the ground
    yaw = np.array([math.pi / 2, 0.0])  # first one faces east
    depth = DepthCamera(spec, 4).render(pos, yaw, 2)
    # Off-axis sub-rays graze the flat body a little below its nose: 5 - R + <2 cm.
    assert 5.0 - 0.3 <= depth[0].min() <= 5.0 - 0.3 + 0.02
    rows, cols = np.nonzero(depth[0] < spec.max_range_m - 1)
    # Centred in the image, where the optical axis is.
    assert set(cols) <= {15, 16} and set(rows) <= {15, 16}
    # The second UAV faces north, so the first one is 90 deg to its left: outside +-45 deg.
    assert depth[1].min() == pytest.approx(spec.max_range_m)


def test_uav_at_safe_distance_covers_pixels_at_default_resolution():
    spec = CameraSpec()  # the default observation camera
    pos = np.array([[0.0, 0.0, -10.0], [5.0, 0.0, -10.0], [0.0, 0.0, -30.0], [3.0, 2.9, -29.0]])
    depth = DepthCamera(spec, 4).render(pos, np.zeros(4), 2)
    # d_safe = 5 m straight ahead: a 0.6 m x 0.24 m body still covers whole pixels.
    assert (depth[0] < 5.0).sum() >= 2
    # Far off-axis and only partly inside a pixel: min-pooling keeps it.
    assert (depth[2] < 5.0).sum() >= 1


def test_ground_depth_is_planar():
    spec = CameraSpec(width=8, height=8, hfov_deg=90.0, max_range_m=50.0)
    depth = DepthCamera(spec, 1).render(np.array([[0.0, 0.0, -2.0]]), np.zeros(1), 1)
    # Bottom row centre ray looks down at tan = (2*7.5/8 - 1) = 0.875: planar depth = h / tan.
    assert depth[0, 7, 3] == pytest.approx(2.0 / 0.875, rel=1e-5)
    # Same depth across a row: planar, not Euclidean, distance.
    assert np.ptp(depth[0, 7]) == 0.0
    # Rows at or above the horizon see nothing.
    assert np.all(depth[0, :4] == 50.0)


def test_invisible_uavs_are_not_drawn_and_no_self_view():
    spec = CameraSpec(width=16, height=16)
    pos = np.array([[0.0, 0.0, -100.0], [3.0, 0.0, -100.0]])
    cam = DepthCamera(spec, 2)
    seen = cam.render(pos, np.zeros(2), 2, visible=np.array([True, True]))
    hidden = cam.render(pos, np.zeros(2), 2, visible=np.array([True, False]))
    assert seen[0].min() < 3.0 and hidden[0].min() == spec.max_range_m
    # Worlds are separate: the same two UAVs split into two worlds of one see nothing.
    assert cam.render(pos, np.zeros(2), 1).min() == spec.max_range_m


def test_stereo_noise_grows_with_depth_squared():
    rng = np.random.default_rng(0)
    near = np.full((200, 32, 32), 2.0, dtype=np.float32)
    far = np.full((200, 32, 32), 8.0, dtype=np.float32)
    noise = StereoNoise(edge_hole_prob=0.0, blob_prob=0.0)
    noisy_near, noisy_far = noise.apply(near, 10.0, rng), noise.apply(far, 10.0, rng)
    kept_near, kept_far = noisy_near[noisy_near > 0], noisy_far[noisy_far > 0]
    coeff = noise.baseline_m and noise.subpixel_px / (noise.focal_px * noise.baseline_m)
    assert kept_near.std() == pytest.approx(coeff * 4, rel=0.1)
    assert kept_far.std() == pytest.approx(coeff * 64, rel=0.1)
    # Holes: the per-pixel dropout everywhere, plus far pixels failing to match more often.
    hole_near, hole_far = (noisy_near == 0).mean(), (noisy_far == 0).mean()
    assert hole_near == pytest.approx(0.01 + 0.3 * 0.2 ** 2, abs=0.005)
    assert hole_far == pytest.approx(0.01 + 0.3 * 0.8 ** 2, abs=0.01)


def test_stereo_noise_reports_no_data_as_zero_not_a_noisy_far_wall():
    rng = np.random.default_rng(1)
    spec = CameraSpec(width=32, height=24, hfov_deg=87.0, vfov_deg=58.0, max_range_m=10.0)
    # Level, 15 m up: nothing within 10 m, every pixel is sky or far ground.
    perfect = DepthCamera(spec, 2).render(np.array([[0.0, 0.0, -15.0]]), np.zeros(1), 1)
    assert np.all(perfect == spec.max_range_m)
    noisy = StereoNoise().apply(perfect, spec.max_range_m, rng)
    assert np.all(noisy == 0.0)


def test_edge_holes_fall_in_the_occlusion_shadow_not_on_the_nearer_surface():
    """A stereo pair cannot match the strip of far surface left of a nearer one (depth is the left
    imager's): only that side of a vertical edge gets holes; the near surface keeps its depth."""
    rng = np.random.default_rng(2)
    edges_only = dict(dropout_prob=0.0, far_hole_prob=0.0, blob_prob=0.0)
    depth = np.full((400, 8, 8), 9.0, dtype=np.float32)
    depth[:, :, 4:] = 2.0  # a near surface on the right: its shadow falls on column 3
    holes = (StereoNoise(**edges_only).apply(depth, 10.0, rng) == 0).mean(axis=(0, 1))
    assert holes[3] == pytest.approx(0.3, abs=0.05)
    assert np.all(holes[[0, 1, 2, 4, 5, 6, 7]] == 0)
    mirrored = depth[:, :, ::-1].copy()  # near on the left: the strip the right imager misses is behind it
    assert np.all(StereoNoise(**edges_only).apply(mirrored, 10.0, rng) > 0)
    above = np.full((400, 8, 8), 9.0, dtype=np.float32)
    above[:, 4:, :] = 2.0  # a horizontal edge: no parallax along a horizontal baseline
    assert np.all(StereoNoise(**edges_only).apply(above, 10.0, rng) > 0)
    # The training noise (sessions <= 34's model) erases both sides of every edge, the near one too.
    both = StereoNoise(**edges_only, edge_holes="both")
    holes = (both.apply(depth, 10.0, rng) == 0).mean(axis=(0, 1))
    assert holes[3] == pytest.approx(0.3, abs=0.05) and holes[4] == pytest.approx(0.3, abs=0.05)
    assert holes[0] == 0 and holes[7] == 0
    assert (both.apply(above, 10.0, rng) == 0).mean(axis=(0, 2))[4] == pytest.approx(0.3, abs=0.05)
    # The threshold is a quarter of the NEARER (right-hand) depth: 1.3 against 1.0 is an edge, and
    # the hole is the far pixel's only.
    step = np.full((400, 4, 2), 1.0, dtype=np.float32)
    step[:, :, 0] = 1.3
    holes = (StereoNoise(**edges_only).apply(step, 10.0, rng) == 0).mean(axis=(0, 1))
    assert holes[0] == pytest.approx(0.3, abs=0.05) and holes[1] == 0
    step[:, :, 0] = 1.24  # 24 % farther: no edge
    assert np.all(StereoNoise(**edges_only).apply(step, 10.0, rng) > 0)
    with pytest.raises(ValueError, match="edge_holes"):
        StereoNoise(edge_holes="left")


def test_pitched_camera_and_nearest_object_match_reference():
    rng = np.random.default_rng(11)
    spec = CameraSpec(width=9, height=6, hfov_deg=87.0, vfov_deg=58.0, max_range_m=12.0)
    geom = SceneGeometry(body_radius_m=0.6, body_half_height_m=0.3)
    pos, yaw, visible, boxes, cylinders = _random_scene(rng, worlds=2, per_world=5)
    pitch = rng.uniform(-0.4, 0.4, 10)
    fast, nearest = DepthCamera(spec, 2, geom).render_with_objects(pos, yaw, 5, visible, boxes, cylinders,
                                                                   pitch_rad=pitch)
    slow, slow_nearest = render_reference(spec, 2, pos, yaw, 5, visible, geom.body_radius_m, geom.body_half_height_m,
                                          boxes, cylinders, pitch_rad=pitch, with_objects=True)
    np.testing.assert_allclose(fast, slow, atol=2e-4)
    np.testing.assert_allclose(nearest, slow_nearest, atol=2e-4)
    assert (nearest < spec.max_range_m).sum() >= 3  # objects are in view of several cameras


def test_pitch_moves_the_horizon_and_the_ground_is_not_an_object():
    spec = CameraSpec(width=8, height=31, hfov_deg=60.0, vfov_deg=40.0, max_range_m=50.0)
    cam = DepthCamera(spec, 1)
    pos = np.array([[0.0, 0.0, -2.0]])
    level, nearest = cam.render_with_objects(pos, np.zeros(1), 1)
    down = cam.render(pos, np.zeros(1), 1, pitch_rad=np.radians([-10.0]))
    up = cam.render(pos, np.zeros(1), 1, pitch_rad=np.radians([10.0]))
    first_ground_row = lambda img: int(np.argmax(img[:, 0] < spec.max_range_m))  # noqa: E731
    assert first_ground_row(down[0]) < first_ground_row(level[0]) < first_ground_row(up[0])
    assert level[0, :16].min() == spec.max_range_m  # nothing at or above the horizon (the centre row)
    # The ground fills the lower half of the image, but no UAV or obstacle is in view.
    assert level.min() < 6.0 and nearest[0] == spec.max_range_m
    # Planar depth of the ground in the centre row of a camera pitched down 10 deg: 2 / sin(10 deg).
    assert down[0, 15, 0] == pytest.approx(2.0 / math.sin(math.radians(10.0)), rel=0.02)


def test_bad_arguments():
    with pytest.raises(ValueError, match="supersample"):
        DepthCamera(CameraSpec(), 0)
    with pytest.raises(ValueError, match="do not split"):
        DepthCamera(CameraSpec(), 1).render(np.zeros((3, 3)), np.zeros(3), 2)
    with pytest.raises(ValueError, match="hfov"):
        CameraSpec(hfov_deg=200)


@pytest.mark.parametrize("preset", ["realsense_d435", "wide_stereo"])
def test_a_simulated_real_sensor_image_becomes_what_the_policy_was_trained_on(preset):
    """sitl.vehicle's 160x90 image of a real sensor (a D435, a wide stereo camera), through the companion's
    converter (cropped to the policy's field in both axes, min-pooled), matches the policy camera's render."""
    from companion.depth_sources import DepthConverter
    from companion.spec import CAMERA_PRESETS, SENSOR_PRESETS

    policy_cam, sensor_cam = CAMERA_PRESETS[preset], SENSOR_PRESETS[preset]
    pos = np.array([[0.0, 0.0, -2.5], [5.0, 1.0, -2.5]])  # 2.5 m up, a UAV 5 m ahead, slightly right
    sensor = DepthCamera(sensor_cam, 2).render(pos, np.zeros(2), 2)[0]
    converted = DepthConverter(policy_cam, max_invalid_fraction=1.0).convert(sensor, sensor_cam.hfov_deg)
    trained = DepthCamera(policy_cam, 4).render(pos, np.zeros(2), 2)[0]
    assert converted.shape == trained.shape == (policy_cam.height, policy_cam.width)
    assert converted.min() == pytest.approx(trained.min(), abs=0.05)  # the UAV, ~4.7 m
    # Same picture: the ground rows and the UAV's pixels agree to within a pixel's footprint.
    assert np.mean(np.abs(converted - trained) < 0.5) > 0.9


def _stereo_noise_numpy(noise: StereoNoise, depth_m: np.ndarray, max_range_m: float,
                        rng: np.random.Generator) -> np.ndarray:
    """The NumPy expression :meth:`StereoNoise.apply` was until session 68, kept as its oracle."""
    depth_m = np.asarray(depth_m, dtype=np.float32)
    coeff = np.float32(noise.quadratic_coeff_per_m)
    noisy = depth_m + rng.standard_normal(depth_m.shape, dtype=np.float32) * (coeff * depth_m * depth_m)
    z = np.clip(depth_m, 0.0, max_range_m) / np.float32(max_range_m)
    invalid = (depth_m >= max_range_m) | (depth_m < noise.min_range_m)
    invalid |= rng.random(depth_m.shape, dtype=np.float32) < noise.far_hole_prob * z * z + noise.dropout_prob
    if noise.edge_hole_prob > 0:
        edge = np.zeros(depth_m.shape, dtype=bool)
        if noise.edge_holes == "shadow":
            left, right = depth_m[..., :-1], depth_m[..., 1:]
            edge[..., :-1] = left - right > noise.edge_jump_fraction * right
        else:
            frac = noise.edge_jump_fraction
            jump = np.abs(np.diff(depth_m, axis=-1)) > frac * np.minimum(depth_m[..., 1:], depth_m[..., :-1])
            edge[..., 1:] |= jump
            edge[..., :-1] |= jump
            jump = np.abs(np.diff(depth_m, axis=-2)) > frac * np.minimum(depth_m[..., 1:, :], depth_m[..., :-1, :])
            edge[..., 1:, :] |= jump
            edge[..., :-1, :] |= jump
        invalid |= edge & (rng.random(depth_m.shape, dtype=np.float32) < noise.edge_hole_prob)
    height, width = depth_m.shape[-2:]
    mask = invalid.reshape(-1, height, width)
    for k in np.flatnonzero(rng.random(mask.shape[0]) < noise.blob_prob):
        bh, bw = rng.integers(2, noise.blob_max_px + 1, size=2)
        top, left = rng.integers(0, max(height - bh, 0) + 1), rng.integers(0, max(width - bw, 0) + 1)
        mask[k, top:top + bh, left:left + bw] = True
    noisy = np.maximum(noisy, np.float32(noise.min_range_m))
    noisy[mask.reshape(depth_m.shape)] = 0.0
    return noisy


@pytest.mark.parametrize("edge_holes", EDGE_HOLE_MODELS)
def test_compiled_stereo_noise_equals_the_numpy_expression_bit_for_bit(edge_holes):
    """The same draws give the same noisy image as the NumPy expression, so every number measured
    before the compiled pass (session 68) reproduces exactly: thresholds included (depths exactly at
    the range, at min_range, and steps exactly at the edge jump)."""
    rng = np.random.default_rng(5)
    depth = (rng.random((2, 40, 20, 32), dtype=np.float32) * 24.0).astype(np.float32)
    depth[0, :, :, :4] = 20.0  # exactly at the range: invalid
    depth[0, :, :, 4:6] = np.float32(0.2)  # exactly at min_range
    depth[1, :, :, 8], depth[1, :, :, 9] = 5.0, 4.0  # a jump of exactly 0.25 of the nearer side
    depth[1, :, 5:8, :] = 1.0  # a near band: horizontal and vertical edges
    for noise in (StereoNoise(edge_holes=edge_holes), StereoNoise(edge_holes=edge_holes, edge_hole_prob=0.0),
                  StereoNoise(edge_holes=edge_holes, blob_prob=1.0, edge_hole_prob=1.0)):
        expected = _stereo_noise_numpy(noise, depth, 20.0, np.random.default_rng(7))
        got = noise.apply(depth, 20.0, np.random.default_rng(7))
        assert got.dtype == np.float32 and got.shape == depth.shape
        np.testing.assert_array_equal(got, expected)
