"""`python -m sitl.eval.flight_video`: a companion recording becomes a video that plays back."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.recording import FlightRecorder
from companion.spec import DEFAULT_CAMERA_SPEC

REPO = Path(__file__).resolve().parents[1]
cv2 = pytest.importorskip("cv2")


def _record(path: Path, steps: int) -> None:
    camera = DEFAULT_CAMERA_SPEC
    recorder = FlightRecorder(path, camera, control_period_s=0.1, policy_path="models/policy.pt")
    rng = np.random.default_rng(3)
    for step in range(steps):
        depth = rng.uniform(0.5, camera.max_range_m, (camera.height, camera.width)).astype(np.float32)
        recorder.write(t_wall_s=1e9 + 0.1 * step, t_mono_s=50.0 + 0.1 * step, step=step, frame_seq=3 * step,
                       hold=step % 4 == 0, depth_m=depth, state=np.arange(6, dtype=np.float32),
                       action=np.array([1.0, -0.1, 0.05], np.float32), pos_ned_m=np.zeros(3, np.float32),
                       yaw_rad=0.3)
    recorder.close()


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sitl.eval.flight_video", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=120)


def test_recording_exports_to_a_video_with_one_frame_per_step(tmp_path):
    _record(tmp_path / "flight.snrec", steps=12)
    video = tmp_path / "flight.mp4"
    run = _run(str(tmp_path / "flight.snrec"), "-o", str(video))
    assert run.returncode == 0, run.stderr
    assert "12 frames" in run.stdout
    capture = cv2.VideoCapture(str(video))
    try:
        width, height = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
        frames = []
        while True:
            ok, frame = capture.read()
            if not ok:
                break
            frames.append(frame)
    finally:
        capture.release()
    assert len(frames) == 12
    # 32x32 depth enlarged 12x (384 px) beside the 448 px text panel; 19 text lines set the height.
    assert (width, height) == (384 + 448, 528) and frames[0].shape == (528, 832, 3)
    assert frames[0][:384, :384].std() > 10  # the colour-mapped depth is there, not a blank panel
    assert frames[0][:, 400:].max() > 150  # and the text


def test_bad_or_missing_recording_is_a_one_line_error(tmp_path):
    missing = _run(str(tmp_path / "nope.snrec"), "-o", str(tmp_path / "v.mp4"))
    assert missing.returncode == 2 and "no such file" in missing.stderr and len(missing.stderr.strip().splitlines()) == 1
    junk = tmp_path / "junk.snrec"
    junk.write_text("hello\nworld")
    bad = _run(str(junk), "-o", str(tmp_path / "v.mp4"))
    assert bad.returncode == 2 and "not a swarmnav recording" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
    _record(tmp_path / "empty.snrec", steps=0)
    empty = _run(str(tmp_path / "empty.snrec"), "-o", str(tmp_path / "v.mp4"))
    assert empty.returncode == 2 and "no control step" in empty.stderr
