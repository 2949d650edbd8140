"""The companion's OpenCV min-pool (optional fast path) gives the numpy path's frame exactly."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.observation import _min_pool_depth_numpy, _min_pool_depth_opencv, min_pool_depth

REPO = Path(__file__).resolve().parents[1]
cv2 = pytest.importorskip("cv2")


def test_opencv_min_pool_is_identical_to_numpy_on_holes_and_odd_sizes():
    rng = np.random.default_rng(7)
    for _ in range(60):
        height, width = int(rng.integers(32, 200)), int(rng.integers(32, 200))
        depth = rng.uniform(-5.0, 30.0, (height, width)).astype(np.float32)
        kind = rng.random((height, width))
        depth[kind < 0.05] = np.nan
        depth[(kind >= 0.05) & (kind < 0.08)] = np.inf
        depth[(kind >= 0.08) & (kind < 0.10)] = -np.inf
        depth[(kind >= 0.10) & (kind < 0.15)] = 0.0
        max_range_m = float(rng.uniform(1.0, 25.0))
        expected = _min_pool_depth_numpy(depth, 32, 32, max_range_m)
        assert np.array_equal(_min_pool_depth_opencv(cv2, depth, 32, 32, max_range_m), expected)
        assert np.array_equal(min_pool_depth(depth, 32, 32, max_range_m), expected)


def test_opencv_min_pool_keeps_a_single_pixel_object_and_reads_empty_blocks_as_max_range():
    depth = np.zeros((64, 96), np.float32)  # nothing but holes ...
    depth[10:40, :] = 8.0
    depth[33, 50] = 1.5  # ... a wall and a one-pixel object
    pooled = _min_pool_depth_opencv(cv2, depth, 4, 6, 20.0)
    assert pooled[2, 3] == 1.5 and pooled[3, 0] == 20.0 and pooled[1, 0] == 8.0


def test_preprocess_benchmark_smoke():
    out = subprocess.run([sys.executable, "benchmarks/depth_preprocess.py", "--smoke"], cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    assert summary["identical"] is True and summary["numpy_ms_median"] > 0 and summary["opencv_ms_median"] > 0
