"""Building the policy's observation (paper III.B.1) — the same code in flight and in SITL.

An observation is ``(depth, state)``:

* ``depth``: float32 [3, H, W] planar depth in metres, the last three frames, oldest first;
* ``state``: float32 [6] laid out as :data:`companion.spec.STATE_NAMES` — the goal in the
  heading FRD frame and the vehicle's own forward speed, down speed and yaw rate.

All functions are vectorized over a leading batch axis so the simulator can build the
observations of thousands of UAVs at once with exactly the code the companion runs for one.
Nothing here depends on the simulator.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from companion.frames import frd_to_ned, ned_to_frd
from companion.spec import (MAX_INVALID_DEPTH_FRACTION, MEMORY_AZIMUTH_SECTORS, MEMORY_ELEVATION_EDGES_DEG, STATE_DIM,
                            CameraSpec, MemorySpec)


class DepthFrameError(ValueError):
    """A depth frame that cannot be turned into a valid observation."""


class DepthBlindedError(DepthFrameError):
    """A well-formed frame from a blinded or dead sensor (too many pixels without data)."""


def check_not_blinded(depth_m: np.ndarray, max_invalid_fraction: float = MAX_INVALID_DEPTH_FRACTION) -> None:
    """Raise :class:`DepthBlindedError` if too many pixels of a raw frame are invalid.

    Invalid means 0 (a stereo camera's "no data"), negative (never a distance) or non-finite.
    Must run on the camera's own pixels *before* any conversion: pooling and validation
    turn invalid pixels into ``max_range_m``, which would make a covered lens read as clear
    sky. See :data:`companion.spec.MAX_INVALID_DEPTH_FRACTION` for the threshold.
    """
    depth_m = np.asarray(depth_m)
    total = depth_m.size
    if total == 0:
        raise DepthBlindedError("depth blinded: the frame has no pixel")
    with np.errstate(invalid="ignore"):
        finite = np.isfinite(depth_m)
        zero = int(np.count_nonzero(depth_m == 0))
        negative = int(np.count_nonzero(depth_m < 0))
    non_finite = total - int(np.count_nonzero(finite))
    invalid = zero + negative + non_finite
    if invalid > max_invalid_fraction * total:
        raise DepthBlindedError(
            f"depth blinded: {100.0 * invalid / total:.0f} % of pixels invalid "
            f"(zero {zero}, negative {negative}, NaN/inf {non_finite} of {total}; "
            f"limit {100.0 * max_invalid_fraction:.0f} %)")


def clean_depth(depth_m: np.ndarray, max_range_m: float) -> np.ndarray:
    """The policy's view of raw depth pixels [...]: THE conversion, in training and in flight.

    Invalid pixels — 0 (:data:`companion.spec.INVALID_DEPTH_M`, the RealSense SDK's "no data":
    no stereo match, beyond range, too near), negative or non-finite — read ``max_range_m``
    ("nothing seen within range"), and valid ones farther than ``max_range_m`` are clipped to
    it. The simulator passes every rendered (and noised) frame through this function; the
    companion every camera frame, after min-pooling to the policy's grid (which ignores invalid
    pixels the same way, :func:`min_pool_depth`).
    """
    depth_m = np.asarray(depth_m, dtype=np.float32)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(depth_m) & (depth_m > 0)
    return np.where(valid, np.minimum(depth_m, np.float32(max_range_m)), np.float32(max_range_m)).astype(np.float32)


def default_max_invalid_fraction(camera: CameraSpec) -> float:
    """The blinded-camera limit the companion uses unless ``--max-invalid-depth`` says otherwise.

    An ideal camera (``min_range_m == 0``: the paper's, rendered by the simulator, where only
    a dead or covered sensor reads 0) keeps :data:`companion.spec.MAX_INVALID_DEPTH_FRACTION`.
    A real stereo sensor (``min_range_m > 0``) reports the sky, the ground beyond its range
    and untextured patches as 0: measured with ``benchmarks/camera_model.py`` (D435 preset,
    noise, straight flights), frames are 70 % invalid on average below 3 m, more than 90 %
    invalid in ~97 % of frames above 6 m, and 100 % invalid in ~40 % of them — exactly what a
    covered lens reads. No fraction separates the two there, so for a real sensor the
    default is 1.0: the check never trips in normal flight. docs/companion.md says when to
    set it (missions that stay within the sensor's range of a surface, e.g. below ~2.5 m).
    """
    return 1.0 if camera.min_range_m > 0 else MAX_INVALID_DEPTH_FRACTION


def build_state(
    pos_ned: np.ndarray,
    yaw_rad: np.ndarray,
    vel_ned: np.ndarray,
    yaw_rate_rad_s: np.ndarray,
    goal_ned: np.ndarray,
) -> np.ndarray:
    """Return the policy's state vector(s), float32 [..., 6].

    Args:
        pos_ned: vehicle position [..., 3] in local NED (m).
        yaw_rad: heading [...] (rad, from north, positive right).
        vel_ned: velocity [..., 3] in local NED (m/s).
        yaw_rate_rad_s: yaw rate [...] (rad/s, positive right).
        goal_ned: goal position [..., 3] in local NED (m).
    """
    goal_frd = ned_to_frd(np.asarray(goal_ned) - np.asarray(pos_ned), yaw_rad)
    vel_frd = ned_to_frd(vel_ned, yaw_rad)
    state = np.empty(goal_frd.shape[:-1] + (STATE_DIM,), dtype=np.float32)
    state[..., 0:3] = goal_frd
    state[..., 3] = vel_frd[..., 0]
    state[..., 4] = vel_frd[..., 2]
    state[..., 5] = yaw_rate_rad_s
    return state


def min_pool_depth(depth_m: np.ndarray, out_height: int, out_width: int, max_range_m: float) -> np.ndarray:
    """Downsample depth [..., H, W] to [..., out_height, out_width] by min-pooling valid pixels.

    Min-pooling keeps the nearest surface in each block, so a thin or distant object that
    covers a single source pixel survives the resize (an average would blur it away).
    Invalid pixels (0, negative or non-finite: a stereo camera's "no data") are ignored;
    a block with no valid pixel reads ``max_range_m``. Values are clipped to ``max_range_m``.
    Source sizes that are not multiples of the output use the nearest block boundaries.

    A single frame [H, W] goes through OpenCV when it is installed (``swarmnav[realsense]``;
    about 2x faster on a 848x480 frame, ``benchmarks/depth_preprocess.py``), with a result
    identical to the numpy path, which the base install uses.
    """
    depth_m = np.asarray(depth_m, dtype=np.float32)
    if depth_m.ndim < 2:
        raise DepthFrameError(f"depth frame must be at least 2-D, got shape {depth_m.shape}")
    height, width = depth_m.shape[-2:]
    if height < out_height or width < out_width:
        raise DepthFrameError(
            f"depth frame {height}x{width} is smaller than the policy's {out_height}x{out_width}"
        )
    cv2 = _opencv()
    if cv2 is not None and depth_m.ndim == 2:
        return _min_pool_depth_opencv(cv2, depth_m, out_height, out_width, max_range_m)
    return _min_pool_depth_numpy(depth_m, out_height, out_width, max_range_m)


_OPENCV_UNSET = object()
_opencv_module: object = _OPENCV_UNSET


def _opencv():
    """The cv2 module, or None when OpenCV is not installed (imported on first use: it is heavy)."""
    global _opencv_module
    if _opencv_module is _OPENCV_UNSET:
        try:
            import cv2  # noqa: PLC0415 - optional fast path, not in the base install
        except ImportError:
            cv2 = None
        _opencv_module = cv2
    return _opencv_module


def _block_edges(size: int, out_size: int) -> np.ndarray:
    """The nearest block boundaries, [out_size + 1] ints from 0 to ``size``."""
    return np.linspace(0, size, out_size + 1).round().astype(int)


def _min_pool_depth_numpy(depth_m: np.ndarray, out_height: int, out_width: int, max_range_m: float) -> np.ndarray:
    """:func:`min_pool_depth` in numpy, for any leading batch axes."""
    height, width = depth_m.shape[-2:]
    cleaned = clean_depth(depth_m, max_range_m)
    if height % out_height == 0 and width % out_width == 0:
        fy, fx = height // out_height, width // out_width
        blocks = cleaned.reshape(cleaned.shape[:-2] + (out_height, fy, out_width, fx))
        return blocks.min(axis=(-3, -1)).astype(np.float32)
    row_edges, col_edges = _block_edges(height, out_height), _block_edges(width, out_width)
    rows = np.minimum.reduceat(cleaned, row_edges[:-1], axis=-2)
    return np.minimum.reduceat(rows, col_edges[:-1], axis=-1).astype(np.float32)


def _min_pool_depth_opencv(cv2, depth_m: np.ndarray, out_height: int, out_width: int, max_range_m: float) -> np.ndarray:
    """:func:`min_pool_depth` of one float32 frame [H, W] with OpenCV, identical to the numpy path.

    Resizing (area, bilinear) averages and would blur a thin obstacle away; a min-pool is an
    erosion sampled per block. The blocks are ``k`` or ``k + 1`` pixels, so one erosion with
    a ``kh x kw`` window anchored at its top-left corner, read at the four windows that start
    at a block's corners, covers each block exactly.
    """
    height, width = depth_m.shape
    cleaned = depth_m.copy()
    cv2.patchNaNs(cleaned, max_range_m)
    cleaned = cv2.min(cleaned, max_range_m)  # +inf and far returns read max_range_m
    _, invalid = cv2.threshold(cleaned, 0.0, max_range_m, cv2.THRESH_BINARY_INV)  # max where <= 0, else 0
    cleaned = cv2.max(cleaned, invalid)  # 0, negative and -inf read max_range_m
    row_edges, col_edges = _block_edges(height, out_height), _block_edges(width, out_width)
    kh, kw = int(np.diff(row_edges).min()), int(np.diff(col_edges).min())
    # eroded[y, x] = min of cleaned[y : y + kh, x : x + kw]; only windows inside the frame are read.
    eroded = cv2.erode(cleaned, np.ones((kh, kw), np.uint8), anchor=(0, 0), borderType=cv2.BORDER_REPLICATE)
    r0, r1 = row_edges[:-1], row_edges[1:] - kh
    c0, c1 = col_edges[:-1], col_edges[1:] - kw
    out = np.minimum(np.minimum(eroded[np.ix_(r0, c0)], eroded[np.ix_(r0, c1)]),
                     np.minimum(eroded[np.ix_(r1, c0)], eroded[np.ix_(r1, c1)]))
    return out.astype(np.float32)


def crop_to_hfov(depth_m: np.ndarray, source_hfov_deg: float, target: CameraSpec,
                 source_vfov_deg: float | None = None) -> np.ndarray:
    """Crop a wider camera's frame [..., H, W] to the policy's field of view in both axes.

    Keeps the centred region that spans ``target.hfov_deg`` horizontally and the target's
    vertical field of view vertically (its pixels are min-pooled to the policy's grid
    afterwards, so the kept region need not have the policy's aspect ratio). The source's
    vertical field of view is ``source_vfov_deg``, or follows from its square pixels. Raises
    :class:`DepthFrameError` (one line) if the source is narrower than the policy in either axis.
    """
    height, width = depth_m.shape[-2:]
    src_tan_h = float(np.tan(np.radians(source_hfov_deg) / 2))
    src_tan_v = (src_tan_h * height / width if source_vfov_deg is None
                 else float(np.tan(np.radians(source_vfov_deg) / 2)))
    src_vfov_deg = float(np.degrees(2 * np.arctan(src_tan_v)))
    tolerance = 1e-6  # relative: the same camera described twice must not be refused for rounding
    if target.tan_half_hfov > src_tan_h * (1 + tolerance):
        raise DepthFrameError(
            f"camera hfov {source_hfov_deg:.1f} deg is narrower than the policy's {target.hfov_deg:.1f} deg"
        )
    if target.tan_half_vfov > src_tan_v * (1 + tolerance):
        raise DepthFrameError(
            f"camera vfov {src_vfov_deg:.1f} deg is narrower than the policy's {target.vertical_fov_deg:.1f} deg"
        )
    keep_w = min(width, max(1, int(round(width * target.tan_half_hfov / src_tan_h))))
    keep_h = min(height, max(1, int(round(height * target.tan_half_vfov / src_tan_v))))
    top, left = (height - keep_h) // 2, (width - keep_w) // 2
    return depth_m[..., top : top + keep_h, left : left + keep_w]


def validate_depth_frame(depth_m: np.ndarray, camera: CameraSpec,
                         max_invalid_fraction: float = MAX_INVALID_DEPTH_FRACTION) -> np.ndarray:
    """Check one frame [H, W] against the camera spec and return it as clean float32.

    Raises :class:`DepthFrameError` with a precise reason for a wrong shape or a wrong
    dtype, and :class:`DepthBlindedError` for a frame whose pixels are mostly invalid (a
    blinded or dead sensor, not an empty sky: :func:`check_not_blinded`). The remaining
    non-finite or non-positive pixels are "no data" and read ``max_range_m``.
    """
    depth_m = np.asarray(depth_m)
    if depth_m.shape != (camera.height, camera.width):
        raise DepthFrameError(f"depth frame has shape {depth_m.shape}, expected ({camera.height}, {camera.width})")
    if not np.issubdtype(depth_m.dtype, np.floating):
        raise DepthFrameError(f"depth frame must be floating-point metres, got dtype {depth_m.dtype}")
    check_not_blinded(depth_m, max_invalid_fraction)
    return clean_depth(depth_m, camera.max_range_m)


class DepthFrameStack:
    """The policy's depth input for ``num_stacks`` cameras: ``frames`` images, oldest first.

    The stack remembers the last ``camera.history_frames`` images and :attr:`frames` picks those
    ``camera.stack_ages`` pushes old (every ``frame_stride``-th, or the listed ``frame_ages``),
    ending with the newest. After a reset the history is filled with copies of the first
    frame, so a freshly started vehicle has a full observation at once.
    """

    def __init__(self, num_stacks: int, camera: CameraSpec) -> None:
        self.camera = camera
        # Which remembered images the policy sees: fixed by the camera, so looked up once, not every step.
        self._columns = list(camera.history_columns)
        self._consecutive = len(self._columns) == camera.history_frames
        self.history = np.full(
            (num_stacks, camera.history_frames, camera.height, camera.width), camera.max_range_m, dtype=np.float32
        )

    @property
    def frames(self) -> np.ndarray:
        """The policy's ``depth`` input [num_stacks, frames, H, W] (oldest first): the history itself
        (a view) for consecutive frames, else a copy of the images at ``camera.history_columns``."""
        if self._consecutive:
            return self.history
        return np.ascontiguousarray(self.history[:, self._columns])

    def reset(self, first_frame: np.ndarray, index: np.ndarray | slice = slice(None)) -> None:
        """Fill the stacks at ``index`` with ``first_frame`` ([k, H, W] or [H, W])."""
        self.history[index] = np.asarray(first_frame, dtype=np.float32)[..., None, :, :]

    def push(self, frame: np.ndarray, index: np.ndarray | slice = slice(None)) -> None:
        """Append the newest frame ([k, H, W] or [H, W]) to the stacks at ``index``."""
        if isinstance(index, slice) and index == slice(None):
            self.history[:, :-1] = self.history[:, 1:]
            self.history[:, -1] = frame
        else:
            rolled = self.history[index]
            rolled[:, :-1] = rolled[:, 1:]
            rolled[:, -1] = frame
            self.history[index] = rolled

    @property
    def latest(self) -> np.ndarray:
        """The newest frame of every stack, [num_stacks, H, W] (a view)."""
        return self.history[:, -1]


class RememberedDepth:
    """The remembered-depth input (:class:`companion.spec.MemorySpec`) of ``num_stacks`` vehicles.

    :meth:`push` takes each clean depth frame (what :class:`DepthFrameStack` takes) with the pose it
    was seen from and keeps its points in local NED; :meth:`sector_ranges` gives, from a pose, the
    range of the nearest remembered point in each direction sector. The camera's pixels are unprojected
    with the spec's mount pitch (the companion knows no other), at the centres of the pooled grid.
    """

    def __init__(self, num_stacks: int, camera: CameraSpec, memory: MemorySpec) -> None:
        self.camera, self.memory = camera, memory
        height, width = max(1, camera.height // memory.pool), max(1, camera.width // memory.pool)
        # The pooled grid spans the camera's field of view (vfov given, so it stays the camera's).
        self._pooled = dataclasses.replace(camera, width=width, height=height, vfov_deg=camera.vertical_fov_deg)
        tan_u, tan_v = self._pooled.pixel_tangents()
        cp, sp = np.cos(camera.mount_pitch_rad), np.sin(camera.mount_pitch_rad)
        self._mount_cos_sin = (cp, sp)
        # A point at planar depth z in pixel p lies z * ray[p] from the camera, in the heading FRD frame
        # (a camera pitched up by p: its ray (1, u, v) is (cp + v sp, u, v cp - sp)).
        u, v = np.meshgrid(tan_u, tan_v)
        self._ray_frd = np.stack([cp + v * sp, u, v * cp - sp], axis=-1).reshape(-1, 3).astype(np.float32)
        self.points_ned = np.full((num_stacks, memory.slots, height * width, 3), np.nan, dtype=np.float32)
        self._head = np.zeros(num_stacks, dtype=np.int64)  # the slot the newest frame is written to
        self._pushes = np.zeros(num_stacks, dtype=np.int64)
        inner = np.asarray(MEMORY_ELEVATION_EDGES_DEG[1:-1])
        self._sin_band_edges = np.sin(np.radians(inner))
        counts = np.asarray(MEMORY_AZIMUTH_SECTORS)
        self._band_count = counts
        self._band_offset = np.concatenate([[0], np.cumsum(counts)[:-1]])

    def reset(self, frame: np.ndarray, pos_ned: np.ndarray, yaw_rad: np.ndarray,
              index: np.ndarray | slice = slice(None)) -> None:
        """Forget everything at ``index`` and remember ``frame`` (a new flight or episode)."""
        self.points_ned[index] = np.nan
        self._head[index] = 0
        self._pushes[index] = 0
        self.push(frame, pos_ned, yaw_rad, index)

    def push(self, frame: np.ndarray, pos_ned: np.ndarray, yaw_rad: np.ndarray,
             index: np.ndarray | slice = slice(None)) -> None:
        """Remember the clean frames [k, H, W] seen from ``pos_ned`` [k, 3] with heading ``yaw_rad`` [k].

        The newest frame always replaces the one in the head slot; the first push after a reset and every
        ``every_steps``-th one after it stay.
        """
        rows = np.arange(len(self._head))[index]
        cam = self.camera
        pooled = min_pool_depth(np.asarray(frame, dtype=np.float32).reshape(len(rows), cam.height, cam.width),
                                self._pooled.height, self._pooled.width, cam.max_range_m)
        z = pooled.reshape(len(rows), -1, 1)
        points = frd_to_ned(z * self._ray_frd, np.asarray(yaw_rad)[:, None]) + np.asarray(pos_ned)[:, None, :]
        points[z[..., 0] >= cam.max_range_m] = np.nan  # max_range_m: no return
        self.points_ned[rows, self._head[rows]] = points
        keep = self._pushes[rows] % self.memory.every_steps == 0  # the first push of a flight stays, then every n-th
        self._pushes[rows] += 1
        self._head[rows] = np.where(keep, (self._head[rows] + 1) % self.memory.slots, self._head[rows])

    def sector_ranges(self, pos_ned: np.ndarray, yaw_rad: np.ndarray,
                      index: np.ndarray | slice = slice(None)) -> np.ndarray:
        """float32 [k, sectors]: the nearest remembered point's range in each sector, from ``pos_ned``
        [k, 3] with heading ``yaw_rad`` [k], clipped to ``range_m``; sectors laid out as
        :meth:`companion.spec.MemorySpec.state_names`."""
        points = self.points_ned[index]
        k = points.shape[0]
        rel = points.reshape(k, -1, 3) - np.asarray(pos_ned, dtype=np.float32)[:, None, :]
        limit = np.float32(self.memory.range_m)
        with np.errstate(invalid="ignore"):
            distance = np.sqrt(np.einsum("kqi,kqi->kq", rel, rel))
            near = distance < limit  # NaN (nothing remembered) is never near
        row, col = np.nonzero(near)
        out = np.full((k, self.memory.num_sectors), limit, dtype=np.float32)
        if len(row) == 0:
            return out
        d_frd, dist = ned_to_frd(rel[row, col], np.asarray(yaw_rad)[row]), distance[row, col]
        if self.memory.outside_view:  # drop what the camera looks at now: the image shows it (or its absence)
            keep = ~self._in_view(d_frd)
            row, d_frd, dist = row[keep], d_frd[keep], dist[keep]
        fwd, right = d_frd[:, 0], d_frd[:, 1]
        sin_up = -d_frd[:, 2] / np.maximum(dist, 1e-6)
        band = np.searchsorted(self._sin_band_edges, sin_up)
        count = self._band_count[band]
        azimuth = np.arctan2(right, fwd)  # rad, positive right
        sector = np.floor(azimuth / (2 * np.pi) * count + 0.5).astype(np.int64) % count
        flat = out.reshape(-1)
        np.minimum.at(flat, row * self.memory.num_sectors + self._band_offset[band] + sector, dist)
        return out

    def _in_view(self, d_frd: np.ndarray) -> np.ndarray:
        """Whether heading-frame offsets [n, 3] lie inside the camera's field of view (its mount pitch included)."""
        cp, sp = self._mount_cos_sin
        along = d_frd[:, 0] * cp - d_frd[:, 2] * sp  # along the optical axis
        below = d_frd[:, 0] * sp + d_frd[:, 2] * cp  # towards the image's bottom
        cam = self.camera
        return ((along > 0) & (np.abs(d_frd[:, 1]) <= along * cam.tan_half_hfov)
                & (np.abs(below) <= along * cam.tan_half_vfov))
