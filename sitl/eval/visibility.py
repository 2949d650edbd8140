"""Who can see whom: the camera frustum as a geometric test on true positions.

Used where an analysis or a reference controller needs to know whether another UAV was in a
UAV's depth image, without rendering one: :mod:`sitl.eval.collision_anatomy` (could the
collider have seen its partner?) and the camera-limited ORCA of :mod:`sitl.eval.orca`.
The test is on the other UAV's centre, in the heading frame with a level camera (the
simulator's evaluation flies the nominal mount, pitch 0).
"""

from __future__ import annotations

import math

import numpy as np

from companion.frames import ned_to_frd
from companion.spec import CameraSpec
from sitl.sim.camera import in_frustum


def camera_fov_rad(camera: CameraSpec) -> tuple[float, float]:
    """The camera's horizontal and vertical field of view (rad): a real sensor's, or square pixels'."""
    return math.radians(camera.hfov_deg), 2.0 * math.atan(camera.tan_half_vfov)


def in_view(pos_ned: np.ndarray, yaw_rad: np.ndarray, other_ned: np.ndarray, hfov_rad: float, vfov_rad: float,
            max_range_m: float) -> np.ndarray:
    """Whether each ``other_ned`` point lies in the level camera frustum of the UAV at ``pos_ned``/``yaw_rad``.

    Shapes broadcast: ``pos_ned``/``other_ned`` [..., 3], ``yaw_rad`` [...].
    """
    d = other_ned - pos_ned
    return (in_frustum(ned_to_frd(d, yaw_rad), math.tan(hfov_rad / 2), math.tan(vfov_rad / 2))
            & (np.linalg.norm(d, axis=-1) <= max_range_m))


def in_view_all_around(pos_ned: np.ndarray, other_ned: np.ndarray, vfov_rad: float, max_range_m: float) -> np.ndarray:
    """Whether each ``other_ned`` point lies in the ring a level camera with this vertical view and range sweeps
    when it turns once around (any bearing, elevation within +-vfov/2). Shapes broadcast as :func:`in_view`."""
    d = other_ned - pos_ned
    horizontal = np.hypot(d[..., 0], d[..., 1])
    return (np.abs(d[..., 2]) <= horizontal * math.tan(vfov_rad / 2)) & (np.linalg.norm(d, axis=-1) <= max_range_m)
