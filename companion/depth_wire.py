"""The SITL depth transport: one rendered depth frame per UDP datagram on the loopback.

``python -m sitl.vehicle`` sends vehicle ``i``'s frames to ``127.0.0.1:<depth-port + i>``;
the companion's ``--camera sitl:<port>`` source listens there. The companion owns the
format (the simulator imports it from here), so the reader and the writer cannot drift.

Datagram layout, little-endian, version 1 (a 40-byte header, then the pixels)::

    offset size  field
     0     4     magic          b"SNDP"
     4     1     version        1
     5     1     encoding       1 = float32 metres, 2 = uint16 scaled by depth_scale (like z16)
     6     2     vehicle        index of the sending vehicle (0-based)
     8     4     seq            frame counter (uint32, wraps)
    12     8     stamp_us       capture time, microseconds since the UNIX epoch (sender's clock)
    20     2     height         rows
    22     2     width          columns
    24     4     hfov_deg       horizontal field of view of the rendered image (float32)
    28     4     max_range_m    range of the renderer: pixels without a hit read this (float32)
    32     4     depth_scale    metres per unit for encoding 2, 0 for encoding 1 (float32)
    36     4     reserved       0
    40     ...   pixels         height * width values, row-major, row 0 = top, column 0 = left

Pixels are *planar* depth (distance along the optical axis) of a forward-looking level
camera, exactly what :class:`companion.spec.CameraSpec` describes. 0, negative or
non-finite pixels mean "no data" (a stereo camera's holes), never an obstacle at 0 m.
A datagram is at most 65507 bytes, so a float32 frame holds up to 16 373 pixels
(e.g. 128 x 96); larger renders use encoding 2.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from companion.observation import DepthFrameError

MAGIC = b"SNDP"
VERSION = 1
ENCODING_FLOAT32_M = 1
ENCODING_UINT16_SCALED = 2
HEADER = struct.Struct("<4sBBHIQHHfffI")
HEADER_SIZE = HEADER.size  # 40
MAX_DATAGRAM = 65507
_PIXEL_DTYPES = {ENCODING_FLOAT32_M: np.dtype("<f4"), ENCODING_UINT16_SCALED: np.dtype("<u2")}

assert HEADER_SIZE == 40


@dataclass
class WireFrame:
    """One decoded datagram: the depth image in metres and what the sender said about it."""

    depth_m: np.ndarray  # float32 [height, width], 0 / non-finite = no data
    vehicle: int
    seq: int
    stamp_us: int
    hfov_deg: float
    max_range_m: float


def encode_frame(depth_m: np.ndarray, *, vehicle: int, seq: int, stamp_us: int, hfov_deg: float,
                 max_range_m: float, depth_scale: float | None = None) -> bytes:
    """Pack one planar depth image [H, W] (metres) into a datagram.

    With ``depth_scale`` (metres per unit) the pixels travel as uint16 like a RealSense's
    z16 stream (no data = 0); otherwise as float32 metres.
    """
    depth_m = np.asarray(depth_m)
    if depth_m.ndim != 2:
        raise ValueError(f"depth frame must be 2-D [H, W], got shape {depth_m.shape}")
    height, width = depth_m.shape
    if depth_scale is None:
        encoding, scale = ENCODING_FLOAT32_M, 0.0
        payload = np.ascontiguousarray(depth_m, dtype="<f4").tobytes()
    else:
        if not depth_scale > 0:
            raise ValueError(f"depth_scale must be > 0, got {depth_scale}")
        encoding, scale = ENCODING_UINT16_SCALED, float(depth_scale)
        valid = np.isfinite(depth_m) & (depth_m > 0)
        units = np.where(valid, np.round(np.where(valid, depth_m, 0) / scale), 0)
        payload = np.clip(units, 0, 65535).astype("<u2").tobytes()
    header = HEADER.pack(MAGIC, VERSION, encoding, vehicle & 0xFFFF, seq & 0xFFFFFFFF, int(stamp_us),
                         height, width, float(hfov_deg), float(max_range_m), scale, 0)
    datagram = header + payload
    if len(datagram) > MAX_DATAGRAM:
        raise ValueError(f"a {height}x{width} frame does not fit one UDP datagram ({len(datagram)} bytes); "
                         "use depth_scale (uint16) or a smaller render")
    return datagram


def decode_frame(datagram: bytes) -> WireFrame:
    """Unpack a datagram; raise :class:`DepthFrameError` saying what is wrong with a bad one."""
    if len(datagram) < HEADER_SIZE:
        raise DepthFrameError(f"depth datagram of {len(datagram)} bytes is shorter than the {HEADER_SIZE}-byte header")
    (magic, version, encoding, vehicle, seq, stamp_us, height, width, hfov_deg, max_range_m,
     depth_scale, _reserved) = HEADER.unpack_from(datagram)
    if magic != MAGIC:
        raise DepthFrameError(f"depth datagram has magic {magic!r}, expected {MAGIC!r} (not a swarmnav depth frame)")
    if version != VERSION:
        raise DepthFrameError(f"depth datagram version {version} is not supported (this companion reads {VERSION})")
    dtype = _PIXEL_DTYPES.get(encoding)
    if dtype is None:
        raise DepthFrameError(f"depth datagram has unknown pixel encoding {encoding}")
    if height == 0 or width == 0:
        raise DepthFrameError(f"depth datagram declares an empty {height}x{width} image")
    expected = HEADER_SIZE + height * width * dtype.itemsize
    if len(datagram) != expected:
        raise DepthFrameError(f"depth datagram is {len(datagram)} bytes but a {height}x{width} "
                              f"{dtype.name} frame needs {expected} (truncated or corrupted)")
    if not (np.isfinite(hfov_deg) and 1.0 <= hfov_deg < 179.0):
        raise DepthFrameError(f"depth datagram declares an invalid field of view {hfov_deg} deg")
    if not (np.isfinite(max_range_m) and max_range_m > 0):
        raise DepthFrameError(f"depth datagram declares an invalid range {max_range_m} m")
    pixels = np.frombuffer(datagram, dtype=dtype, offset=HEADER_SIZE).reshape(height, width)
    if encoding == ENCODING_UINT16_SCALED:
        if not (np.isfinite(depth_scale) and depth_scale > 0):
            raise DepthFrameError(f"depth datagram declares an invalid depth scale {depth_scale}")
        depth_m = pixels.astype(np.float32) * np.float32(depth_scale)  # 0 stays 0: no data
    else:
        depth_m = pixels.astype(np.float32)
    return WireFrame(depth_m, int(vehicle), int(seq), int(stamp_us), float(hfov_deg), float(max_range_m))
