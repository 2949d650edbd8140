"""Onboard depth preprocessing: today's numpy path against an OpenCV path, same output required.

Times what the companion does with every full-resolution RealSense frame before the policy
sees it: a 848x480 z16 frame (depth scale 0.001 m, about 30 % zero holes in clumps, like
stereo shadows) is converted to metres, checked for a blinded sensor, cropped to the policy's
field of view and min-pooled over valid pixels to the policy's 32x32 (holes ignored; a block
with no valid pixel reads ``max_range_m``).

* ``numpy``: :meth:`companion.depth_sources.DepthConverter.convert`'s steps with the numpy
  min-pool (what the base install runs);
* ``opencv``: the same steps with the OpenCV min-pool (what the companion runs when OpenCV is
  installed, ``companion.observation._min_pool_depth_opencv``): one
  ``cv2.erode`` with a rectangle of the smallest block size, anchored at the window's top-left,
  then each output pixel is the min of the eroded image at its block's four corner windows
  (blocks are 1 pixel larger at most, so the four windows cover the block exactly). Bilinear or
  area resizing is not a min; this is.

Both outputs are compared element for element on every frame (the script fails if they
differ). Timings are per frame, single-threaded (the companion pins one torch thread; OpenCV is
set to one thread too so the comparison is fair on a busy flight computer).

The policy camera is 32x32 at 55 deg: a D435/D455 (87 deg, 848x480) cannot feed a square 90 deg
policy (its vertical field of view is 56 deg), see docs/companion.md.

Usage: ``python benchmarks/depth_preprocess.py [--frames 300] [--smoke]``. The last line of
output is one JSON object: medians in ms, ``opencv_speedup`` (numpy median / opencv median) and
``identical``.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from companion.depth_sources import DepthConverter, z16_to_metres  # noqa: E402
from companion.observation import (  # noqa: E402
    _min_pool_depth_numpy,
    _min_pool_depth_opencv,
    check_not_blinded,
    crop_to_hfov,
    validate_depth_frame,
)
from companion.spec import CameraSpec  # noqa: E402

SOURCE_WIDTH_PX, SOURCE_HEIGHT_PX, SOURCE_HFOV_DEG = 848, 480, 87.0
DEPTH_SCALE_M = 0.001
HOLE_FRACTION = 0.30
POLICY_CAMERA = CameraSpec(width=32, height=32, hfov_deg=55.0)


def synthetic_z16(rng: np.random.Generator) -> np.ndarray:
    """A 848x480 z16 frame: a ramp of walls 0.3..25 m, a few near objects, ~30 % holes in clumps."""
    rows = np.linspace(300, 25000, SOURCE_HEIGHT_PX, dtype=np.float32)[:, None]
    frame = np.broadcast_to(rows, (SOURCE_HEIGHT_PX, SOURCE_WIDTH_PX)).copy()
    frame += rng.normal(0.0, 50.0, frame.shape).astype(np.float32)
    for _ in range(20):  # near objects, some a single pixel wide
        y, x = rng.integers(0, SOURCE_HEIGHT_PX), rng.integers(0, SOURCE_WIDTH_PX)
        h, w = rng.integers(1, 40), rng.integers(1, 40)
        frame[y : y + h, x : x + w] = rng.uniform(300, 3000)
    # Holes in 8x8 clumps (stereo shadows and textureless patches), then single dropouts.
    clumps = rng.random((SOURCE_HEIGHT_PX // 8, SOURCE_WIDTH_PX // 8)) < HOLE_FRACTION * 0.8
    holes = np.kron(clumps, np.ones((8, 8), bool)) | (rng.random(frame.shape) < HOLE_FRACTION * 0.25)
    frame[holes] = 0
    return np.clip(frame, 0, 65535).astype(np.uint16)


def convert_with(pool, z16: np.ndarray, camera: CameraSpec) -> np.ndarray:
    """:meth:`DepthConverter.convert` of a z16 frame, step by step, with the given min-pool."""
    metres = z16_to_metres(z16, DEPTH_SCALE_M)
    check_not_blinded(metres)  # on the raw pixels: pooling would hide a covered lens
    cropped = crop_to_hfov(metres, SOURCE_HFOV_DEG, camera)
    pooled = pool(cropped, camera.height, camera.width, camera.max_range_m)
    return validate_depth_frame(pooled, camera)


def _median_ms(fn, frames: list[np.ndarray]) -> tuple[float, list[np.ndarray]]:
    outputs, samples = [], []
    for frame in frames:
        started = time.perf_counter()
        outputs.append(fn(frame))
        samples.append(time.perf_counter() - started)
    return 1e3 * float(np.median(samples)), outputs


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300, help="timed frames per path (default 300)")
    parser.add_argument("--smoke", action="store_true", help="a few frames: checks that both paths agree")
    args = parser.parse_args(argv)
    if args.frames < 1:
        parser.error(f"--frames must be >= 1, got {args.frames}")
    try:
        import cv2
    except ImportError:
        print("error: OpenCV is not installed (pip install 'swarmnav[video]')", file=sys.stderr)
        return 1
    cv2.setNumThreads(1)
    count = 5 if args.smoke else args.frames
    rng = np.random.default_rng(0)
    frames = [synthetic_z16(rng) for _ in range(min(count, 20))]
    frames = (frames * math.ceil(count / len(frames)))[:count]
    numpy_path = functools.partial(convert_with, _min_pool_depth_numpy, camera=POLICY_CAMERA)
    opencv_path = functools.partial(convert_with, functools.partial(_min_pool_depth_opencv, cv2), camera=POLICY_CAMERA)
    # What the companion itself runs (OpenCV when installed) gives the same frame.
    converter = DepthConverter(POLICY_CAMERA)
    identical = np.array_equal(converter.convert(z16_to_metres(frames[0], DEPTH_SCALE_M), SOURCE_HFOV_DEG),
                               numpy_path(frames[0]))
    for fn in (numpy_path, opencv_path):  # warm-up (first-call allocations, OpenCV dispatch)
        fn(frames[0])
    # Interleave the two paths in rounds so that load from other processes hits both alike.
    numpy_ms, opencv_ms = [], []
    for start in range(0, count, 10):
        chunk = frames[start : start + 10]
        t_np, out_np = _median_ms(numpy_path, chunk)
        t_cv, out_cv = _median_ms(opencv_path, chunk)
        numpy_ms.append(t_np)
        opencv_ms.append(t_cv)
        identical &= all(np.array_equal(a, b) for a, b in zip(out_np, out_cv))
    hole_fraction = float(np.mean([np.mean(f == 0) for f in frames[:20]]))
    summary = {
        "frame": f"{SOURCE_WIDTH_PX}x{SOURCE_HEIGHT_PX} z16, {100 * hole_fraction:.0f} % holes",
        "policy": f"{POLICY_CAMERA.width}x{POLICY_CAMERA.height} at {POLICY_CAMERA.hfov_deg:g} deg",
        "frames": count,
        "numpy_ms_median": round(float(np.median(numpy_ms)), 3),
        "opencv_ms_median": round(float(np.median(opencv_ms)), 3),
        "opencv_speedup": round(float(np.median(numpy_ms) / np.median(opencv_ms)), 2),
        "identical": bool(identical),
        "opencv": cv2.__version__,
    }
    print(json.dumps(summary))
    return 0 if identical else 1


if __name__ == "__main__":
    raise SystemExit(main())
