"""A slow, obviously-correct depth renderer that the fast kernel is tested against.

It casts every sub-ray of the high-resolution image against every object with unit
direction vectors and Euclidean hit distances, converts them to planar depth, and
min-pools — sharing no code with :mod:`sitl.sim.camera` except the camera spec.
"""

from __future__ import annotations

import math

import numpy as np

from companion.spec import CameraSpec


def _hit_spheroid(o, d, center, a_h, a_v):
    scale = np.array([1.0, 1.0, a_h / a_v])
    oc = (o - center) * scale
    ds = d * scale
    A, B, C = ds @ ds, 2 * oc @ ds, oc @ oc - a_h * a_h
    if C <= 0:
        return 0.0
    disc = B * B - 4 * A * C
    if disc < 0:
        return math.inf
    t = (-B - math.sqrt(disc)) / (2 * A)
    return t if t > 0 else math.inf


def _hit_box(o, d, box):
    c, h = np.asarray(box[:3]), np.asarray(box[3:])
    lo, hi = c - h, c + h
    if np.all(lo < o) and np.all(o < hi):
        return 0.0
    t_near, t_far = -math.inf, math.inf
    for k in range(3):
        if abs(d[k]) < 1e-12:
            if not lo[k] <= o[k] <= hi[k]:
                return math.inf
            continue
        t1, t2 = sorted(((lo[k] - o[k]) / d[k], (hi[k] - o[k]) / d[k]))
        t_near, t_far = max(t_near, t1), min(t_far, t2)
    return t_near if t_near <= t_far and t_near > 0 else math.inf


def _hit_cylinder(o, d, cyl):
    cn, ce, rad, z_top, z_bot = cyl
    rel = np.array([o[0] - cn, o[1] - ce])
    if rel @ rel < rad * rad and z_top < o[2] < z_bot:
        return 0.0
    best = math.inf
    dxy = d[:2]
    A, B, C = dxy @ dxy, 2 * rel @ dxy, rel @ rel - rad * rad
    if A > 1e-12 and C > 0:
        disc = B * B - 4 * A * C
        if disc >= 0:
            t = (-B - math.sqrt(disc)) / (2 * A)
            if t > 0 and z_top <= o[2] + t * d[2] <= z_bot:
                best = t
    if abs(d[2]) > 1e-12:
        for zc in (z_top, z_bot):
            t = (zc - o[2]) / d[2]
            p = rel + t * dxy
            if 0 < t < best and p @ p <= rad * rad:
                best = t
    return best


def render_reference(spec: CameraSpec, supersample: int, pos_ned, yaw_rad, uavs_per_world, visible,
                     body_radius_m, body_half_height_m, boxes, cylinders, pitch_rad=None,
                     with_objects: bool = False):
    """Render [M, H, W] planar depth by brute force (see module doc).

    ``pitch_rad`` [M]: each camera's optical axis raised by this angle (default the spec's mount
    pitch). With ``with_objects`` also return [M] the nearest non-ground planar depth of any sub-ray.
    """
    pos_ned = np.asarray(pos_ned, dtype=float)
    total = pos_ned.shape[0]
    pitch = np.full(total, math.radians(spec.mount_pitch_deg)) if pitch_rad is None else np.asarray(pitch_rad)
    sub_h, sub_w = spec.height * supersample, spec.width * supersample
    out = np.full((total, spec.height, spec.width), spec.max_range_m)
    objects = np.full(total, spec.max_range_m)
    for m in range(total):
        o = pos_ned[m]
        heading = np.array([math.cos(yaw_rad[m]), math.sin(yaw_rad[m]), 0.0])
        right = np.array([-math.sin(yaw_rad[m]), math.cos(yaw_rad[m]), 0.0])
        # Pitch up by p: forward tilts towards -z (up), the image's down axis towards +heading.
        forward = math.cos(pitch[m]) * heading + math.sin(pitch[m]) * np.array([0.0, 0.0, -1.0])
        down = math.sin(pitch[m]) * heading + math.cos(pitch[m]) * np.array([0.0, 0.0, 1.0])
        world = m // uavs_per_world
        others = [k for k in range(world * uavs_per_world, (world + 1) * uavs_per_world) if k != m and visible[k]]
        for si in range(sub_h):
            v = (2 * (si + 0.5) / sub_h - 1) * spec.tan_half_vfov
            for sj in range(sub_w):
                u = (2 * (sj + 0.5) / sub_w - 1) * spec.tan_half_hfov
                ray = forward + u * right + v * down
                unit = ray / np.linalg.norm(ray)
                ground = []
                if o[2] >= 0:
                    ground.append(0.0)
                elif unit[2] > 0:
                    ground.append(-o[2] / unit[2])
                hits = [_hit_spheroid(o, unit, pos_ned[k], body_radius_m, body_half_height_m) for k in others]
                hits += [_hit_box(o, unit, b) for b in boxes[world] if b[3] > 0]
                hits += [_hit_cylinder(o, unit, c) for c in cylinders[world] if c[2] > 0]
                euclid = min(hits + ground) if hits + ground else math.inf
                planar = euclid * (unit @ forward)  # distance along the optical axis
                i, j = si // supersample, sj // supersample
                out[m, i, j] = min(out[m, i, j], planar, spec.max_range_m)
                if hits:
                    objects[m] = min(objects[m], min(hits) * (unit @ forward))
    return (out, objects) if with_objects else out
