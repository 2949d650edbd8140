"""MAVLink OBSTACLE_DISTANCE from the policy's depth frames: the autopilot's own collision prevention.

The companion publishes one OBSTACLE_DISTANCE per depth frame it uses (at the camera rate),
so that PX4's collision prevention (``CP_DIST``) and ArduPilot's proximity avoidance
(``PRX1_TYPE`` = 2, MAVLink) can stop the vehicle independently of the policy. The message
(https://mavlink.io/en/messages/common.html#OBSTACLE_DISTANCE) is filled as follows:

* ``frame`` = ``MAV_FRAME_BODY_FRD``: angles from the vehicle's nose, positive clockwise
  (to the right) seen from above; the camera looks along the nose.
* 72 bins of ``increment_f`` = 5 degrees (the full circle). Bin ``i`` is the direction
  ``angle_offset + i * increment_f`` and covers +-2.5 degrees around it. The first
  ``ceil(hfov / 5)`` bins span the camera's horizontal field of view, centred on the nose
  (``angle_offset`` = -42.5 degrees for the 90-degree policy camera); the others are
  ``UINT16_MAX`` (unknown: no sensor looks there).
* A bin holds the nearest obstacle in cm: the smallest horizontal distance of the depth
  pixels whose column overlaps the bin's directions and whose point lies within
  ``vertical_band_m`` above or below the camera (the ground and what the vehicle passes
  over or under are not obstacles to horizontal flight). Nothing within range reads
  ``max_distance + 1`` (MAVLink: no obstacle); an obstacle nearer than ``min_distance`` reads
  ``min_distance``.
* ``min_distance`` = :data:`MIN_DISTANCE_CM`, ``max_distance`` = the policy camera's
  ``max_range_m`` in cm.

The frame is the policy's own input (:mod:`companion.depth_sources`: cropped to its field of
view, min-pooled, "no data" read as ``max_range_m``): what the autopilot sees is what the
policy sees. Horizontal distance assumes a level camera; the few degrees of pitch a
quadrotor flies with tilt the vertical band accordingly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.mavlink_link import mavlink
from companion.spec import CameraSpec

#: Bins in one message (fixed by MAVLink) and their width (degrees): 72 x 5 = the full circle.
BIN_COUNT = 72
BIN_WIDTH_DEG = 360.0 / BIN_COUNT
#: A bin no sensor covers (MAVLink: "unknown/not used").
UNKNOWN_CM = 65535
#: Nearest distance (cm) the depth cameras we fly measure reliably (a RealSense D4xx: ~0.2-0.3 m);
#: a closer obstacle is reported at this distance.
MIN_DISTANCE_CM = 20
#: Height (m) above and below the camera within which a depth point counts as an obstacle.
VERTICAL_BAND_M = 1.0
#: A RealSense is active-infrared stereo (MAVLink has no "stereo" sensor type).
SENSOR_TYPE = mavlink.MAV_DISTANCE_SENSOR_INFRARED


@dataclass(frozen=True)
class ObstacleDistance:
    """The fields of one OBSTACLE_DISTANCE message (distances in cm, angles in degrees)."""

    distances_cm: np.ndarray  # uint16 [72]
    angle_offset_deg: float
    increment_deg: float
    min_distance_cm: int
    max_distance_cm: int


class ObstacleBins:
    """Turns a policy depth frame [H, W] (planar metres) into OBSTACLE_DISTANCE bins.

    Args:
        camera: the policy's camera (its field of view, resolution and range).
        vertical_band_m: points more than this above or below the camera are ignored.
    """

    def __init__(self, camera: CameraSpec, vertical_band_m: float = VERTICAL_BAND_M) -> None:
        self.camera = camera
        self.vertical_band_m = vertical_band_m
        width = camera.width
        self.tan_u, self.tan_v = camera.pixel_tangents()  # x right = z * tan_u, y down = z * tan_v
        edges_u = (2.0 * np.arange(width + 1) / width - 1.0) * camera.tan_half_hfov  # column edges, for the bins
        self.horizontal_factor = np.sqrt(1.0 + self.tan_u**2)  # planar depth -> horizontal range
        self.fov_bins = math.ceil(camera.hfov_deg / BIN_WIDTH_DEG - 1e-9)
        self.angle_offset_deg = -0.5 * self.fov_bins * BIN_WIDTH_DEG + 0.5 * BIN_WIDTH_DEG
        # Which bins each column's directions overlap (a column on a bin boundary counts in both).
        col_lo, col_hi = np.degrees(np.arctan(edges_u[:-1])), np.degrees(np.arctan(edges_u[1:]))
        bin_lo = self.angle_offset_deg - 0.5 * BIN_WIDTH_DEG + BIN_WIDTH_DEG * np.arange(self.fov_bins)
        bin_hi = bin_lo + BIN_WIDTH_DEG
        self.overlap = (col_lo[:, None] < bin_hi[None, :]) & (col_hi[:, None] > bin_lo[None, :])  # [W, fov_bins]
        self.min_distance_cm = MIN_DISTANCE_CM
        self.max_distance_cm = min(int(round(camera.max_range_m * 100.0)), UNKNOWN_CM - 2)

    def compute(self, depth_m: np.ndarray) -> ObstacleDistance:
        """The message fields for one frame [H, W] in the policy's layout."""
        depth = np.asarray(depth_m, dtype=np.float64)
        cam = self.camera
        in_band = np.abs(depth * self.tan_v[:, None]) <= self.vertical_band_m
        seen = (depth < cam.max_range_m) & (depth > 0) & in_band  # max_range_m: nothing in range, or no data
        horizontal = np.where(seen, depth * self.horizontal_factor[None, :], np.inf)
        nearest_per_column = horizontal.min(axis=0)  # [W]
        nearest = np.where(self.overlap, nearest_per_column[:, None], np.inf).min(axis=0)  # [fov_bins]
        distances = np.full(BIN_COUNT, UNKNOWN_CM, dtype=np.uint16)
        found = np.isfinite(nearest)
        cm = np.clip(np.floor(np.where(found, nearest, 0.0) * 100.0), self.min_distance_cm, self.max_distance_cm)
        distances[: self.fov_bins] = np.where(found, cm, self.max_distance_cm + 1).astype(np.uint16)
        return ObstacleDistance(distances, self.angle_offset_deg, BIN_WIDTH_DEG, self.min_distance_cm,
                                self.max_distance_cm)


class ObstacleDistancePublisher:
    """Sends OBSTACLE_DISTANCE for each depth frame over the companion's autopilot link.

    Args:
        camera: the policy's camera.
        link: the :class:`companion.mavlink_link.AutopilotLink` (its pymavlink connection and clock).
    """

    def __init__(self, camera: CameraSpec, link) -> None:
        self.bins = ObstacleBins(camera)
        self.link = link
        self.sent = 0

    def publish(self, depth_m: np.ndarray) -> ObstacleDistance:
        """Compute the bins of ``depth_m`` and send them; return what was sent."""
        msg = self.bins.compute(depth_m)
        self.link.conn.mav.obstacle_distance_send(
            self.link.time_boot_ms() * 1000, SENSOR_TYPE, msg.distances_cm.tolist(), int(round(msg.increment_deg)),
            msg.min_distance_cm, msg.max_distance_cm, float(msg.increment_deg), float(msg.angle_offset_deg),
            mavlink.MAV_FRAME_BODY_FRD)
        self.sent += 1
        return msg
