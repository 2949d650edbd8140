"""The RealSense source through the real SDK: z16 frames injected with ``rs.software_device``.

No camera is needed: a software device with a D435-like depth stream (848x480 z16, 87 deg,
an off-centre principal point) feeds the SDK's own syncer, and the companion's
:class:`RealSenseDepthSource` streams from it exactly as from a connected camera: depth scale,
"no data" zeros, the crop to the policy's field of view, min-pooling, the blinded check.
Skips with the reason where pyrealsense2 does not import (no wheel for this platform, or its
libusb missing).
"""

from __future__ import annotations

import math
import select
import threading
import time

import numpy as np
import pytest

# exc_type=ImportError: the wheel installs without libusb-1.0 and then fails to load its library; skip then too.
rs = pytest.importorskip("pyrealsense2", reason="pyrealsense2 is not importable here (pip install 'swarmnav[realsense]'; "
                         "it needs libusb-1.0)", exc_type=ImportError)

from companion.depth_sources import (  # noqa: E402
    DepthFault,
    DepthFrame,
    DepthSourceError,
    RealSenseDepthSource,
    RealSenseSensorStream,
)
from companion.spec import CameraSpec  # noqa: E402

W, H, FPS = 848, 480, 30
HFOV_DEG = 87.0
FX = (W / 2) / math.tan(math.radians(HFOV_DEG / 2))
PPX, PPY = 421.7, 238.2  # a real D435's principal point is a few pixels off centre
DEPTH_UNITS_M = 0.0005  # not the usual 1 mm: the scale must come from the device
#: A policy camera a RealSense covers (87 x 58 deg sensor): 80 deg wide, 32x20 -> 55.3 deg high.
POLICY = CameraSpec(width=32, height=20, hfov_deg=80.0, max_range_m=20.0)


class SoftwareCamera:
    """A ``rs.software_device`` with one z16 depth stream, and a thread that injects frames."""

    def __init__(self) -> None:
        self.device = rs.software_device()
        self.device.register_info(rs.camera_info.name, "swarmnav test D435 (software)")
        self.sensor = self.device.add_sensor("Stereo Module")
        intr = rs.intrinsics()
        intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy = W, H, FX, FX, PPX, PPY
        intr.model, intr.coeffs = rs.distortion.brown_conrady, [0.0] * 5
        stream = rs.video_stream()
        stream.type, stream.index, stream.uid = rs.stream.depth, 0, 0
        stream.width, stream.height, stream.fps, stream.bpp, stream.fmt = W, H, FPS, 2, rs.format.z16
        stream.intrinsics = intr
        self.profile = self.sensor.add_video_stream(stream)
        self.sensor.add_read_only_option(rs.option.depth_units, DEPTH_UNITS_M)
        self.current: np.ndarray | None = None  # the scene the feeder thread injects
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def stream(self) -> RealSenseSensorStream:
        return RealSenseSensorStream(self.sensor, self.profile)

    def play(self, pixels: np.ndarray) -> None:
        """Inject ``pixels`` (uint16 [H, W]) at the stream's rate from a thread, as the camera would, until
        :meth:`stop`; assigning :attr:`current` changes the scene."""
        self.current = pixels

        def run() -> None:
            vsp = self.profile.as_video_stream_profile()
            number = 0
            while not self._stop.is_set():
                number += 1
                frame = rs.software_video_frame()
                frame.pixels, frame.stride, frame.bpp = np.ascontiguousarray(self.current), W * 2, 2
                frame.timestamp, frame.domain = time.time() * 1000.0, rs.timestamp_domain.hardware_clock
                frame.frame_number, frame.profile = number, vsp
                self.sensor.on_video_frame(frame)
                time.sleep(1.0 / FPS)
        self._thread = threading.Thread(target=run, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)


def _column(bearing_deg: float) -> float:
    return PPX + math.tan(math.radians(bearing_deg)) * FX


def _scene() -> np.ndarray:
    """A wall 6 m ahead, a pole 2 m away 20 deg right, a box 1 m away outside the policy's FOV, sky above."""
    z16 = np.full((H, W), round(6.0 / DEPTH_UNITS_M), np.uint16)
    centre = int(round(_column(20.0)))
    z16[:, centre - 4: centre + 5] = round(2.0 / DEPTH_UNITS_M)
    z16[:, int(_column(42.0)):] = round(1.0 / DEPTH_UNITS_M)  # 42..43.5 deg: the sensor sees it, the policy (40) not
    z16[: int(PPY - math.tan(math.radians(20)) * FX)] = 0  # no stereo match above 20 deg up: sky
    return z16


def _collect(source: RealSenseDepthSource, done, timeout_s: float = 30.0) -> list:
    """What the source delivers until ``done(items)`` is true (the source keeps only the newest frame)."""
    items: list = []
    deadline = time.monotonic() + timeout_s
    while not done(items) and time.monotonic() < deadline:
        select.select([source.fileno()], [], [], 0.2)
        items.extend(source.poll(time.monotonic()))
    return items


def test_injected_z16_frames_become_the_policys_depth_through_the_sdk():
    camera = SoftwareCamera()
    source = RealSenseDepthSource(POLICY, device=camera.stream())
    source.start()
    try:
        assert source.depth_scale_m == pytest.approx(DEPTH_UNITS_M)
        assert source.hfov_deg == pytest.approx(HFOV_DEG, abs=0.2)
        camera.play(_scene())
        items = _collect(source, lambda got: sum(isinstance(i, DepthFrame) for i in got) >= 5)
        camera.current = np.zeros((H, W), np.uint16)  # a covered lens: no pixel has data
        after = _collect(source, lambda got: any(isinstance(i, DepthFault) for i in got))
    finally:
        camera.stop()
        source.close()
    frames = [i for i in items if isinstance(i, DepthFrame)]
    faults = [i for i in after if isinstance(i, DepthFault)]
    assert len(frames) >= 5, f"{len(frames)} frames came through the SDK: {items[:3]}"
    seqs = [f.seq for f in frames]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)  # the SDK's frame numbers, in order
    depth = frames[0].depth_m
    assert depth.shape == (POLICY.height, POLICY.width) and depth.dtype == np.float32
    # Rows whose whole block lies above 20 deg up are sky ("no data": max range); 20 deg up is
    # row (1 - tan 20 / tan_half_vfov) * 10 of the policy's 20.
    sky_rows = int(math.floor((1 - math.tan(math.radians(20)) / POLICY.tan_half_vfov) * POLICY.height / 2))
    assert sky_rows >= 2 and np.all(depth[:sky_rows] == POLICY.max_range_m)
    ground = depth[sky_rows + 1:]
    # The pole (2 m) lies in the policy columns whose directions include 20 deg right.
    tangents = (np.arange(POLICY.width + 1) * 2 / POLICY.width - 1) * POLICY.tan_half_hfov
    pole_cols = [c for c in range(POLICY.width) if tangents[c] - 0.01 <= math.tan(math.radians(20)) <= tangents[c + 1] + 0.01]
    assert pole_cols and np.allclose(ground[:, pole_cols], 2.0)
    others = [c for c in range(POLICY.width) if c not in pole_cols and c not in (pole_cols[0] - 1, pole_cols[-1] + 1)]
    assert np.allclose(ground[:, others], 6.0)  # the 1 m box beyond 40 deg never shows: cropped away
    assert any("depth blinded" in f.reason for f in faults), [f.reason for f in faults]


def test_a_policy_wider_than_the_sensor_is_refused_at_start_with_the_reason():
    camera = SoftwareCamera()
    wide = CameraSpec(width=32, height=32, hfov_deg=90.0)  # 90 x 90 deg: wider than the sensor's 87 x 58
    source = RealSenseDepthSource(wide, device=camera.stream())
    with pytest.raises(DepthSourceError, match=r"does not cover the policy's 90.0 deg") as info:
        source.start()
    assert "\n" not in str(info.value)
    source.close()
