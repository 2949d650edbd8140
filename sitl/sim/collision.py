"""Collision detection between UAVs (spheres of radius R) and with the ground."""

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
