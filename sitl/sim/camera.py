"""Raycast depth camera: planar depth of other UAVs, the ground and static obstacles.

Every UAV carries a forward-looking pinhole camera at its centre, level or pitched by its
mount (``CameraSpec.mount_pitch_deg``, or per camera; see
:mod:`companion.frames` for the frames and :class:`companion.spec.CameraSpec` for the
image layout). One call renders the cameras of all UAVs of all worlds.

Rendering is "render high, min-pool down": each output pixel is the minimum planar depth
over ``supersample x supersample`` rays spread evenly over its footprint. A UAV smaller
than a pixel therefore still shows up with its true depth instead of vanishing between
pixel centres — what a stereo camera's min-pooled downsampling gives the companion too.
The kernel does this at the cost of the *output* resolution: the ground is a plane, whose
nearest sub-ray in a pixel row is known analytically, and the few pixels an object can
cover are found from its projected bounding box, where only those sub-rays are cast.

Scene geometry (all in local NED, metres):

* UAVs: oblate spheroids with horizontal semi-axis ``body_radius_m`` and vertical
  semi-axis ``body_half_height_m`` (default 0.3 m x 0.12 m: a 0.6 m prop-tip span, ~0.25 m
  tall — an F450-class quadrotor), centred on the UAV position. Invisible UAVs (crashed and
  removed) are skipped. A camera never sees its own UAV.
* Ground: the plane z = 0.
* Boxes: axis-aligned, rows of (north, east, down centre, half-north, half-east, half-down).
* Cylinders: vertical, rows of (north, east centre, radius, z_top, z_bottom) with
  z_top < z_bottom (NED: the top is higher, so more negative).

A camera inside a shape reads 0 m in the pixels that see it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from companion.frames import ned_to_frd
from companion.spec import DEFAULT_TASK_SPEC, CameraSpec

_EPS_FWD = 1e-3  # an object reaching closer than this to the image plane is not culled
LANDED_CAMERA_HEIGHT_M = 0.15  # a landed quadrotor's camera is above its landing gear, not at z = 0


@dataclass(frozen=True)
class SceneGeometry:
    """Shape of the UAV bodies as the camera sees them."""

    body_radius_m: float = DEFAULT_TASK_SPEC.collision_radius_m  # the UAVs' collision radius R
    body_half_height_m: float = 0.12


def empty_boxes(num_worlds: int) -> np.ndarray:
    """A padded obstacle array for worlds without boxes, float64 [num_worlds, 0, 6]."""
    return np.zeros((num_worlds, 0, 6))


def empty_cylinders(num_worlds: int) -> np.ndarray:
    """A padded obstacle array for worlds without cylinders, float64 [num_worlds, 0, 5]."""
    return np.zeros((num_worlds, 0, 5))


class DepthCamera:
    """Renders planar depth for every UAV of every world in one call.

    Args:
        spec: output image layout, field of view and range.
        supersample: sub-rays per pixel side (min-pooled). 1 casts one ray per pixel centre.
        geometry: the UAV body shape.
        parallel: render cameras on all cores (numba threads).
    """

    def __init__(
        self,
        spec: CameraSpec,
        supersample: int = 4,
        geometry: SceneGeometry = SceneGeometry(),
        parallel: bool = False,
    ) -> None:
        if supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {supersample}")
        self.spec = spec
        self.supersample = supersample
        self.geometry = geometry
        self._kernel = _render_all_parallel if parallel else _render_all
        # Sub-ray coordinates on the image plane at unit forward distance (tangents):
        # u to the right, v downwards, at the centres of a (s*H) x (s*W) grid.
        sub_w, sub_h = spec.width * supersample, spec.height * supersample
        self.u_sub = (-spec.tan_half_hfov + (np.arange(sub_w) + 0.5) * (2 * spec.tan_half_hfov / sub_w))
        self.v_sub = (-spec.tan_half_vfov + (np.arange(sub_h) + 0.5) * (2 * spec.tan_half_vfov / sub_h))

    def render(
        self,
        pos_ned: np.ndarray,
        yaw_rad: np.ndarray,
        uavs_per_world: int,
        visible: np.ndarray | None = None,
        boxes: np.ndarray | None = None,
        cylinders: np.ndarray | None = None,
        out: np.ndarray | None = None,
        pitch_rad: np.ndarray | None = None,
    ) -> np.ndarray:
        """Render all cameras: planar depth, float32 [B*N, H, W] (see :meth:`render_with_objects`)."""
        return self.render_with_objects(pos_ned, yaw_rad, uavs_per_world, visible, boxes, cylinders, out,
                                        pitch_rad)[0]

    def render_with_objects(
        self,
        pos_ned: np.ndarray,
        yaw_rad: np.ndarray,
        uavs_per_world: int,
        visible: np.ndarray | None = None,
        boxes: np.ndarray | None = None,
        cylinders: np.ndarray | None = None,
        out: np.ndarray | None = None,
        pitch_rad: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Render all cameras, and the nearest non-ground surface each one sees.

        Args:
            pos_ned: [B*N, 3] UAV (and camera) positions, world-major (world b holds
                UAVs b*N .. b*N+N-1).
            yaw_rad: [B*N] headings.
            uavs_per_world: N.
            visible: [B*N] bool, which UAVs are drawn (default all).
            boxes: [B, K, 6] static boxes per world (see module doc), or None.
            cylinders: [B, K, 5] static cylinders per world, or None.
            out: optional float32 [B*N, H, W] to write into.
            pitch_rad: [B*N] camera mount pitch (rad, positive up), default the spec's
                ``mount_pitch_deg`` for every camera.

        Returns:
            ``(depth, nearest_object_m)``: float32 [B*N, H, W] planar depth in metres, pixels
            with nothing within ``max_range_m`` reading ``max_range_m`` (a perfect camera); and
            float64 [B*N] the smallest planar depth of any other UAV, box or cylinder inside
            the field of view (over every sub-ray, so a UAV smaller than a pixel counts),
            ``max_range_m`` when none is — eq. 4's d_min without the ground.
        """
        pos_ned = np.ascontiguousarray(pos_ned, dtype=np.float64)
        yaw_rad = np.ascontiguousarray(yaw_rad, dtype=np.float64)
        total = pos_ned.shape[0]
        if total % uavs_per_world:
            raise ValueError(f"{total} UAVs do not split into worlds of {uavs_per_world}")
        num_worlds = total // uavs_per_world
        visible = np.ones(total, dtype=np.bool_) if visible is None else np.ascontiguousarray(visible, dtype=np.bool_)
        boxes = empty_boxes(num_worlds) if boxes is None else np.ascontiguousarray(boxes, dtype=np.float64)
        cylinders = empty_cylinders(num_worlds) if cylinders is None else np.ascontiguousarray(cylinders, dtype=np.float64)
        if boxes.shape[0] != num_worlds or cylinders.shape[0] != num_worlds:
            raise ValueError("boxes and cylinders need one (possibly empty) row per world")
        if pitch_rad is None:
            pitch_rad = np.full(total, self.spec.mount_pitch_rad)
        else:
            pitch_rad = np.ascontiguousarray(np.broadcast_to(np.asarray(pitch_rad, dtype=np.float64), (total,)))
        if out is None:
            out = np.empty((total, self.spec.height, self.spec.width), dtype=np.float32)
        nearest_object_m = np.empty(total, dtype=np.float64)
        self._kernel(
            pos_ned, yaw_rad, pitch_rad, visible, uavs_per_world,
            self.geometry.body_radius_m, self.geometry.body_half_height_m,
            boxes, cylinders, self.u_sub, self.v_sub,
            self.spec.tan_half_hfov, self.spec.tan_half_vfov, self.supersample,
            self.spec.max_range_m, out, nearest_object_m,
        )
        return out, nearest_object_m


def in_frustum(d_frd: np.ndarray, tan_half_hfov: float, tan_half_vfov: float,
               pitch_rad: np.ndarray | float = 0.0) -> np.ndarray:
    """Whether directions ``d_frd`` [..., 3] (heading frame, FRD) point into a camera's field of view.

    The camera is pitched up by ``pitch_rad`` (broadcasts against ``d_frd[..., 0]``), as the
    renderer mounts it; range is not checked. A zero vector is outside.
    """
    d_frd = np.asarray(d_frd, dtype=np.float64)
    cos_p, sin_p = np.cos(pitch_rad), np.sin(pitch_rad)
    fwd, right, down = d_frd[..., 0], d_frd[..., 1], d_frd[..., 2]
    ahead = fwd * cos_p - down * sin_p  # along the optical axis (the renderer's ray (1, u, v) inverted)
    below = fwd * sin_p + down * cos_p  # along the image's down axis
    return (ahead > 0) & (np.abs(right) <= tan_half_hfov * ahead) & (np.abs(below) <= tan_half_vfov * ahead)


def blind_speed_m_s(vel_ned: np.ndarray, yaw_rad: np.ndarray, pitch_rad: np.ndarray | float,
                    camera: CameraSpec) -> np.ndarray:
    """Each UAV's speed (m/s) where its velocity points outside its camera's frustum, else 0 [M].

    On a forward camera this is mostly vertical: a D435 covers +-29 deg, so a climb at 0.5 m/s is
    blind below ~0.9 m/s of forward speed.
    """
    seen = in_frustum(ned_to_frd(vel_ned, yaw_rad), camera.tan_half_hfov, camera.tan_half_vfov, pitch_rad)
    return np.where(seen, 0.0, np.linalg.norm(vel_ned, axis=-1))


# --------------------------------------------------------------------------- kernel

@numba.njit(cache=True, inline="always")
def _sub_range(lo: float, hi: float, first: float, step: float, count: int) -> tuple[int, int]:
    """Indices [i0, i1] of grid points first + i*step that fall inside [lo, hi]."""
    i0 = int(math.ceil((lo - first) / step))
    i1 = int(math.floor((hi - first) / step))
    if i0 < 0:
        i0 = 0
    if i1 > count - 1:
        i1 = count - 1
    return i0, i1


@numba.njit(cache=True)
def _project_box_bounds(cn, ce, cd, hn, he, hd, px, py, pz, cos_y, sin_y, cp, sp, tu, tv, max_range):
    """Image-plane bounds (umin, umax, vmin, vmax) of an AABB seen by a camera pitched (cp, sp), or cull/full flags.

    Returns (status, umin, umax, vmin, vmax) with status 0 = culled, 1 = bounded, 2 = full.
    """
    fmin = 1e30
    fmax = -1e30
    umin = 1e30
    umax = -1e30
    vmin = 1e30
    vmax = -1e30
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            for sz in (-1.0, 1.0):
                dn = cn + sx * hn - px
                de = ce + sy * he - py
                dd = cd + sz * hd - pz
                fh = cos_y * dn + sin_y * de
                r = -sin_y * dn + cos_y * de
                f = cp * fh - sp * dd  # camera axes
                dd = sp * fh + cp * dd
                fmin = min(fmin, f)
                fmax = max(fmax, f)
                if f > _EPS_FWD:
                    umin = min(umin, r / f)
                    umax = max(umax, r / f)
                    vmin = min(vmin, dd / f)
                    vmax = max(vmax, dd / f)
    if fmax <= 0.0 or fmin > max_range:
        return 0, 0.0, 0.0, 0.0, 0.0
    if fmin <= _EPS_FWD:
        return 2, -tu, tu, -tv, tv
    return 1, umin, umax, vmin, vmax


@numba.njit(cache=True)
def _render_one(m, pos, yaw, pitch, visible, n_per_world, a_h, a_v, boxes, cyls, u_sub, v_sub, tu, tv, s, max_range,
                out, nearest_obj):
    H = out.shape[1]
    W = out.shape[2]
    px, py, pz = pos[m, 0], pos[m, 1], pos[m, 2]
    cos_y = math.cos(yaw[m])
    sin_y = math.sin(yaw[m])
    # Camera pitched up by p: a ray (1, u, v) in camera axes is (cp + v sp, u, v cp - sp) in the
    # heading frame (forward, right, down). Its parameter t stays the planar depth.
    cp = math.cos(pitch[m])
    sp = math.sin(pitch[m])
    obj_min = max_range  # nearest non-ground surface hit by any sub-ray (the reward's d_min)
    n_sub_u = u_sub.shape[0]
    n_sub_v = v_sub.shape[0]
    du = 2.0 * tu / n_sub_u  # sub-ray spacing on the image plane
    dv = 2.0 * tv / n_sub_v

    # Ground: planar depth along a ray (1, u, v) is -pz / v, independent of u, and smallest
    # for the lowest sub-ray of a pixel row — so the min-pooled value is exact per row.
    # With pitch the ray's down component v cp - sp still grows with v only, so the same holds.
    for i in range(H):
        v_low = v_sub[i * s + s - 1] * cp - sp
        if pz >= 0.0:
            g = 0.0
        elif v_low > 0.0:
            g = min(-pz / v_low, max_range)
        else:
            g = max_range
        for j in range(W):
            out[m, i, j] = g

    # Other UAVs of this world: spheroids, scaled to spheres of radius a_h.
    k_scale = a_h / a_v
    world_start = (m // n_per_world) * n_per_world
    for k in range(world_start, world_start + n_per_world):
        if k == m or not visible[k]:
            continue
        dn = pos[k, 0] - px
        de = pos[k, 1] - py
        dd = pos[k, 2] - pz
        f = cos_y * dn + sin_y * de
        r = -sin_y * dn + cos_y * de
        fc = cp * f - sp * dd  # the bounding sphere's centre in camera axes
        dc = sp * f + cp * dd
        a = a_h  # bounding-sphere radius (a_h >= a_v for an oblate body)
        if fc + a <= 0.0 or fc - a > max_range:
            continue
        if fc - a <= _EPS_FWD:
            umin, umax, vmin, vmax = -tu, tu, -tv, tv
        else:
            umin = min((r - a) / (fc - a), (r - a) / (fc + a))
            umax = max((r + a) / (fc - a), (r + a) / (fc + a))
            vmin = min((dc - a) / (fc - a), (dc - a) / (fc + a))
            vmax = max((dc + a) / (fc - a), (dc + a) / (fc + a))
        c0, c1 = _sub_range(umin, umax, u_sub[0], du, n_sub_u)
        r0, r1 = _sub_range(vmin, vmax, v_sub[0], dv, n_sub_v)
        cz = dd * k_scale
        c_sq = f * f + r * r + cz * cz - a * a
        for ri in range(r0, r1 + 1):
            v = v_sub[ri]
            wf = cp + v * sp
            vk = (v * cp - sp) * k_scale
            for ci in range(c0, c1 + 1):
                u = u_sub[ci]
                A = wf * wf + u * u + vk * vk
                b = f * wf + u * r + vk * cz
                if c_sq <= 0.0:
                    t = 0.0
                else:
                    disc = b * b - A * c_sq
                    if disc < 0.0:
                        continue
                    t = (b - math.sqrt(disc)) / A
                    if t <= 0.0:
                        continue
                oi = ri // s
                oj = ci // s
                if t < out[m, oi, oj]:
                    out[m, oi, oj] = t
                if t < obj_min:
                    obj_min = t

    w = m // n_per_world
    # Boxes: slab test in NED along the ray direction (cos - sin u, sin + cos u, v).
    for q in range(boxes.shape[1]):
        cn, ce, cd, hn, he, hd = boxes[w, q, 0], boxes[w, q, 1], boxes[w, q, 2], boxes[w, q, 3], boxes[w, q, 4], boxes[w, q, 5]
        if hn <= 0.0 or he <= 0.0 or hd <= 0.0:
            continue  # padding row
        status, umin, umax, vmin, vmax = _project_box_bounds(cn, ce, cd, hn, he, hd, px, py, pz, cos_y, sin_y, cp, sp,
                                                             tu, tv, max_range)
        if status == 0:
            continue
        c0, c1 = _sub_range(umin, umax, u_sub[0], du, n_sub_u)
        r0, r1 = _sub_range(vmin, vmax, v_sub[0], dv, n_sub_v)
        lo_n, hi_n = cn - hn - px, cn + hn - px
        lo_e, hi_e = ce - he - py, ce + he - py
        lo_d, hi_d = cd - hd - pz, cd + hd - pz
        inside = lo_n < 0.0 < hi_n and lo_e < 0.0 < hi_e and lo_d < 0.0 < hi_d
        for ri in range(r0, r1 + 1):
            v = v_sub[ri]
            wf = cp + v * sp
            wd = v * cp - sp
            for ci in range(c0, c1 + 1):
                u = u_sub[ci]
                if inside:
                    t = 0.0
                else:
                    wn = cos_y * wf - sin_y * u
                    we = sin_y * wf + cos_y * u
                    t_near = 0.0
                    t_far = 1e30
                    hit = True
                    for lo, hi, w_ax in ((lo_n, hi_n, wn), (lo_e, hi_e, we), (lo_d, hi_d, wd)):
                        if abs(w_ax) < 1e-12:
                            if lo > 0.0 or hi < 0.0:
                                hit = False
                        else:
                            t1 = lo / w_ax
                            t2 = hi / w_ax
                            if t1 > t2:
                                t1, t2 = t2, t1
                            t_near = max(t_near, t1)
                            t_far = min(t_far, t2)
                    if not hit or t_near > t_far or t_near <= 0.0:
                        continue
                    t = t_near
                oi = ri // s
                oj = ci // s
                if t < out[m, oi, oj]:
                    out[m, oi, oj] = t
                if t < obj_min:
                    obj_min = t

    # Vertical cylinders: side surface plus the two caps.
    for q in range(cyls.shape[1]):
        cn, ce, rad, z_top, z_bot = cyls[w, q, 0], cyls[w, q, 1], cyls[w, q, 2], cyls[w, q, 3], cyls[w, q, 4]
        if rad <= 0.0 or z_bot <= z_top:
            continue  # padding row
        hd = 0.5 * (z_bot - z_top)
        status, umin, umax, vmin, vmax = _project_box_bounds(cn, ce, z_top + hd, rad, rad, hd, px, py, pz, cos_y, sin_y,
                                                             cp, sp, tu, tv, max_range)
        if status == 0:
            continue
        c0, c1 = _sub_range(umin, umax, u_sub[0], du, n_sub_u)
        r0, r1 = _sub_range(vmin, vmax, v_sub[0], dv, n_sub_v)
        on, oe = px - cn, py - ce
        radial_sq = on * on + oe * oe - rad * rad
        inside = radial_sq < 0.0 and z_top < pz < z_bot
        for ri in range(r0, r1 + 1):
            v = v_sub[ri]
            wf = cp + v * sp
            wd = v * cp - sp
            for ci in range(c0, c1 + 1):
                u = u_sub[ci]
                if inside:
                    t = 0.0
                else:
                    wn = cos_y * wf - sin_y * u
                    we = sin_y * wf + cos_y * u
                    t = 1e30
                    A = wn * wn + we * we
                    b = on * wn + oe * we
                    disc = b * b - A * radial_sq
                    if disc >= 0.0 and radial_sq > 0.0:
                        ts = (-b - math.sqrt(disc)) / A
                        if ts > 0.0:
                            zs = pz + ts * wd
                            if z_top <= zs <= z_bot:
                                t = ts
                    if abs(wd) > 1e-12:
                        for zc in (z_top, z_bot):
                            tc = (zc - pz) / wd
                            if 0.0 < tc < t:
                                hn_ = on + tc * wn
                                he_ = oe + tc * we
                                if hn_ * hn_ + he_ * he_ <= rad * rad:
                                    t = tc
                    if t >= 1e30:
                        continue
                oi = ri // s
                oj = ci // s
                if t < out[m, oi, oj]:
                    out[m, oi, oj] = t
                if t < obj_min:
                    obj_min = t
    nearest_obj[m] = obj_min


@numba.njit(cache=True)
def _render_all(pos, yaw, pitch, visible, n_per_world, a_h, a_v, boxes, cyls, u_sub, v_sub, tu, tv, s, max_range,
                out, nearest_obj):
    for m in range(pos.shape[0]):
        _render_one(m, pos, yaw, pitch, visible, n_per_world, a_h, a_v, boxes, cyls, u_sub, v_sub, tu, tv, s,
                    max_range, out, nearest_obj)


@numba.njit(cache=True, parallel=True)
def _render_all_parallel(pos, yaw, pitch, visible, n_per_world, a_h, a_v, boxes, cyls, u_sub, v_sub, tu, tv, s,
                         max_range, out, nearest_obj):
    for m in numba.prange(pos.shape[0]):
        _render_one(m, pos, yaw, pitch, visible, n_per_world, a_h, a_v, boxes, cyls, u_sub, v_sub, tu, tv, s,
                    max_range, out, nearest_obj)


# --------------------------------------------------------------------------- noise

#: Intel RealSense D435 stereo geometry behind :class:`StereoNoise`'s defaults: 50 mm baseline,
#: a focal length of ~447 px at 848x480 (87 deg horizontal FOV: 424 / tan(43.5 deg)) and a
#: subpixel disparity error of ~0.08 px (Intel's depth tuning white paper: 0.05-0.1 px on a
#: well-textured scene). RMS depth error = z^2 * subpixel / (focal_px * baseline).
D435_BASELINE_M = 0.050
D435_FOCAL_PX = 447.0
D435_SUBPIXEL_PX = 0.08


#: Where depth edges leave holes (:attr:`StereoNoise.edge_holes`).
EDGE_HOLE_MODELS = ("shadow", "both")


@dataclass(frozen=True)
class StereoNoise:
    """A stereo depth camera's errors, reported the way the RealSense SDK reports them.

    Applied to a perfect render (:meth:`DepthCamera.render`, nothing in range = ``max_range_m``):

    * depth error: Gaussian with ``sigma = z^2 * subpixel_px / (focal_px * baseline_m)``
      (the stereo RMS error; ~1.4 % at 4 m, ~3.6 % at 10 m with the D435 defaults);
    * beyond the range: a pixel whose true depth is ``max_range_m`` or more (sky, a far
      wall) is invalid, 0 — not a noisy far reading; nearer than ``min_range_m``: invalid too;
    * holes, all invalid (0): far pixels fail to match with probability
      ``far_hole_prob * (z / max_range_m)^2``; pixels at a depth edge with ``edge_hole_prob``
      (which pixels: ``edge_holes`` below); any pixel with ``dropout_prob``; and with
      ``blob_prob`` per frame one rectangular blob (a textureless or glaring patch) of 2 to
      ``blob_max_px`` pixels per side.

    ``edge_holes`` says where depth edges leave holes. ``"shadow"`` (the default, what the
    evaluation protocols fly) is the stereo occlusion shadow: the strip of farther surface
    just *left* of a nearer one, which the right imager cannot see (RealSense depth is
    referenced to the left imager; the baseline is horizontal, so only jumps along a row
    cast one): a pixel whose right-hand neighbour is nearer by more than
    ``edge_jump_fraction`` of that neighbour's depth. The nearer surface itself keeps its
    depth: both imagers see it. ``"both"`` erases the pixels on both sides of every jump,
    along rows and columns: the model of sessions <= 34, harsher than the sensor (it erases
    the edges of a UAV, which at 2-4 pixels is all edge), kept as the recipes' training noise
    (:data:`sitl.learn.config.TRAINING_STEREO_NOISE`; docs/simulator.md "Stereo noise").

    The output follows :data:`companion.spec.INVALID_DEPTH_M`: invalid pixels read exactly 0,
    which :func:`companion.observation.clean_depth` turns into ``max_range_m`` for the policy,
    as onboard. Noise is drawn per policy pixel (the sim renders at the policy's resolution).
    """

    baseline_m: float = D435_BASELINE_M
    focal_px: float = D435_FOCAL_PX
    subpixel_px: float = D435_SUBPIXEL_PX
    min_range_m: float = 0.2
    far_hole_prob: float = 0.3
    edge_jump_fraction: float = 0.25
    edge_hole_prob: float = 0.3
    dropout_prob: float = 0.01
    blob_prob: float = 0.2
    blob_max_px: int = 6
    edge_holes: str = "shadow"  # one of EDGE_HOLE_MODELS

    def __post_init__(self) -> None:
        if self.edge_holes not in EDGE_HOLE_MODELS:
            raise ValueError(f"edge_holes must be one of {EDGE_HOLE_MODELS}, got {self.edge_holes!r}")

    @property
    def quadratic_coeff_per_m(self) -> float:
        """sigma / z^2 (1/m)."""
        return self.subpixel_px / (self.focal_px * self.baseline_m)

    def apply(self, depth_m: np.ndarray, max_range_m: float, rng: np.random.Generator) -> np.ndarray:
        """Return a noisy float32 copy of perfect depth ``depth_m`` [..., H, W], invalid pixels 0.

        The random draws are taken from ``rng`` in a fixed order (depth error, holes, edge
        holes, blobs) and the per-pixel arithmetic runs in one compiled pass
        (:func:`_stereo_noise_pixels`), in float32 as NumPy would do it: the same draws give the
        same image bit for bit as the NumPy expression it replaced (session 68, ``tests/test_camera.py``),
        in about half the time (``python benchmarks/camera_model.py --noise-cost``); the draws are
        most of what is left.
        """
        depth_m = np.asarray(depth_m, dtype=np.float32)
        if depth_m.ndim < 2:
            raise ValueError(f"depth must be [..., H, W], got shape {depth_m.shape}")
        height, width = depth_m.shape[-2:]
        frames = np.ascontiguousarray(depth_m).reshape(-1, height, width)
        error = rng.standard_normal(frames.shape, dtype=np.float32)
        hole_draw = rng.random(frames.shape, dtype=np.float32)
        edge_draw = rng.random(frames.shape, dtype=np.float32) if self.edge_hole_prob > 0 else hole_draw
        noisy, invalid = _stereo_noise_pixels(
            frames, error, hole_draw, edge_draw, np.float32(self.quadratic_coeff_per_m), np.float32(max_range_m),
            np.float32(self.min_range_m), np.float32(self.far_hole_prob), np.float32(self.dropout_prob),
            self.edge_hole_prob > 0, self.edge_holes == "shadow", np.float32(self.edge_jump_fraction),
            np.float32(self.edge_hole_prob))
        if self.blob_prob > 0:
            for k in np.flatnonzero(rng.random(frames.shape[0]) < self.blob_prob):
                bh, bw = rng.integers(2, self.blob_max_px + 1, size=2)
                top, left = rng.integers(0, max(height - bh, 0) + 1), rng.integers(0, max(width - bw, 0) + 1)
                invalid[k, top:top + bh, left:left + bw] = True
        noisy[invalid] = 0.0
        return noisy.reshape(depth_m.shape)


@numba.njit(cache=True)
def _stereo_noise_pixels(depth, error, hole_draw, edge_draw, coeff, max_range, min_range, far_hole_prob,
                         dropout_prob, edge_holes, shadow, jump_fraction, edge_hole_prob):
    """:meth:`StereoNoise.apply`'s per-pixel part on frames [F, H, W]: (depth with its error, clamped to
    ``min_range``; invalid mask before the blobs). Every operand is float32, in NumPy's order of operations."""
    n_frames, height, width = depth.shape
    noisy = np.empty_like(depth)
    invalid = np.empty(depth.shape, dtype=np.bool_)
    zero = np.float32(0.0)
    for f in range(n_frames):
        for r in range(height):
            for c in range(width):
                d = depth[f, r, c]
                z = min(max(d, zero), max_range) / max_range
                bad = (d >= max_range) or (d < min_range)
                bad = bad or hole_draw[f, r, c] < far_hole_prob * z * z + dropout_prob
                if edge_holes and not bad and edge_draw[f, r, c] < edge_hole_prob:
                    edge = False
                    if shadow:
                        # the pixel left of a nearer right-hand neighbour (the far side of the jump only)
                        if c + 1 < width:
                            right = depth[f, r, c + 1]
                            edge = d - right > jump_fraction * right
                    else:  # both sides of every jump, along rows and columns
                        if c + 1 < width:
                            o = depth[f, r, c + 1]
                            edge = edge or abs(o - d) > jump_fraction * min(o, d)
                        if c > 0:
                            o = depth[f, r, c - 1]
                            edge = edge or abs(d - o) > jump_fraction * min(d, o)
                        if r + 1 < height:
                            o = depth[f, r + 1, c]
                            edge = edge or abs(o - d) > jump_fraction * min(o, d)
                        if r > 0:
                            o = depth[f, r - 1, c]
                            edge = edge or abs(d - o) > jump_fraction * min(d, o)
                    bad = edge
                invalid[f, r, c] = bad
                noisy[f, r, c] = max(d + error[f, r, c] * (coeff * d * d), min_range)
    return noisy, invalid
