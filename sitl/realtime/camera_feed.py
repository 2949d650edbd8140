"""The depth cameras of the real-time processes: their options, rendering, and sending to companions.

``python -m sitl.vehicle`` and ``python -m sitl.world`` both render a forward depth camera per
vehicle with :class:`sitl.camera.DepthCamera` (the other vehicles as UAV bodies, the ground and
``--box``/``--cylinder`` obstacles) and send each frame to the companion at ``HOST:depth-port + i``
(:mod:`sitl.realtime.depth_transport`). This module is that part, once.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np

from companion.spec import CAMERA_PRESETS, DEFAULT_CAMERA_SPEC, SENSOR_PRESETS, CameraSpec
from sitl.sim.camera import LANDED_CAMERA_HEIGHT_M, DepthCamera
from sitl.cli_args import (
    MAX_CAMERA_HZ,
    MAX_SUPERSAMPLE,
    box,
    camera_preset,
    check_camera,
    cylinder,
    cylinder_rows,
    finite_float,
    float_range,
    image_size,
    int_range,
    positive_float,
)
from sitl.realtime.depth_transport import DepthFrameSender

DEFAULT_CAMERA_HZ = 30.0
#: The sensor a simulated vehicle carries unless ``--camera`` says otherwise: the bundled policy's
#: (models/policy.pt is trained for a RealSense D435; ``--camera paper`` feeds the paper camera's policies).
DEFAULT_SENSOR = "realsense_d435"
DEFAULT_SUPERSAMPLE = 4


@dataclass(frozen=True)
class CameraConfig:
    """What each vehicle's depth camera renders, and how often.

    ``cylinders`` rows are the camera's (north, east, radius, z_top, z_bottom) and ``boxes``
    rows (north, east, down, half north, half east, half down), metres in the world NED frame.
    """

    spec: CameraSpec = DEFAULT_CAMERA_SPEC
    hz: float = DEFAULT_CAMERA_HZ
    supersample: int = DEFAULT_SUPERSAMPLE
    cylinders: tuple[tuple[float, ...], ...] = ()
    boxes: tuple[tuple[float, ...], ...] = ()

    def describe(self) -> dict:
        """The camera as the ``ready`` event reports it."""
        return {"size": [self.spec.width, self.spec.height], "hfov_deg": self.spec.hfov_deg, "hz": self.hz}


def describe_sensor_presets() -> str:
    """``--camera``'s choices for people, from :data:`SENSOR_PRESETS` and the policy cameras they carry."""
    parts = []
    for name, sensor in SENSOR_PRESETS.items():
        policy = CAMERA_PRESETS[name]
        text = (f"{name} ({sensor.width}x{sensor.height} at {sensor.hfov_deg:g} x {sensor.vertical_fov_deg:.1f} deg, "
                f"{sensor.min_range_m:g}-{sensor.max_range_m:g} m")
        if policy != sensor:
            text += f", cropped to the policy's {policy.hfov_deg:g} x {policy.vertical_fov_deg:.0f} deg"
        parts.append(text + ")")
    return ", ".join(parts)


def add_camera_arguments(parser: argparse.ArgumentParser, frame: str = "") -> None:
    """``--camera-hz``, ``--camera-size``, ``--hfov``, ``--max-range``, ``--supersample``, ``--cylinder``, ``--box``.

    ``frame`` names the obstacles' frame in the help (``"world"`` for the depth bridge).
    """
    spec = SENSOR_PRESETS[DEFAULT_SENSOR]
    parser.add_argument("--camera", type=camera_preset, default=DEFAULT_SENSOR,
                        help=f"the depth sensor each vehicle carries: {describe_sensor_presets()}; --camera-size, "
                             f"--hfov and --max-range override its values (default {DEFAULT_SENSOR})")
    parser.add_argument("--camera-hz", type=float_range(0.0, MAX_CAMERA_HZ, low_open=True), default=DEFAULT_CAMERA_HZ,
                        help=f"depth frame rate, up to {MAX_CAMERA_HZ:g} (default {DEFAULT_CAMERA_HZ:g}; use a multiple "
                             "of the policy's control rate)")
    parser.add_argument("--camera-size", type=image_size, default=None, metavar="WxH",
                        help=f"rendered resolution (default the --camera's, {spec.width}x{spec.height} for {DEFAULT_SENSOR})")
    parser.add_argument("--hfov", type=finite_float, default=None,
                        help=f"horizontal field of view in degrees (default the --camera's, {spec.hfov_deg:g} for "
                             f"{DEFAULT_SENSOR})")
    parser.add_argument("--max-range", type=positive_float, default=None,
                        help=f"camera range in metres (default the --camera's, {spec.max_range_m:g} for {DEFAULT_SENSOR})")
    parser.add_argument("--supersample", type=int_range(1, MAX_SUPERSAMPLE), default=DEFAULT_SUPERSAMPLE,
                        help=f"sub-rays per pixel side, 1..{MAX_SUPERSAMPLE} (default {DEFAULT_SUPERSAMPLE})")
    where = f" ({frame} frame)" if frame else ""
    parser.add_argument("--cylinder", type=cylinder, action="append", metavar="N,E,R[,H]",
                        help=f"a vertical pole at N,E{where} of radius R (and height H, default 30 m); repeatable")
    parser.add_argument("--box", type=box, action="append", metavar="N,E,D,HN,HE,HD",
                        help=f"an axis-aligned box: centre and half sizes in {frame + ' ' if frame else ''}NED metres; "
                             "repeatable")


def check_camera_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Exit 2 unless the camera options make a valid camera; ``args.cylinder`` becomes camera rows."""
    args.cylinder = cylinder_rows(args.cylinder)
    sensor = SENSOR_PRESETS[args.camera]
    if args.camera_size is None:
        args.camera_size = (sensor.width, sensor.height)
    if args.hfov is None:
        args.hfov = sensor.hfov_deg
    if args.max_range is None:
        args.max_range = sensor.max_range_m
    check_camera(parser, args)


def camera_config(args: argparse.Namespace) -> CameraConfig:
    """The :class:`CameraConfig` of parsed (and checked) camera options."""
    return CameraConfig(
        spec=CameraSpec(width=args.camera_size[0], height=args.camera_size[1], hfov_deg=args.hfov,
                        max_range_m=args.max_range,
                        min_range_m=min(SENSOR_PRESETS[args.camera].min_range_m, args.max_range / 2)),
        hz=args.camera_hz, supersample=args.supersample,
        cylinders=tuple(tuple(row) for row in args.cylinder or ()), boxes=tuple(tuple(row) for row in args.box or ()))


class CameraFeed:
    """Every vehicle's depth camera and the sender of its frames to ``host:base_port + i``."""

    def __init__(self, config: CameraConfig, host: str, base_port: int, num_vehicles: int) -> None:
        self.config = config
        self.camera = DepthCamera(config.spec, supersample=config.supersample)
        self.cylinders = np.asarray(config.cylinders, dtype=np.float64).reshape(1, -1, 5) if config.cylinders else None
        self.boxes = np.asarray(config.boxes, dtype=np.float64).reshape(1, -1, 6) if config.boxes else None
        self.sender = DepthFrameSender(host, base_port, num_vehicles, config.spec.hfov_deg, config.spec.max_range_m)

    def render(self, camera_ned: np.ndarray, yaw_rad: np.ndarray) -> np.ndarray:
        """Depth images [k, H, W] of cameras at ``camera_ned`` [k, 3], each seeing the others as UAVs.

        A camera on the ground is raised to the landing gear's height (it sees over the grass).
        """
        camera_ned = np.array(camera_ned, dtype=np.float64)
        camera_ned[:, 2] = np.minimum(camera_ned[:, 2], -LANDED_CAMERA_HEIGHT_M)
        return self.camera.render(camera_ned, np.asarray(yaw_rad, dtype=np.float64), len(camera_ned),
                                  boxes=self.boxes, cylinders=self.cylinders)

    def render_and_send(self, vehicles: list[int], camera_ned: np.ndarray, yaw_rad: np.ndarray) -> None:
        """Render the cameras of ``vehicles`` (indices, at ``camera_ned``/``yaw_rad``) and send each frame."""
        depth = self.render(camera_ned, yaw_rad)
        for k, vehicle in enumerate(vehicles):
            self.sender.send(vehicle, depth[k])

    def frames_sent(self, vehicle: int) -> int:
        return int(self.sender.sent[vehicle])

    def close(self) -> None:
        self.sender.close()
