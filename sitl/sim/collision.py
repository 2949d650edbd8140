"""Collision detection between UAVs (spheres of radius R), with the ground and with static obstacles.

Obstacles use :mod:`sitl.sim.camera`'s layout, per world: boxes ``[B, K, 6]`` (north, east,
down centre, half-north, half-east, half-down) and vertical cylinders ``[B, K, 5]`` (north,
east, radius, z_top, z_bottom with z_top < z_bottom). A row of :data:`DISABLED_BOX` /
:data:`DISABLED_CYLINDER` is padding: far beyond any camera range and never touched.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def _uav_collisions(prev_pos, pos, present, n_per_world, min_dist, out):
    # Continuous check: two UAVs collide if their centres come within 2R at any moment of
    # the control period, assuming straight-line motion over it. A discrete check at 10 Hz
    # would miss two UAVs crossing at 4 m/s closing speed with a small offset.
    total = pos.shape[0]
    min_sq = min_dist * min_dist
    for w0 in range(0, total, n_per_world):
        for i in range(w0, w0 + n_per_world):
            if not present[i]:
                continue
            for j in range(i + 1, w0 + n_per_world):
                if not present[j]:
                    continue
                # relative position r(t) = r0 + t * dr, t in [0, 1]
                r0x = prev_pos[i, 0] - prev_pos[j, 0]
                r0y = prev_pos[i, 1] - prev_pos[j, 1]
                r0z = prev_pos[i, 2] - prev_pos[j, 2]
                drx = (pos[i, 0] - pos[j, 0]) - r0x
                dry = (pos[i, 1] - pos[j, 1]) - r0y
                drz = (pos[i, 2] - pos[j, 2]) - r0z
                dd = drx * drx + dry * dry + drz * drz
                t = 0.0
                if dd > 1e-12:
                    t = -(r0x * drx + r0y * dry + r0z * drz) / dd
                    t = min(max(t, 0.0), 1.0)
                cx = r0x + t * drx
                cy = r0y + t * dry
                cz = r0z + t * drz
                if cx * cx + cy * cy + cz * cz < min_sq:
                    out[i] = True
                    out[j] = True


def uav_uav_collisions(prev_pos_ned: np.ndarray, pos_ned: np.ndarray, present: np.ndarray,
                       uavs_per_world: int, collision_radius_m: float) -> np.ndarray:
    """[M] bool: UAVs whose centre came within 2R of another present UAV of its world this step."""
    out = np.zeros(pos_ned.shape[0], dtype=np.bool_)
    _uav_collisions(np.ascontiguousarray(prev_pos_ned), np.ascontiguousarray(pos_ned),
                    np.ascontiguousarray(present, dtype=np.bool_), uavs_per_world, 2.0 * collision_radius_m, out)
    return out


def ground_collisions(pos_ned: np.ndarray, collision_radius_m: float) -> np.ndarray:
    """[M] bool: UAVs lower than R above the ground (z = 0, NED z down)."""
    return pos_ned[:, 2] > -collision_radius_m


#: Padding rows of the per-world obstacle arrays: a point-sized shape 1000 km north (beyond every
#: camera's range, so the camera culls it; never within R of a UAV).
DISABLED_BOX = np.array([1e6, 1e6, -1.0, 0.0, 0.0, 0.0])
DISABLED_CYLINDER = np.array([1e6, 1e6, 0.0, -1.0, 0.0])


def distance_to_obstacles_m(points_ned: np.ndarray, boxes: np.ndarray, cylinders: np.ndarray) -> np.ndarray:
    """Euclidean distance (m) from each point to the nearest obstacle surface (0 inside one).

    Args:
        points_ned: [..., P, 3] points.
        boxes: [..., Kb, 6] axis-aligned boxes; cylinders: [..., Kc, 5] vertical cylinders (leading
            dimensions broadcast with the points', e.g. one world each).

    Returns:
        [..., P] distances; ``inf`` where there are no obstacles.
    """
    p = np.asarray(points_ned, dtype=np.float64)[..., :, None, :]  # [..., P, 1, 3]
    best = np.full(p.shape[:-2], np.inf)
    if boxes.shape[-2]:
        b = np.asarray(boxes, dtype=np.float64)[..., None, :, :]  # [..., 1, Kb, 6]
        outside = np.maximum(np.abs(p - b[..., 0:3]) - b[..., 3:6], 0.0)
        best = np.minimum(best, np.linalg.norm(outside, axis=-1).min(axis=-1))
    if cylinders.shape[-2]:
        c = np.asarray(cylinders, dtype=np.float64)[..., None, :, :]  # [..., 1, Kc, 5]
        radial = np.maximum(np.hypot(p[..., 0] - c[..., 0], p[..., 1] - c[..., 1]) - c[..., 2], 0.0)
        vertical = np.maximum(np.maximum(c[..., 3] - p[..., 2], p[..., 2] - c[..., 4]), 0.0)
        best = np.minimum(best, np.hypot(radial, vertical).min(axis=-1))
    return best


def nearest_obstacle_points(points_ned: np.ndarray, boxes: np.ndarray, cylinders: np.ndarray) -> np.ndarray:
    """[B, P, 3]: the nearest point on any box or vertical cylinder of each world to each of its points.

    ``points_ned`` [B, P, 3]; boxes [B, Kb, 6] and cylinders [B, Kc, 5] in the layout of
    :mod:`sitl.sim.collision` (padding rows lie 1,000 km away and never win). ``inf`` where a
    world has no obstacle rows at all.
    """
    p = points_ned[:, :, None, :]  # [B, P, 1, 3]
    candidates, distances = [], []
    if boxes.shape[1]:
        b = boxes[:, None, :, :]  # [B, 1, Kb, 6]
        closest = np.clip(p, b[..., 0:3] - b[..., 3:6], b[..., 0:3] + b[..., 3:6])
        candidates.append(closest)
    if cylinders.shape[1]:
        c = cylinders[:, None, :, :]  # [B, 1, Kc, 5]
        offset = p[..., 0:2] - c[..., 0:2]
        radial = np.linalg.norm(offset, axis=-1, keepdims=True)
        scale = np.minimum(1.0, c[..., 2:3] / np.maximum(radial, 1e-9))  # onto the surface when outside
        horizontal = c[..., 0:2] + offset * scale
        vertical = np.clip(p[..., 2:3], c[..., 3:4], c[..., 4:5])
        candidates.append(np.concatenate([horizontal, vertical], axis=-1))
    if not candidates:
        return np.full(points_ned.shape, np.inf)
    for closest in candidates:
        distances.append(np.linalg.norm(closest - p, axis=-1))
    closest = np.concatenate(candidates, axis=2)  # [B, P, K, 3]
    best = np.argmin(np.concatenate(distances, axis=2), axis=2)  # [B, P]
    return np.take_along_axis(closest, best[..., None, None], axis=2)[:, :, 0, :]


def obstacle_collisions(prev_pos_ned: np.ndarray, pos_ned: np.ndarray, boxes: np.ndarray | None,
                        cylinders: np.ndarray | None, uavs_per_world: int, collision_radius_m: float) -> np.ndarray:
    """[M] bool: UAVs whose sphere of radius R touched a static obstacle of its world this step.

    Checked at the step's end and its midpoint: a UAV moves at most ~0.2 m per 0.1 s control
    period (2 m/s), while the thinnest obstacle a centre can cross is a 0.2 m pole widened by R
    on both sides (0.8 m), so the sphere cannot pass through one between two checks.
    """
    m = pos_ned.shape[0]
    if (boxes is None or not boxes.shape[1]) and (cylinders is None or not cylinders.shape[1]):
        return np.zeros(m, dtype=bool)
    worlds = m // uavs_per_world
    boxes = np.zeros((worlds, 0, 6)) if boxes is None else boxes
    cylinders = np.zeros((worlds, 0, 5)) if cylinders is None else cylinders
    hit = np.zeros(m, dtype=bool)
    for points in (pos_ned, 0.5 * (prev_pos_ned + pos_ned)):
        d = distance_to_obstacles_m(points.reshape(worlds, uavs_per_world, 3), boxes, cylinders)
        hit |= d.reshape(m) < collision_radius_m
    return hit
