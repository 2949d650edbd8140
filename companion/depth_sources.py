"""Depth cameras behind one interface, converted to exactly what the policy's metadata says.

Three sources (``--camera``):

* ``sitl:PORT`` or ``sitl:HOST:PORT`` — the frames ``python -m sitl.vehicle`` renders,
  one UDP datagram each (format: :mod:`companion.depth_wire`); the companion listens.
  It locks to the first vehicle index it hears, or to ``VEHICLE`` with ``sitl:PORT:VEHICLE``
  / ``sitl:HOST:PORT:VEHICLE``, and faults frames from any other vehicle.
* ``realsense`` or ``realsense:WIDTHxHEIGHT@FPS`` — an Intel RealSense through
  ``pyrealsense2`` (optional extra ``swarmnav[realsense]``): z16 pixels times the device's
  depth scale, zeros are "no data", not obstacles at 0 m.
* ``replay:PATH`` or ``replay:PATH,loop`` — the depth frames of a flight recording
  (:mod:`companion.recording`) at their recorded timing.

Every frame goes through :class:`DepthConverter`: cropped to the policy's horizontal field
of view and aspect (:func:`companion.observation.crop_to_hfov`; a RealSense around its principal
point from its intrinsics, :func:`crop_to_policy_fov`), min-pooled over valid
pixels to the policy's resolution (:func:`companion.observation.min_pool_depth`) and
checked (:func:`companion.observation.validate_depth_frame`) — the code the simulator
uses. A frame that cannot be converted becomes a :class:`DepthFault` with the reason, which
the control loop answers with a hold.

Sources never block: the control loop waits on :meth:`DepthSource.fileno` (or wakes at
:meth:`DepthSource.next_due_s`) and calls :meth:`DepthSource.poll`.
"""

from __future__ import annotations

import math
import os
import socket
import struct
import threading
import time
from abc import ABC, abstractmethod
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion.depth_wire import MAX_DATAGRAM, decode_frame
from companion.observation import (
    DepthBlindedError,
    DepthFrameError,
    check_not_blinded,
    crop_to_hfov,
    min_pool_depth,
    validate_depth_frame,
)
from companion.spec import MAX_INVALID_DEPTH_FRACTION, CameraSpec

_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux value; Python does not export it


class DepthSourceError(RuntimeError):
    """A depth source that cannot be opened or has failed for good."""


@dataclass
class DepthFrame:
    """A frame ready for the policy: float32 [H, W] planar metres in the policy's layout."""

    depth_m: np.ndarray
    arrival_s: float  # time.monotonic() at which it reached this computer
    seq: int
    source_stamp_us: int | None = None


@dataclass
class DepthFault:
    """A frame that arrived but cannot be used (malformed, wrong size, dead sensor...)."""

    reason: str
    arrival_s: float


class DepthConverter:
    """Turns any camera's planar depth image into the policy's input frame.

    Args:
        camera: the policy's camera (from its metadata).
    """

    def __init__(self, camera: CameraSpec, max_invalid_fraction: float = MAX_INVALID_DEPTH_FRACTION) -> None:
        self.camera = camera
        self.max_invalid_fraction = max_invalid_fraction  # above it a frame is a blinded sensor (spec.py)

    def convert(self, depth_m: np.ndarray, source_hfov_deg: float) -> np.ndarray:
        """Return float32 [H, W] for the policy; raise :class:`DepthFrameError` if impossible."""
        raw = np.asarray(depth_m)
        if raw.ndim != 2:
            raise DepthFrameError(f"depth frame must be 2-D [H, W], got shape {raw.shape}")
        if not np.issubdtype(raw.dtype, np.floating):
            raise DepthFrameError(f"depth frame must be floating-point metres, got dtype {raw.dtype}")
        # Counted on the raw pixels: pooling would turn a covered lens (all 0) into "all clear".
        check_not_blinded(raw, self.max_invalid_fraction)
        cam = self.camera
        if raw.shape == (cam.height, cam.width) and abs(source_hfov_deg - cam.hfov_deg) < 1e-3:
            return validate_depth_frame(raw, cam, self.max_invalid_fraction)
        cropped = crop_to_hfov(raw, source_hfov_deg, cam)
        pooled = min_pool_depth(cropped, cam.height, cam.width, cam.max_range_m)
        return validate_depth_frame(pooled, cam, self.max_invalid_fraction)


def z16_to_metres(z16: np.ndarray, depth_scale_m: float) -> np.ndarray:
    """A RealSense z16 image (uint16) in metres; 0 (no data) stays 0 and is invalid downstream."""
    z16 = np.asarray(z16)
    if z16.dtype != np.uint16:
        raise DepthFrameError(f"z16 frame must be uint16, got {z16.dtype}")
    return z16.astype(np.float32) * np.float32(depth_scale_m)


class DepthSource(ABC):
    """A depth camera as the control loop sees it."""

    name: str = "depth"

    @abstractmethod
    def start(self) -> None:
        """Open the device or socket; raise :class:`DepthSourceError` with the reason if impossible."""

    def fileno(self) -> int | None:
        """A descriptor that becomes readable when frames wait, or None."""
        return None

    def next_due_s(self) -> float | None:
        """Monotonic time at which :meth:`poll` has something to return, for timer-driven sources."""
        return None

    @abstractmethod
    def poll(self, now_s: float) -> list[DepthFrame | DepthFault]:
        """Everything that arrived since the last call, oldest first (never blocks)."""

    def set_stale_limit(self, limit_s: float) -> None:
        """How old (s) a frame may be when it arrives, for sources whose frames carry a capture stamp."""

    def close(self) -> None:
        """Release the device or socket."""


# --------------------------------------------------------------------------- SITL


class FrameTiming:
    """Refuses replayed, reordered and old frames by the sender's stamps, without synchronized clocks.

    The sender stamps each frame with its own clock (``stamp_us``, microseconds). A frame
    whose stamp does not move forward is a replay or reordered; a frame is stale when its
    ``arrival - stamp`` exceeds the smallest ``arrival - stamp`` of the last ``window``
    accepted frames (the clock offset plus the fastest transport seen) by more than
    ``stale_limit_s``. A single odd frame (e.g. a forged stamp far ahead) is refused and
    changes nothing; a sender whose clock steps or who restarts is followed again after
    ``resync_frames`` consecutive frames that agree with each other (a short hold).
    """

    def __init__(self, stale_limit_s: float = 0.15, window: int = 64, resync_frames: int = 5) -> None:
        self.stale_limit_s = stale_limit_s
        self.resync_frames = resync_frames
        self._offsets_s: deque[float] = deque(maxlen=window)
        self._last_stamp_us: int | None = None
        self._candidate: list[tuple[int, float]] = []  # a new, self-consistent stamp series

    def check(self, stamp_us: int, arrival_wall_s: float) -> str | None:
        """Accept the frame (None) or say why it cannot be used."""
        offset_s = arrival_wall_s - stamp_us * 1e-6
        if self._last_stamp_us is None:
            self._accept(stamp_us, offset_s)
            return None
        floor_s = min(self._offsets_s)
        problem = None
        if stamp_us <= self._last_stamp_us:
            what = "repeats" if stamp_us == self._last_stamp_us else "goes backwards"
            problem = (f"depth frame stamp {what} ({(stamp_us - self._last_stamp_us) / 1000.0:+.0f} ms): "
                       "replayed or reordered")
        elif offset_s - floor_s > self.stale_limit_s:
            problem = (f"depth frame stale: {(offset_s - floor_s) * 1000.0:.0f} ms older than the freshest frames "
                       f"(limit {self.stale_limit_s * 1000.0:.0f} ms)")
        elif floor_s - offset_s > self.stale_limit_s:
            problem = f"depth frame stamp jumped {(floor_s - offset_s) * 1000.0:.0f} ms ahead of the sender's clock"
        if problem is None:
            self._accept(stamp_us, offset_s)
            return None
        # A sustained series that is consistent with itself (a restarted sender, a clock step)
        # becomes the new reference; one forged or replayed frame never does.
        cand = self._candidate
        if cand and stamp_us > cand[-1][0] and abs(offset_s - min(o for _s, o in cand)) <= self.stale_limit_s:
            cand.append((stamp_us, offset_s))
        else:
            self._candidate = cand = [(stamp_us, offset_s)]
        if len(cand) >= self.resync_frames:
            self._offsets_s.clear()
            self._offsets_s.extend(o for _s, o in cand)
            self._last_stamp_us = stamp_us
            self._candidate = []
            return None
        return problem

    def _accept(self, stamp_us: int, offset_s: float) -> None:
        self._offsets_s.append(offset_s)
        self._last_stamp_us = stamp_us
        self._candidate = []


class SitlDepthSource(DepthSource):
    """Frames from ``python -m sitl.vehicle`` over loopback UDP (see :mod:`companion.depth_wire`).

    Arrival times are the kernel's receive timestamps (``SO_TIMESTAMPNS``), so latency
    figures include time a datagram spent queued while the loop was busy. The source locks
    to one vehicle index (``vehicle``, or the first one heard) and faults frames from any
    other, and refuses replayed, reordered and stale frames (:class:`FrameTiming`).
    """

    def __init__(self, host: str, port: int, camera: CameraSpec, vehicle: int | None = None) -> None:
        self.host, self.port = host, port
        self.name = f"sitl:{host}:{port}"
        self.converter = DepthConverter(camera)
        self.sock: socket.socket | None = None
        self.frames_superseded = 0  # frames that arrived together with a newer one
        self.vehicle = vehicle  # locked vehicle index (None: the first one heard)
        self.timing = FrameTiming()

    def set_stale_limit(self, limit_s: float) -> None:
        self.timing.stale_limit_s = limit_s

    def start(self) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((self.host, self.port))
        except OSError as err:
            sock.close()
            raise DepthSourceError(f"cannot listen for SITL depth frames on {self.host}:{self.port}: {err}") from err
        self.port = sock.getsockname()[1]  # the real port when asked for any (0)
        self.name = f"sitl:{self.host}:{self.port}"
        sock.setblocking(False)
        try:
            sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        except OSError:
            pass  # fall back to user-space arrival times
        self.sock = sock

    def fileno(self) -> int | None:
        return self.sock.fileno() if self.sock else None

    def poll(self, now_s: float) -> list[DepthFrame | DepthFault]:
        if self.sock is None:
            return []
        received: list[tuple[bytes, float, float]] = []
        mono_now, wall_now = time.monotonic(), time.time()
        while True:
            try:
                data, ancdata, _flags, _addr = self.sock.recvmsg(MAX_DATAGRAM + 1, 64)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                break
            arrival, arrival_wall = mono_now, wall_now
            for level, kind, payload in ancdata:
                if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(payload) >= 16:
                    sec, nsec = struct.unpack_from("qq", payload)
                    arrival_wall = sec + nsec * 1e-9
                    arrival = min(mono_now, mono_now - (wall_now - arrival_wall))
            received.append((data, arrival, arrival_wall))
        out: list[DepthFrame | DepthFault] = []
        newest = None  # the newest decodable frame of our vehicle: the only one worth converting
        for data, arrival, arrival_wall in received:
            try:
                wire = decode_frame(data)
            except DepthFrameError as err:
                out.append(DepthFault(f"malformed depth frame: {err}", arrival))
                continue
            if self.vehicle is None:
                self.vehicle = wire.vehicle  # lock to the first vehicle heard
            if wire.vehicle != self.vehicle:
                out.append(DepthFault(f"depth frame from vehicle {wire.vehicle}, but {self.name} is locked to "
                                      f"vehicle {self.vehicle}", arrival))
                continue
            if newest is not None:
                self.frames_superseded += 1  # a newer datagram of ours follows: not worth converting
            newest = (wire, arrival, arrival_wall)
        # Faults first, then our newest frame: a stray datagram arriving after it (another vehicle's,
        # or junk) is reported but does not hide the good frame the camera just delivered.
        if newest is not None:
            out.append(self._convert(*newest))
        return out

    def _convert(self, wire, arrival: float, arrival_wall: float) -> DepthFrame | DepthFault:
        """Our vehicle's newest frame as the policy's depth, or why it cannot be used."""
        problem = self.timing.check(wire.stamp_us, arrival_wall)
        if problem is not None:
            return DepthFault(f"{problem} (seq {wire.seq}, {self.name})", arrival)
        try:
            depth = self.converter.convert(wire.depth_m, wire.hfov_deg)
        except DepthBlindedError as err:
            return DepthFault(f"{err} ({self.name})", arrival)
        except DepthFrameError as err:
            return DepthFault(f"malformed depth frame: {err}", arrival)
        return DepthFrame(depth, arrival, wire.seq, wire.stamp_us)

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None


# --------------------------------------------------------------------------- replay


class ReplayDepthSource(DepthSource):
    """The depth frames of a flight recording, played at their recorded timing."""

    def __init__(self, path: str, camera: CameraSpec, loop: bool = False) -> None:
        self.path, self.loop = path, loop
        self.name = f"replay:{path}"
        self.converter = DepthConverter(camera)
        self._records = None
        self._offsets: np.ndarray | None = None
        self._hfov_deg = camera.hfov_deg
        self._t0 = 0.0
        self._index = 0

    def start(self) -> None:
        from companion.recording import RecordingError, read_recording

        try:
            header, records = read_recording(self.path)
        except (OSError, RecordingError) as err:
            raise DepthSourceError(f"cannot replay {self.path}: {err}") from err
        if len(records) == 0:
            raise DepthSourceError(f"cannot replay {self.path}: the recording holds no frame")
        self._records = records
        self._hfov_deg = float(header["camera"]["hfov_deg"])
        t = records["t_mono_s"]
        self._offsets = t - t[0]
        self._t0 = time.monotonic()
        self._index = 0

    def _period_s(self) -> float:
        offsets = self._offsets
        return float(offsets[-1] + (np.median(np.diff(offsets)) if len(offsets) > 1 else 0.1))

    def next_due_s(self) -> float | None:
        if self._offsets is None or self._index >= len(self._offsets):
            return None
        return self._t0 + float(self._offsets[self._index])

    def poll(self, now_s: float) -> list[DepthFrame | DepthFault]:
        if self._records is None:
            return []
        out: list[DepthFrame | DepthFault] = []
        due = None
        while self._index < len(self._offsets) and self._t0 + self._offsets[self._index] <= now_s:
            due = self._index
            self._index += 1
            if self._index == len(self._offsets) and self.loop:
                self._t0 += self._period_s()
                self._index = 0
        if due is not None:
            record = self._records[due]
            try:
                depth = self.converter.convert(np.array(record["depth_m"]), self._hfov_deg)
            except DepthBlindedError as err:
                out.append(DepthFault(f"{err} ({self.name})", now_s))
            except DepthFrameError as err:
                out.append(DepthFault(f"malformed depth frame in recording: {err}", now_s))
            else:
                out.append(DepthFrame(depth, now_s, int(record["frame_seq"]), None))
        return out


# --------------------------------------------------------------------------- RealSense


class RealSenseDevice:
    """What :class:`RealSenseDepthSource` needs from the RealSense SDK: a z16 depth stream.

    The default, :class:`RealSensePipeline`, opens the first connected camera through
    ``rs.pipeline``; :class:`RealSenseSensorStream` streams any SDK depth sensor (such as a
    ``rs.software_device``'s, which tests feed with frames) through an ``rs.syncer``.
    """

    def start(self):
        """Start streaming; return (depth scale in m per z16 unit, the stream's ``rs.intrinsics``)."""
        raise NotImplementedError

    def wait_for_frames(self, timeout_ms: int):
        """The next ``rs.composite_frame``; raise RuntimeError if none comes within ``timeout_ms``."""
        raise NotImplementedError

    def stop(self) -> None:
        """Stop streaming."""
        raise NotImplementedError


class RealSensePipeline(RealSenseDevice):
    """The first connected RealSense camera's depth stream through ``rs.pipeline``."""

    def __init__(self, width: int, height: int, fps: int) -> None:
        self.width, self.height, self.fps = width, height, fps
        self._pipeline = None

    def start(self):
        import pyrealsense2 as rs  # noqa: PLC0415 - optional extra

        pipeline = rs.pipeline()
        config = rs.config()
        config.enable_stream(rs.stream.depth, self.width, self.height, rs.format.z16, self.fps)
        profile = pipeline.start(config)
        self._pipeline = pipeline
        scale = float(profile.get_device().first_depth_sensor().get_depth_scale())
        return scale, profile.get_stream(rs.stream.depth).as_video_stream_profile().get_intrinsics()

    def wait_for_frames(self, timeout_ms: int):
        return self._pipeline.wait_for_frames(timeout_ms)

    def stop(self) -> None:
        if self._pipeline is not None:
            self._pipeline.stop()
            self._pipeline = None


class RealSenseSensorStream(RealSenseDevice):
    """One SDK depth sensor's z16 stream (``profile``) delivered through an ``rs.syncer``.

    Args:
        sensor: an ``rs.sensor`` that is a depth sensor (it reports ``depth_units``).
        profile: the ``rs.stream_profile`` of its z16 depth stream to open.
    """

    def __init__(self, sensor, profile) -> None:
        self.sensor, self.profile = sensor, profile
        self._syncer = None

    def start(self):
        import pyrealsense2 as rs  # noqa: PLC0415 - optional extra

        self._syncer = rs.syncer()
        self.sensor.open(self.profile)
        self.sensor.start(self._syncer)
        scale = float(self.sensor.as_depth_sensor().get_depth_scale())
        return scale, self.profile.as_video_stream_profile().get_intrinsics()

    def wait_for_frames(self, timeout_ms: int):
        return self._syncer.wait_for_frames(timeout_ms)

    def stop(self) -> None:
        if self._syncer is not None:
            self.sensor.stop()
            self.sensor.close()
            self._syncer = None


def crop_to_policy_fov(depth_m: np.ndarray, fx: float, fy: float, ppx: float, ppy: float,
                       target: CameraSpec) -> np.ndarray:
    """The pixels of a pinhole camera's frame [H, W] that lie within the policy's field of view.

    Keeps the columns whose centre direction ``(u - ppx) / fx`` lies within +-``tan_half_hfov``
    and the rows whose ``(v - ppy) / fy`` lies within +-``tan_half_vfov`` (RealSense
    intrinsics: pixel centres at integer coordinates), so the crop is centred on the optical
    axis even when the principal point is off-centre. Raises :class:`DepthFrameError` when the
    sensor does not see the whole of the policy's field of view (half a pixel of tolerance).
    """
    height, width = depth_m.shape[-2:]
    bounds = []
    for name, size, focal, centre, tan_half, fov_deg in (
            ("horizontal", width, fx, ppx, target.tan_half_hfov, target.hfov_deg),
            ("vertical", height, fy, ppy, target.tan_half_vfov, target.vfov_deg)):
        low, high = centre - tan_half * focal, centre + tan_half * focal
        if low < -0.5 or high > size - 0.5:
            seen = math.degrees(math.atan((centre + 0.5) / focal) + math.atan((size - 0.5 - centre) / focal))
            raise DepthFrameError(f"camera {name} field of view {seen:.1f} deg does not cover the policy's "
                                  f"{fov_deg:.1f} deg")
        bounds.append((max(0, math.ceil(low - 1e-9)), min(size - 1, math.floor(high + 1e-9)) + 1))
    (left, right), (top, bottom) = bounds
    return depth_m[..., top:bottom, left:right]


class RealSenseDepthSource(DepthSource):
    """An Intel RealSense depth stream through ``pyrealsense2`` (optional dependency).

    A background thread owns the device (``wait_for_frames`` blocks) and hands the newest
    frame to the control loop through a one-slot mailbox, waking it with a pipe. Each z16
    frame is scaled to metres by the device's depth scale (0 stays "no data"), cropped to
    the policy's field of view around the principal point (:func:`crop_to_policy_fov`) and
    converted like every other source (:class:`DepthConverter`: blinded check on the raw
    pixels, min-pool, validation).

    Args:
        camera: the policy's camera.
        width, height, fps: the stream to ask the connected camera for.
        device: the SDK device to stream from (default: :class:`RealSensePipeline`, the first
            connected camera); tests pass a :class:`RealSenseSensorStream` of a ``software_device``.
    """

    def __init__(self, camera: CameraSpec, width: int = 848, height: int = 480, fps: int = 30,
                 device: RealSenseDevice | None = None) -> None:
        self.width, self.height, self.fps = width, height, fps
        self.name = f"realsense:{width}x{height}@{fps}"
        self.converter = DepthConverter(camera)
        self.device = device or RealSensePipeline(width, height, fps)
        self._started = False
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._mailbox: list[DepthFrame | DepthFault] = []
        self._wake_r, self._wake_w = -1, -1
        self.depth_scale_m = 0.001
        self.hfov_deg = 87.0
        self.intrinsics: tuple[float, float, float, float] | None = None  # fx, fy, ppx, ppy (pixels)

    def start(self) -> None:
        try:
            import pyrealsense2  # noqa: F401, PLC0415 - optional extra
        except ImportError as err:
            raise DepthSourceError("the realsense camera needs pyrealsense2: pip install 'swarmnav[realsense]'") from err
        try:
            self.depth_scale_m, intr = self.device.start()
        except RuntimeError as err:
            raise DepthSourceError(f"cannot start the RealSense depth stream {self.width}x{self.height}@{self.fps}: {err}") from err
        self._started = True
        self.width, self.height = int(intr.width), int(intr.height)
        self.intrinsics = (float(intr.fx), float(intr.fy), float(intr.ppx), float(intr.ppy))
        self.hfov_deg = math.degrees(math.atan((intr.ppx + 0.5) / intr.fx) + math.atan((intr.width - 0.5 - intr.ppx) / intr.fx))
        if not (self.depth_scale_m > 0 and math.isfinite(self.depth_scale_m)):
            self.close()
            raise DepthSourceError(f"RealSense reports an invalid depth scale {self.depth_scale_m!r}")
        try:  # refuse a camera that does not see the policy's whole field of view now, not at the first frame
            crop_to_policy_fov(np.zeros((self.height, self.width), np.float32), *self.intrinsics, self.converter.camera)
        except DepthFrameError as err:
            self.close()
            raise DepthSourceError(f"RealSense cannot feed this policy: {err}") from err
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._thread = threading.Thread(target=self._run, name="realsense", daemon=True)
        self._thread.start()

    def convert(self, z16: np.ndarray) -> np.ndarray:
        """One z16 frame [H, W] as the policy's depth frame; raise :class:`DepthFrameError` if unusable."""
        metres = z16_to_metres(z16, self.depth_scale_m)
        cam = self.converter.camera
        check_not_blinded(metres, self.converter.max_invalid_fraction)  # on the sensor's own pixels, as convert does
        cropped = crop_to_policy_fov(metres, *self.intrinsics, cam)
        pooled = min_pool_depth(cropped, cam.height, cam.width, cam.max_range_m)
        return validate_depth_frame(pooled, cam, self.converter.max_invalid_fraction)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                frames = self.device.wait_for_frames(1000)
            except RuntimeError as err:  # timeout or device gone: the loop sees stale depth
                item: DepthFrame | DepthFault = DepthFault(f"RealSense delivered no frame: {err}", time.monotonic())
            else:
                arrival = time.monotonic()
                depth_frame = frames.get_depth_frame()
                try:
                    if not depth_frame:
                        raise DepthFrameError("the frameset holds no depth frame")
                    item = DepthFrame(self.convert(np.asanyarray(depth_frame.get_data())), arrival,
                                      int(depth_frame.get_frame_number()), None)
                except DepthBlindedError as err:
                    item = DepthFault(f"{err} ({self.name})", arrival)
                except DepthFrameError as err:
                    item = DepthFault(f"malformed depth frame: {err}", arrival)
            with self._lock:
                self._mailbox = [item]  # only the newest matters
            try:
                os.write(self._wake_w, b"x")
            except BlockingIOError:
                pass

    def fileno(self) -> int | None:
        return self._wake_r if self._wake_r >= 0 else None

    def poll(self, now_s: float) -> list[DepthFrame | DepthFault]:
        if self._wake_r >= 0:
            try:
                os.read(self._wake_r, 4096)
            except BlockingIOError:
                pass
        with self._lock:
            items, self._mailbox = self._mailbox, []
        return items

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._started:
            self._started = False
            try:
                self.device.stop()
            except RuntimeError:
                pass
        for fd in (self._wake_r, self._wake_w):
            if fd >= 0:
                os.close(fd)
        self._wake_r = self._wake_w = -1


# --------------------------------------------------------------------------- factory

CAMERA_FORMS = "sitl:PORT[:VEHICLE], sitl:HOST:PORT[:VEHICLE], realsense, realsense:WIDTHxHEIGHT@FPS, replay:PATH or replay:PATH,loop"


def parse_camera_spec(text: str) -> tuple[str, dict]:
    """Check a ``--camera`` value and split it into (kind, options); raise ValueError if invalid."""
    kind, _, rest = text.partition(":")
    if kind == "sitl":
        parts = rest.split(":")
        vehicle_text = None
        if len(parts) == 1:
            host, port_text = "127.0.0.1", parts[0]
        elif len(parts) == 2 and parts[0].isdigit():  # PORT:VEHICLE (a host is never a bare number)
            (port_text, vehicle_text), host = parts, "127.0.0.1"
        elif len(parts) == 2:
            host, port_text = parts
        elif len(parts) == 3:
            host, port_text, vehicle_text = parts
        else:
            raise ValueError(f"invalid camera {text!r}: use sitl:PORT, sitl:HOST:PORT, sitl:PORT:VEHICLE "
                             "or sitl:HOST:PORT:VEHICLE")
        if not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
            raise ValueError(f"invalid camera {text!r}: the port must be a number in 1..65535")
        if vehicle_text is not None and not (vehicle_text.isdigit() and int(vehicle_text) <= 65535):
            raise ValueError(f"invalid camera {text!r}: the vehicle index must be a number in 0..65535")
        return "sitl", {"host": host or "127.0.0.1", "port": int(port_text),
                        "vehicle": None if vehicle_text is None else int(vehicle_text)}
    if kind == "realsense":
        if not rest:
            return "realsense", {}
        try:
            size, _, fps = rest.partition("@")
            width, height = (int(v) for v in size.lower().split("x"))
            options = {"width": width, "height": height, "fps": int(fps) if fps else 30}
        except ValueError:
            raise ValueError(f"invalid camera {text!r}: use realsense:WIDTHxHEIGHT@FPS, e.g. realsense:848x480@30") from None
        if min(options.values()) < 1:
            raise ValueError(f"invalid camera {text!r}: width, height and fps must be positive")
        return "realsense", options
    if kind == "replay":
        path, _, flag = rest.partition(",")
        if not path or flag not in ("", "loop"):
            raise ValueError(f"invalid camera {text!r}: use replay:PATH or replay:PATH,loop")
        return "replay", {"path": path, "loop": flag == "loop"}
    raise ValueError(f"invalid camera {text!r}: use one of {CAMERA_FORMS}")


def open_depth_source(text: str, camera: CameraSpec,
                      max_invalid_fraction: float = MAX_INVALID_DEPTH_FRACTION) -> DepthSource:
    """Build (not start) the source named by a ``--camera`` value for a policy's ``camera``.

    ``max_invalid_fraction``: above this fraction of invalid pixels a frame is a blinded sensor.
    """
    kind, options = parse_camera_spec(text)
    if kind == "sitl":
        source = SitlDepthSource(options["host"], options["port"], camera, vehicle=options["vehicle"])
    elif kind == "realsense":
        source = RealSenseDepthSource(camera, **options)
    elif not Path(options["path"]).is_file():
        raise DepthSourceError(f"cannot replay {options['path']}: no such file")
    else:
        source = ReplayDepthSource(options["path"], camera, loop=options["loop"])
    source.converter.max_invalid_fraction = max_invalid_fraction
    return source
