"""A flight recording as a video a person can watch: the depth the policy saw beside its command.

``python -m sitl.eval.flight_video flight.snrec -o flight.mp4`` turns a ``companion --record``
file (:mod:`companion.recording`) into one video frame per control step: on the left the
policy's newest depth frame, colour-mapped (near = bright/red, ``max_range_m`` and holes = dark
blue) and enlarged with square pixels; on the right the step's time, the command sent
``[fwd, down, yaw rate]``, the policy's state input and the hold flag (red ``HOLD`` when the
companion sent a hold instead of the policy's action). The video plays in real time
(``1 / control_period_s`` frames per second) unless ``--fps`` says otherwise.

Needs OpenCV (``pip install 'swarmnav[video]'``). A missing or unreadable file, a file that is
not a recording, or an empty one ends in one ``error:`` line and exit 2.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from companion.recording import RecordingError, read_recording
from companion.spec import DEFAULT_ACTION_SPEC, STATE_NAMES, CameraSpec
from sitl.cli_args import ArgumentParser, existing_file, output_file, positive_float

#: Height of the enlarged depth panel (pixels); the text panel beside it is TEXT_WIDTH_PX wide.
DEPTH_PANEL_PX = 384
TEXT_WIDTH_PX = 448
_WHITE, _GREY, _RED, _GREEN = (255, 255, 255), (170, 170, 170), (60, 60, 255), (90, 220, 90)  # BGR


def depth_panel(depth_m: np.ndarray, max_range_m: float, scale: int) -> np.ndarray:
    """BGR uint8 image of one depth frame [H, W] (metres), ``scale`` video pixels per depth pixel."""
    import cv2

    nearness = 1.0 - np.clip(np.nan_to_num(depth_m, nan=max_range_m), 0.0, max_range_m) / max_range_m
    colour = cv2.applyColorMap((255.0 * nearness).astype(np.uint8), cv2.COLORMAP_JET)
    return cv2.resize(colour, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)


def text_lines(record: np.void, t0_s: float) -> list[tuple[str, tuple[int, int, int]]]:
    """The lines written beside the depth: (text, BGR colour)."""
    action = [float(v) for v in record["action"]]
    lines = [
        (f"t = {float(record['t_mono_s']) - t0_s:7.2f} s   step {int(record['step'])}", _WHITE),
        (f"frame {int(record['frame_seq'])}", _GREY),
        ("HOLD (policy action not sent)" if record["hold"] else "policy flying", _RED if record["hold"] else _GREEN),
        ("", _WHITE),
        ("command sent:", _WHITE),
    ]
    lines += [(f"  {name:<16} {value:+7.2f}", _WHITE) for name, value in zip(DEFAULT_ACTION_SPEC.names, action)]
    lines += [("", _WHITE), ("state (policy input):", _WHITE)]
    lines += [(f"  {name:<16} {float(value):+7.2f}", _GREY) for name, value in zip(STATE_NAMES, record["state"])]
    pos = record["pos_ned_m"]
    lines += [("", _WHITE), (f"pos NED m  {pos[0]:+.1f} {pos[1]:+.1f} {pos[2]:+.1f}", _GREY),
              (f"yaw rad    {float(record['yaw_rad']):+.2f}", _GREY)]
    return lines


def render_frame(record: np.void, camera: CameraSpec, t0_s: float) -> np.ndarray:
    """One video frame (BGR uint8, even width and height) for one control step."""
    import cv2

    scale = max(1, DEPTH_PANEL_PX // camera.height)
    depth = depth_panel(record["depth_m"], camera.max_range_m, scale)
    height = max(depth.shape[0], 24 * 22)
    height += height % 2
    frame = np.zeros((height, depth.shape[1] + TEXT_WIDTH_PX + depth.shape[1] % 2, 3), np.uint8)
    frame[: depth.shape[0], : depth.shape[1]] = depth
    cv2.putText(frame, f"depth 0..{camera.max_range_m:g} m, near = red", (8, min(depth.shape[0] + 22, height - 8)),
                cv2.FONT_HERSHEY_SIMPLEX, 0.5, _GREY, 1, cv2.LINE_AA)
    x = depth.shape[1] + 16
    for row, (text, colour) in enumerate(text_lines(record, t0_s)):
        cv2.putText(frame, text, (x, 28 + 22 * row), cv2.FONT_HERSHEY_SIMPLEX, 0.55, colour, 1, cv2.LINE_AA)
    return frame


def export_video(recording: str | Path, video: str | Path, fps: float | None = None) -> int:
    """Write ``recording`` as a video to ``video`` (.mp4: MPEG-4, .avi: MJPG); return the frame count.

    Raises :class:`RecordingError` for a file that is not a recording or holds no record, and
    :class:`OSError` if the video cannot be written.
    """
    import cv2

    header, records = read_recording(recording)
    if len(records) == 0:
        raise RecordingError(f"{recording}: the recording holds no control step")
    camera = CameraSpec(**header["camera"])
    fps = fps or 1.0 / float(header["control_period_s"])
    t0_s = float(records[0]["t_mono_s"])
    first = render_frame(records[0], camera, t0_s)
    fourcc = cv2.VideoWriter_fourcc(*("MJPG" if str(video).lower().endswith(".avi") else "mp4v"))
    writer = cv2.VideoWriter(str(video), fourcc, fps, (first.shape[1], first.shape[0]))
    if not writer.isOpened():
        raise OSError(f"cannot write a video to {video} (use .mp4 or .avi)")
    try:
        writer.write(first)
        for record in records[1:]:
            writer.write(render_frame(record, camera, t0_s))
    finally:
        writer.release()
    return len(records)


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m sitl.eval.flight_video``."""
    parser = ArgumentParser(prog="python -m sitl.eval.flight_video", description=__doc__.splitlines()[0])
    parser.add_argument("recording", type=existing_file, help="a companion --record file (.snrec)")
    parser.add_argument("-o", "--output", type=output_file, default="flight.mp4",
                        help="video file to write, .mp4 or .avi (default flight.mp4)")
    parser.add_argument("--fps", type=positive_float, default=None,
                        help="frames per second (default: real time, 1 / the recording's control period)")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.output == "-":
        parser.error("--output must be a file, not '-'")
    try:
        import cv2  # noqa: F401
    except ImportError:
        parser.error("OpenCV is not installed (pip install 'swarmnav[video]')")
    try:
        frames = export_video(args.recording, args.output, args.fps)
    except (RecordingError, OSError) as err:
        parser.error(str(err))
    print(f"wrote {args.output}: {frames} frames")
    return 0


if __name__ == "__main__":
    sys.exit(main())
