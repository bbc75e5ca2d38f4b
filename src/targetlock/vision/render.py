"""Endoscope-like rendering of a planar textured target, with ground truth.

The renderer turns a camera pose and a target pose (4x4, in the world frame, metres) into a
720x576 BGR uint8 frame that looks like a flexible endoscope's video:

* the pinhole intrinsics and radial (Brown-Conrady k1, k2) distortion of
  :class:`~targetlock.model.camera.CameraParams`;
* a round field of view (black outside a circle of ``fov_radius_px``, soft 1-2 px edge);
* a point light at the tip: irradiance ~ cos(angle) / distance^2, displayed with a gamma;
* specular glints from a light at the camera: a Phong-like lobe around the direction in which
  the locally bumped surface (the texture's height channel) faces the camera, so highlights
  slide over the tissue when the view changes, and saturate like real ones;
* motion blur: the exposure is integrated over sub-poses between the start and end pose;
* optical blur, seeded sensor noise, a per-frame light gain (lighting change) and occluders
  (instrument-like polygons drawn in front of the tissue).

Geometry: the target is the plane z = 0 of its frame; texture x runs along the frame's x axis,
texture y along its y axis and the texture's centre is the frame origin. A target frame with
identity rotation placed at (0, 0, d) in the camera frame is seen face-on, upright. Plane points
are given in metres in that frame: (x right, y down from the centre). With a ``surface`` that is
not flat (:class:`~targetlock.model.scene.SurfaceParams`, ``kind = "folds"``) plane point (x, y)
sits at (x, y, w(x, y, t)) instead: the rays of the coarse light grid are intersected with that
surface and the texture is sampled through the interpolated texel coordinates.

``render(region=)`` renders only part of the frame (the pixels a tracker reads), each pixel as in
the whole frame.

Speed (one core: ~2 ms per still 720x576 frame, ~3-3.8 ms with 2-4 motion-blur sub-poses):
everything per pixel runs in a few numba kernels, only over the pixels of the round field of
view, one image row at a time, in buffers allocated once per renderer. The distorted-pixel ->
undistorted-ray map is computed once; per row the texel coordinates come from one homography
per sub-pose and the (mip-mapped, padded) texture is sampled with vector gathers; the diffuse
shade is evaluated on a 4x coarser grid and interpolated, glints at half resolution (and only
where lit), the optical blur is a separable kernel, the sensor noise a seeded window of a few
precomputed noise images. Motion blur with 3 or more sub-poses resamples the mid-exposure
image by each sub-pose's (per tile constant) displacement instead of sampling the texture
again. :func:`render_benchmark` times it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from ..config import param, validate
from ..model.camera import CameraParams, project, world_to_camera
from ..model.scene import SurfaceParams
from .texture import aruco_texture, mucosa_texture, with_height

__all__ = ["RenderSettings", "PlanarTarget", "Frame", "Renderer", "make_pose", "interpolate_pose",
           "endoscope_camera", "render_benchmark"]


def endoscope_camera(**overrides) -> CameraParams:
    """The default intrinsics with the flexible-endoscope barrel distortion switched on
    (k1 = -0.25, k2 = 0.05, see :mod:`targetlock.model.camera`); the renderer's usual camera."""
    kw = {"k1": -0.25, "k2": 0.05}
    kw.update(overrides)
    return CameraParams(**kw)


@dataclass(frozen=True)
class RenderSettings:
    """How the twin's endoscope image is formed (optics, light, sensor)."""
    fov_radius_px: float = param(280.0, unit="px", lo=8.0, hi=4096.0, doc="radius of the round field of view")
    fov_edge_px: float = param(1.5, unit="px", lo=0.0, hi=50.0, doc="width of the soft edge of the field of view")
    light_ref_distance_m: float = param(0.05, unit="m", lo=1e-3, hi=1.0, lo_open=True,
                                        doc="distance at which a face-on surface is lit at gain 1")
    light_gain: float = param(1.0, lo=0.0, hi=100.0, doc="base light gain (render(light_gain=) multiplies it)")
    ambient: float = param(0.03, lo=0.0, hi=1.0, doc="ambient light (fraction of full diffuse)")
    gamma: float = param(2.2, lo=0.5, hi=4.0, doc="display gamma applied to the irradiance")
    specular_strength: float = param(2.5, lo=0.0, hi=10.0, doc="peak specular intensity (1 = white); 0 disables glints")
    specular_exponent: float = param(2000.0, lo=1.0, hi=5000.0, doc="sharpness of the specular lobe (Phong exponent)")
    bump_slope: float = param(0.15, unit="rad", lo=0.0, hi=1.0, doc="RMS surface slope of the texture's height relief")
    noise_sigma: float = param(2.0, unit="DN", lo=0.0, hi=50.0, doc="sensor noise standard deviation (8-bit levels)")
    fresh_noise: bool = param(False, doc="draw new sensor noise for every frame (~8 ms) instead of a shifted window of "
                                         "a small precomputed bank (the same pattern, moved, recurs: on weak texture "
                                         "under strong noise a tracker can follow the pattern's shift)")
    optical_blur_px: float = param(0.6, unit="px", lo=0.0, hi=10.0, doc="Gaussian sigma of the optics' blur; 0 disables")
    blur_step_px: float = param(2.0, unit="px", lo=0.1, hi=100.0, doc="largest image motion between exposure sub-poses")
    max_subframes: int = param(8, lo=1, hi=64, doc="most sub-poses integrated for motion blur")
    mipmap: bool = param(True, doc="sample a texture pyramid level matching the on-screen texel size")
    background_bgr: tuple[int, int, int] = param((40, 45, 110), lo=0, hi=255,
                                                 doc="colour of the plane outside the texture")
    texture_px: int = param(2048, unit="px", lo=64, hi=8192, doc="side of the procedural default texture")
    occluder_bgr: tuple[int, int, int] = param((165, 170, 175), lo=0, hi=255, doc="colour of occluders (instruments)")


@dataclass(frozen=True, eq=False)
class PlanarTarget:
    """A textured rectangle: physical size (m), texture and the selected target point.

    ``texture`` is HxWx4 uint8 (B, G, R, height), see :mod:`targetlock.vision.texture`;
    ``selected_point_m`` is the point the tracker should follow, in plane metres from the
    centre (x right, y down).
    """
    size_m: tuple[float, float]
    texture: np.ndarray
    selected_point_m: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        w, h = self.size_m
        if not (w > 0 and h > 0):
            raise ValueError(f"size_m = {self.size_m}; both sides must be > 0 m")
        object.__setattr__(self, "texture", with_height(self.texture))

    @classmethod
    def mucosa(cls, size_m: tuple[float, float] = (0.2, 0.2), seed: int = 0, texture_px: int = 2048,
               selected_point_m: tuple[float, float] = (0.0, 0.0)) -> "PlanarTarget":
        """The procedural mucosa texture (deterministic in ``seed``)."""
        return cls(size_m, mucosa_texture(seed, texture_px), selected_point_m)

    @classmethod
    def aruco(cls, marker_id: int = 0, dictionary: str = "DICT_4X4_50", size_m: tuple[float, float] = (0.2, 0.2),
              marker_fraction: float = 0.12, seed: int = 0, texture_px: int = 2048) -> "PlanarTarget":
        """Mucosa with an ArUco marker at the centre; the selected point is the marker centre."""
        return cls(size_m, aruco_texture(marker_id, dictionary, texture_px, marker_fraction, seed), (0.0, 0.0))

    @classmethod
    def from_image(cls, path: str | Path, size_m: tuple[float, float],
                   selected_point_m: tuple[float, float] = (0.0, 0.0)) -> "PlanarTarget":
        """Any image file readable by OpenCV as texture (flat height: no glints from relief)."""
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None:
            raise FileNotFoundError(f"cannot read image {path}")
        return cls(size_m, img, selected_point_m)

    def plane_to_texel(self, point_m: np.ndarray) -> np.ndarray:
        """Texel coordinates (..., 2) (level 0, centre-of-texel integers) of plane points (..., 2) m."""
        p = np.asarray(point_m, dtype=float)
        h, w = self.texture.shape[:2]
        return np.stack([(p[..., 0] + self.size_m[0] / 2) * w / self.size_m[0] - 0.5,
                         (p[..., 1] + self.size_m[1] / 2) * h / self.size_m[1] - 0.5], axis=-1)


@dataclass(frozen=True, eq=False)
class Frame:
    """One rendered frame and its ground truth."""
    image: np.ndarray
    """BGR uint8 (height, width, 3)."""
    truth_px: np.ndarray
    """Pixel position (x, y; distorted, as :func:`project` gives it) of the selected target point
    at mid-exposure; may lie outside the image or the field of view."""
    visible: bool
    """The selected point is in front of the camera, inside the round field of view and not covered."""
    occluded: bool = False
    """The selected point is covered by an occluder."""
    subframes: int = 1
    """Number of sub-poses integrated (1: no motion blur)."""

    def truth_offset(self, cam: CameraParams) -> np.ndarray:
        """Ground-truth offset from the image centre (px, x right, y down)."""
        return self.truth_px - np.array([cam.cx, cam.cy])


def make_pose(translation: Sequence[float] = (0.0, 0.0, 0.0), rotvec: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4 pose from a translation (m) and a rotation vector (axis * angle, rad)."""
    out = np.eye(4)
    out[:3, :3] = cv2.Rodrigues(np.asarray(rotvec, dtype=float).reshape(3, 1))[0]
    out[:3, 3] = translation
    return out


def interpolate_pose(a: np.ndarray, b: np.ndarray, s: float) -> np.ndarray:
    """Pose a fraction ``s`` in [0, 1] of the way from ``a`` to ``b`` (linear translation, geodesic rotation)."""
    out = np.eye(4)
    if np.array_equal(a[:3, :3], b[:3, :3]):            # same orientation (e.g. a static pose): no rotation
        out[:3, :3] = a[:3, :3]
    else:
        rel = a[:3, :3].T @ b[:3, :3]
        rv = cv2.Rodrigues(rel)[0].ravel()
        out[:3, :3] = a[:3, :3] @ cv2.Rodrigues(rv * s)[0]
    out[:3, 3] = (1 - s) * a[:3, 3] + s * b[:3, 3]
    return out


def _undistort_radius(rd: np.ndarray, k1: float, k2: float) -> np.ndarray:
    """Solve r (1 + k1 r^2 + k2 r^4) = rd for r >= 0 by Newton's method (vectorised)."""
    r = rd.copy()
    for _ in range(50):
        r2 = r * r
        g = r * (1 + k1 * r2 + k2 * r2 * r2) - rd
        dg = 1 + 3 * k1 * r2 + 5 * k2 * r2 * r2
        step = g / dg
        r -= step
        if np.max(np.abs(step)) < 1e-12:
            break
    return r


# ---------------------------------------------------------------------------------- kernels
# The per-pixel work runs in numba kernels, over the pixels of the round field of view only (one
# span of columns per row), in buffers allocated once per renderer, one image row at a time (the
# working set stays in the L1 cache); the texel fetch uses explicit vector gathers (an LLVM
# intrinsic). For LLVM to vectorise the inner loops they are written with care: they run over row
# slices from index 0 (``for i in range(a, b): x[i]`` carries negative-index checks), without
# reductions through min/max, with float32 constants (an int literal times a float32 is float64 in
# numba) and with error_model="numpy" (no division-by-zero branches). fastmath: no NaN tests.
_JIT = dict(cache=True, fastmath=True, error_model="numpy", boundscheck=False)
_PAD = 2                    # texture levels are padded with 2 texels of the border colour
_FIX = 128                  # texel coordinates in 1/128 texel (7-bit bilinear weights)


def _make_bilerp16(accumulate: bool):
    """Intrinsic: bilinear texture samples of 16 pixels, vectorised with gathers (LLVM's generic
    masked gather: AVX2 / AVX-512 where available, scalar loads elsewhere).

    ``f(tex, rowb, fu, fv, i, a0, a1, a2, a3)``: for pixels i .. i + 15, texel coordinates
    fu, fv (int32, 1/128 texel, in the padded level whose rows are ``rowb`` bytes; tex: its uint8
    bytes, BGRA texels) -> a_c[i ..] (=, or += if ``accumulate``) the 2x2 blend of byte c of the
    texels with weights in 1/128 (so 128^2 x the value). The caller guarantees every coordinate
    (all 16) addresses texels inside ``tex``.
    """
    @intrinsic
    def bilerp16(typingctx, tex, rowb, fu, fv, i, a0, a1, a2, a3):
        sig = types.void(tex, rowb, fu, fv, i, a0, a1, a2, a3)

        def codegen(context, builder, signature, args):
            texv, rowbv, fuv, fvv, iv = args[:5]
            i32, i64 = ir.IntType(32), ir.IntType(64)
            v16, v16l = ir.VectorType(i32, 16), ir.VectorType(i64, 16)
            idx16 = ir.VectorType(i32, 16)

            def data(k, v):
                return context.make_array(signature.args[k])(context, builder, v).data

            def slot(k, v):                         # &array[i] as <16 x i32>*
                return builder.bitcast(builder.gep(data(k, v), [iv]), v16.as_pointer())

            def splat(x, t):
                v = builder.insert_element(ir.Constant(t, ir.Undefined), x, ir.Constant(i32, 0))
                return builder.shuffle_vector(v, v, ir.Constant(idx16, [0] * 16))

            def const(c, t=v16):
                return ir.Constant(t, [c] * 16)

            fu16 = builder.load(slot(2, fuv), align=4)
            fv16 = builder.load(slot(3, fvv), align=4)
            rb = builder.trunc(rowbv, i32)
            off = builder.add(builder.mul(builder.ashr(fv16, const(7)), splat(rb, v16)),
                              builder.shl(builder.ashr(fu16, const(7)), const(2)))
            addr = builder.add(splat(builder.ptrtoint(data(0, texv), i64), v16l), builder.sext(off, v16l))
            ptrs = ir.VectorType(i32.as_pointer(), 16)
            mask = ir.Constant(ir.VectorType(ir.IntType(1), 16), [1] * 16)
            gather = cgutils.get_or_insert_function(
                builder.module, ir.FunctionType(v16, [ptrs, i32, mask.type, v16]), "llvm.masked.gather.v16i32.v16p0")

            def fetch(a):
                return builder.call(gather, [builder.inttoptr(a, ptrs), ir.Constant(i32, 1), mask,
                                             ir.Constant(v16, ir.Undefined)])

            rb16 = splat(builder.sext(rb, i64), v16l)
            c00 = fetch(addr)
            c01 = fetch(builder.add(addr, const(4, v16l)))
            c10 = fetch(builder.add(addr, rb16))
            c11 = fetch(builder.add(builder.add(addr, rb16), const(4, v16l)))
            wu = builder.and_(fu16, const(_FIX - 1))
            wv = builder.and_(fv16, const(_FIX - 1))
            iwu = builder.sub(const(_FIX), wu)
            iwv = builder.sub(const(_FIX), wv)
            for c in range(4):
                def byte(x):
                    return builder.and_(builder.lshr(x, const(8 * c)) if c else x, const(255))
                top = builder.add(builder.mul(byte(c00), iwu), builder.mul(byte(c01), wu))
                bot = builder.add(builder.mul(byte(c10), iwu), builder.mul(byte(c11), wu))
                val = builder.add(builder.mul(top, iwv), builder.mul(bot, wv))
                p = slot(5 + c, args[5 + c])
                if accumulate:
                    val = builder.add(builder.load(p, align=4), val)
                builder.store(val, p, align=4)
            return context.get_dummy_value()
        return sig, codegen
    return bilerp16


_bilerp16_set = _make_bilerp16(False)
_bilerp16_add = _make_bilerp16(True)


@njit(**_JIT)
def _light_grid(rays, spans, shade_spans, nrm, amb, base_pow, shade_max, cos_lut, shade, cs_row):
    """Diffuse shade on the coarse grid of unit rays ((3, ch, cw) float32), over the row
    ``shade_spans`` (within ``spans``): ambient + (e0 cos^3)^(1/gamma) = amb + base_pow
    cos^(3/gamma) (``cos_lut``), clipped to ``shade_max`` and truncated to 1/128 like an 8-bit
    image; returns the largest cos over ``spans`` (0 if none)."""
    nl = cos_lut.shape[0] - 1
    n0, n1, n2 = np.float32(nrm[0]), np.float32(nrm[1]), np.float32(nrm[2])
    cmax = 0.0
    for j in range(shade.shape[0]):
        a, b = spans[j, 0], spans[j, 1]
        if b <= a:
            continue
        rx = rays[0, j, a:b]
        ry = rays[1, j, a:b]
        rz = rays[2, j, a:b]
        cs = cs_row[:b - a]
        for i in range(b - a):
            cs[i] = -(rx[i] * n0 + ry[i] * n1 + rz[i] * n2)
        rm = np.float32(0.0)                      # (float32, branch-free: vectorised)
        for i in range(b - a):
            rm = max(rm, cs[i])
        if rm > 1e-3:
            cmax = max(cmax, float(rm))
        sa, sb = shade_spans[j, 0], shade_spans[j, 1]
        if sb <= sa:
            continue
        sh = shade[j, sa:sb]
        for i in range(sb - sa):
            c = cs[sa - a + i]
            if c > 1e-3:
                t = c * nl
                k = min(int(t), nl - 1)
                p = cos_lut[k] + (cos_lut[k + 1] - cos_lut[k]) * (t - k)
                sh[i] = math.floor(min(amb + base_pow * p, shade_max) * 128.0) / 128.0
            else:
                sh[i] = 0.0
    return cmax


@njit(**_JIT)
def _row_weights(y, q, n):
    """Coarse rows and weight of the second for fine row ``y`` (cv2.resize(INTER_LINEAR) x``q``)."""
    s = (y + 0.5) / q - 0.5
    if s <= 0.0:
        return 0, 0, np.float32(0.0)
    j = int(s)
    if j >= n - 1:
        return n - 1, n - 1, np.float32(0.0)
    return j, j + 1, np.float32(s - j)


@njit(**_JIT)
def _coarse_row(grid, y, q, crow, ext, dst):
    """Row ``y`` of ``grid`` upsampled x``q`` (q = 2 or 4) as cv2.resize(INTER_LINEAR) does
    (coarse sample k sits at q k + (q - 1) / 2, clamped at the ends) into ``dst`` (len q * cw);
    ``crow`` (cw) and ``ext`` (cw + 2) are scratch."""
    n = grid.shape[1]
    j0, j1, wy = _row_weights(y, q, grid.shape[0])
    g0 = grid[j0]
    g1 = grid[j1]
    for i in range(n):
        crow[i] = g0[i] + wy * (g1[i] - g0[i])
    ext[0] = crow[0]
    e = ext[1:n + 1]
    for i in range(n):
        e[i] = crow[i]
    ext[n + 1] = crow[n - 1]
    if q == 4:
        for i in range(n):
            a, b, c = ext[i], ext[i + 1], ext[i + 2]
            dst[4 * i] = np.float32(0.375) * a + np.float32(0.625) * b
            dst[4 * i + 1] = np.float32(0.125) * a + np.float32(0.875) * b
            dst[4 * i + 2] = np.float32(0.875) * b + np.float32(0.125) * c
            dst[4 * i + 3] = np.float32(0.625) * b + np.float32(0.375) * c
    else:
        for i in range(n):
            a, b, c = ext[i], ext[i + 1], ext[i + 2]
            dst[2 * i] = np.float32(0.25) * a + np.float32(0.75) * b
            dst[2 * i + 1] = np.float32(0.75) * b + np.float32(0.25) * c


@njit(**_JIT)
def _texel_coords(m, k, rx, ry, fu, fv, umax, vmax):
    """Texel coordinates (1/128 texel, + 2 texels of padding, clamped to the padded level) of the
    rays (rx, ry) under homography ``m[k]``; rays behind the camera land in the border."""
    lo = np.float32(-_PAD * _FIX)
    a0, a1, a2 = m[k, 0], m[k, 1], m[k, 2]
    b0, b1, b2 = m[k, 3], m[k, 4], m[k, 5]
    c0, c1, c2 = m[k, 6], m[k, 7], m[k, 8]
    for i in range(fu.shape[0]):
        x = rx[i]
        y = ry[i]
        den = c0 * x + c1 * y + c2
        inv = np.float32(_FIX) / max(den, np.float32(1e-30))
        u = (a0 * x + a1 * y + a2) * inv
        v = (b0 * x + b1 * y + b2) * inv
        u = min(max(u, lo), umax) if den > 0 else lo
        v = min(max(v, lo), vmax) if den > 0 else lo
        fu[i] = np.int32(u + np.float32(_PAD * _FIX + 0.5))
        fv[i] = np.int32(v + np.float32(_PAD * _FIX + 0.5))


@njit(**_JIT)
def _grid_coords(gu, gv, fu, fv, umax, vmax):
    """Texel coordinates as :func:`_texel_coords` gives them, from level texel coordinates
    (``gu``, ``gv``, float32) interpolated from a surface's coarse grid."""
    lo = np.float32(-_PAD * _FIX)
    for i in range(fu.shape[0]):
        u = min(max(gu[i] * np.float32(_FIX), lo), umax)
        v = min(max(gv[i] * np.float32(_FIX), lo), vmax)
        fu[i] = np.int32(u + np.float32(_PAD * _FIX + 0.5))
        fv[i] = np.int32(v + np.float32(_PAD * _FIX + 0.5))


@njit(**_JIT)
def _sample_shade(tex, rowb, umax, vmax, mats, rx_map, ry_map, moff, ray0, spans, ospans, shade_c, q, boff, planes,
                  hplane, inter, iota, rxs, rys, fus, fvs, acc, srow, crow, ext, grids, grow):
    """Image (B, G, R interleaved: ``planes`` (rows, cols, 3) uint8) and height (``hplane``
    (rows, cols) uint8) over the row ``spans``.

    The padded texture level (``tex``: its bytes, rows of ``rowb`` bytes) is sampled bilinearly
    (gathers, :func:`_make_bilerp16`) at the sub-pose homographies ``mats`` (n, 9,
    undistorted normalised ray -> level texel) and averaged; B, G, R are multiplied by the shade,
    upsampled from ``shade_c`` (x``q``, on the field-of-view box). Output pixel (y, x) is box pixel
    (y - boff, x - boff). Rays: ``rx_map``/``ry_map`` at (y + moff, x + moff) if not empty (lens
    distortion), else ray0[:2] + (x, y) * ray0[2:], in float32 from the start of the row's span in
    ``ospans`` (the whole frame's spans, which contain ``spans``: a region renders as in the whole
    frame). ``inter``: ``planes`` is (rows, cols, 4) float32
    (B, G, R, height, unrounded) instead and ``hplane`` is unused.
    ``srow``: scratch of the box width + twice the largest ``boff``; ``iota`` = 0, 1, 2, ... (float32);
    the rest are scratch rows (``fus``, ``fvs``, ``acc`` rows: 16 longer than the widest span).
    ``grids`` (n, 2, rows / q, cols / q) float32, if not empty (a surface that is not a plane;
    only with ``boff`` = 0): level texel coordinates on the coarse grid at each sub-pose, upsampled
    x``q`` instead of the homographies ``mats``; ``grow``: (2, cols) float32 scratch.
    """
    have_grid = grids.shape[0] > 0
    n = grids.shape[0] if have_grid else mats.shape[0]
    have_map = rx_map.shape[0] > 0
    inv_n = np.float32(1.0 / (_FIX * _FIX * n))
    half = np.float32(0.5)
    top = np.float32(255.0)
    cw = shade_c.shape[1]
    bw = q * cw
    mg = (srow.shape[0] - bw) // 2
    flat_out = planes.reshape(-1)
    cols_out = planes.shape[1]
    sbox = srow[mg:mg + bw]
    for y in range(spans.shape[0]):
        xa, xb = spans[y, 0], spans[y, 1]
        if xb <= xa:
            continue
        m = xb - xa
        if have_map:
            rx = rx_map[y + moff, xa + moff:xb + moff]
            ry = ry_map[y + moff, xa + moff:xb + moff]
        else:
            rx = rxs[:m]
            ry = rys[:m]
            oa = ospans[y, 0]
            x0 = np.float32(ray0[0] + oa * ray0[2])
            dx = np.float32(ray0[2])
            yv = np.float32(ray0[1] + y * ray0[3])
            xs = iota[xa - oa:xb - oa]
            for i in range(m):
                rx[i] = x0 + xs[i] * dx
                ry[i] = yv
        # shade of this row, box row upsampled and extended by edge replication
        _coarse_row(shade_c, y - boff, q, crow, ext, sbox)
        for i in range(bw):                         # an 8-bit shade image (x 128), as multiplied
            sbox[i] = np.float32(np.int32(sbox[i] * np.float32(128.0) + half)) * np.float32(1.0 / 128.0)
        for i in range(mg):
            srow[i] = sbox[0]
            srow[mg + bw + i] = sbox[bw - 1]
        sr = srow[xa + mg - boff:xb + mg - boff]
        fu = fus[:m]
        fv = fvs[:m]
        m16 = (m + 15) // 16 * 16
        for k in range(n):
            if have_grid:
                _coarse_row(grids[k, 0], y, q, crow, ext, grow[0])
                _coarse_row(grids[k, 1], y, q, crow, ext, grow[1])
                _grid_coords(grow[0, xa:xb], grow[1, xa:xb], fu, fv, umax, vmax)
            else:
                _texel_coords(mats, k, rx, ry, fu, fv, umax, vmax)
            for i in range(m, m16):                 # the gathers' tail lanes: texel (0, 0)
                fus[i] = 0
                fvs[i] = 0
            if k == 0:
                for i in range(0, m16, 16):
                    _bilerp16_set(tex, rowb, fus, fvs, i, acc[0], acc[1], acc[2], acc[3])
            else:
                for i in range(0, m16, 16):
                    _bilerp16_add(tex, rowb, fus, fvs, i, acc[0], acc[1], acc[2], acc[3])
        if inter:                                   # (rows, cols, 4) float32, unrounded
            dst = flat_out[4 * (y * cols_out + xa):4 * (y * cols_out + xb)]
            a0 = acc[0, :m]
            a1 = acc[1, :m]
            a2 = acc[2, :m]
            a3 = acc[3, :m]
            for i in range(m):
                s = sr[i] * inv_n
                dst[4 * i] = min(np.float32(a0[i]) * s, top)
                dst[4 * i + 1] = min(np.float32(a1[i]) * s, top)
                dst[4 * i + 2] = min(np.float32(a2[i]) * s, top)
                dst[4 * i + 3] = np.float32(a3[i]) * inv_n
            continue
        dst = flat_out[3 * (y * cols_out + xa):3 * (y * cols_out + xb)]
        a0 = acc[0, :m]
        a1 = acc[1, :m]
        a2 = acc[2, :m]
        for i in range(m):
            s = sr[i] * inv_n
            dst[3 * i] = min(np.float32(a0[i]) * s + half, top)
            dst[3 * i + 1] = min(np.float32(a1[i]) * s + half, top)
            dst[3 * i + 2] = min(np.float32(a2[i]) * s + half, top)
        a3 = acc[3, :m]
        hp = hplane[y, xa:xb]
        for i in range(m):
            hp[i] = np.float32(a3[i]) * inv_n + half


@njit(**_JIT)
def _tile_shifts(gmats, rx_map, ry_map, ray0, cam6, mg, tw, th, out):
    """Image displacement (px) from each sub-pose to mid-exposure of the plane point seen at the
    centre pixel of each tile (th rows x tw columns of the box): out[k, ti, tj] = (dx, dy).
    ``gmats``, ``cam6``, ``mg``, rays: as in :func:`_motion_blur`. Returns the largest |component|."""
    n, nty, ntx = out.shape[0], out.shape[1], out.shape[2]
    have_map = rx_map.shape[0] > 0
    fx, fy, cx, cy, k1, k2 = cam6[0], cam6[1], cam6[2], cam6[3], cam6[4], cam6[5]
    big = 0.0
    for ti in range(nty):
        y = ti * th + th // 2
        for tj in range(ntx):
            x = tj * tw + tw // 2
            if have_map:
                yy = min(y + mg, rx_map.shape[0] - 1)
                xx = min(x + mg, rx_map.shape[1] - 1)
                rx = float(rx_map[yy, xx])
                ry = float(ry_map[yy, xx])
            else:
                rx = ray0[0] + x * ray0[2]
                ry = ray0[1] + y * ray0[3]
            for k in range(n):
                g = gmats[k]
                w = g[6] * rx + g[7] * ry + g[8]
                if w <= 1e-9:
                    out[k, ti, tj, 0] = 0.0
                    out[k, ti, tj, 1] = 0.0
                    big = 1e9
                    continue
                u = (g[0] * rx + g[1] * ry + g[2]) / w
                v = (g[3] * rx + g[4] * ry + g[5]) / w
                r2 = u * u + v * v
                d = 1.0 + r2 * (k1 + k2 * r2)
                dx = fx * u * d + cx - (x + mg)
                dy = fy * v * d + cy - (y + mg)
                out[k, ti, tj, 0] = dx
                out[k, ti, tj, 1] = dy
                big = max(big, abs(dx), abs(dy))
    return big


@njit(**_JIT)
def _motion_blur(mid, mg, shifts, tw, th, spans, bgr, hplane, acc):
    """Motion blur in the image: ``bgr`` (box, (bh, bw, 3) uint8) and ``hplane`` ((bh, bw) uint8) =
    the average over the sub-poses of the mid-exposure image ``mid`` ((rows, cols, 4) float32: box +
    margin ``mg`` on each side) shifted by each sub-pose's displacement to mid-exposure, taken
    constant over tiles of th x tw pixels (``shifts`` from :func:`_tile_shifts`), with bilinear
    weights (contiguous loads). ``acc``: float32 scratch (4 x box width)."""
    n = shifts.shape[0]
    rows, cols = mid.shape[0], mid.shape[1]
    flat = mid.reshape(-1)
    pitch = 4 * cols
    bflat = bgr.reshape(-1)
    bcols = bgr.shape[1]
    f32 = np.float32
    inv_n = f32(1.0 / n)
    half = f32(0.5)
    for y in range(spans.shape[0]):
        xa, xb = spans[y, 0], spans[y, 1]
        if xb <= xa:
            continue
        ti = y // th
        for tj in range(xa // tw, (xb - 1) // tw + 1):
            xs = max(xa, tj * tw)
            xe = min(xb, tj * tw + tw)
            L4 = 4 * (xe - xs)
            ac = acc[4 * (xs - xa):4 * (xe - xa)]
            for k in range(n):
                dx = shifts[k, ti, tj, 0]
                dy = shifts[k, ti, tj, 1]
                ix = int(np.floor(dx))
                iy = int(np.floor(dy))
                fx = f32(dx - ix)
                fy = f32(dy - iy)
                r0 = min(max(y + mg + iy, 0), rows - 2)
                c0 = 4 * min(max(xs + mg + ix, 0), cols - 1 - (xe - xs))
                w00 = (f32(1.0) - fx) * (f32(1.0) - fy)
                w01 = fx * (f32(1.0) - fy)
                w10 = (f32(1.0) - fx) * fy
                w11 = fx * fy
                t0 = r0 * pitch + c0
                a0 = flat[t0:t0 + L4]
                a1 = flat[t0 + 4:t0 + 4 + L4]
                b0 = flat[t0 + pitch:t0 + pitch + L4]
                b1 = flat[t0 + pitch + 4:t0 + pitch + 4 + L4]
                if k == 0:
                    for i in range(L4):
                        ac[i] = w00 * a0[i] + w01 * a1[i] + w10 * b0[i] + w11 * b1[i]
                else:
                    for i in range(L4):
                        ac[i] += w00 * a0[i] + w01 * a1[i] + w10 * b0[i] + w11 * b1[i]
        m = xb - xa
        dst = bflat[3 * (y * bcols + xa):3 * (y * bcols + xb)]
        hp = hplane[y, xa:xb]
        lo = f32(0.0)
        hi = f32(255.0)
        for i in range(m):
            dst[3 * i] = min(max(acc[4 * i] * inv_n, lo), hi) + half
            dst[3 * i + 1] = min(max(acc[4 * i + 1] * inv_n, lo), hi) + half
            dst[3 * i + 2] = min(max(acc[4 * i + 2] * inv_n, lo), hi) + half
            hp[i] = min(max(acc[4 * i + 3] * inv_n, lo), hi) + half


@njit(**_JIT)
def _dilate_spans(spans, r, width, out):
    """Row spans of the ``spans`` region dilated by a (2r + 1)^2 square, clipped to [0, width)."""
    h = spans.shape[0]
    for y in range(h):
        a = width
        b = 0
        for d in range(max(0, y - r), min(h, y + r + 1)):
            if spans[d, 1] > spans[d, 0]:
                a = min(a, spans[d, 0])
                b = max(b, spans[d, 1])
        if b > a:
            out[y, 0] = max(a - r, 0)
            out[y, 1] = min(b + r, width)
        else:
            out[y, 0] = 0
            out[y, 1] = 0


@njit(**_JIT)
def _specular_half(hplane, hspans, sspans, rays, nrm, r0, r1, w_scale, cmat, half_k, thresh, hmap, t_row, spec,
                   lit_rng, sgrid, srows, crow, ext):
    """Glints at half resolution into ``spec`` (uint8) over ``sspans``; returns whether any is lit.

    Lobe exp(-k/2 |a - g|^2) times the glint weight w_scale cos^3 (cos = -ray . nrm) times the
    gloss min(height, 16) / 16, with a = -(ray . r0, ray . r1) the view tilt along the texture
    axes and g the surface slope: ``cmat`` (2x2) times the Sobel gradient of the 2x2-averaged
    sampled height (``hplane``). ``rays``: (3, h2, w2) unit rays of the half-resolution pixels.
    ``hmap``: (h2 + 2, w2 + 2) float32 scratch (averaged height, reflected 1-pixel border).
    Pixels with k/2 |a - g|^2 >= ``thresh`` round to 0 and skip the exponential. ``lit_rng`` (h2, 2):
    per row, the columns [first, last + 1) with a glint ((0, 0) if none).
    ``sgrid`` (3, h2 / 2, w2 / 2) float32, if not empty (a surface that is not a plane): on the
    coarse grid, the surface's own slope along the texture axes (added to the bump slope) and the
    glint weight (instead of w_scale cos^3), upsampled x2 (``srows`` (3, w2), ``crow``, ``ext``: scratch).
    """
    have_grid = sgrid.shape[0] > 0
    h2, w2 = spec.shape
    for i in range(h2):
        ja, jb = hspans[i, 0], hspans[i, 1]
        if jb <= ja:
            continue
        m = jb - ja
        p0 = hplane[2 * i, 2 * ja:2 * jb]
        p1 = hplane[2 * i + 1, 2 * ja:2 * jb]
        d = hmap[i + 1, ja + 1:jb + 1]
        for t in range(m):                                  # cv2.resize(INTER_AREA) x1/2, rounded
            d[t] = np.float32((np.int32(p0[2 * t]) + np.int32(p0[2 * t + 1]) + np.int32(p1[2 * t])
                               + np.int32(p1[2 * t + 1]) + 2) >> 2)
        if ja == 0:                                         # reflect-101 border
            hmap[i + 1, 0] = hmap[i + 1, 2]
        if jb == w2:
            hmap[i + 1, w2 + 1] = hmap[i + 1, w2 - 1]
    if hspans[0, 1] > hspans[0, 0]:
        hmap[0, :] = hmap[2, :]
    if hspans[h2 - 1, 1] > hspans[h2 - 1, 0]:
        hmap[h2 + 1, :] = hmap[h2 - 1, :]
    f32 = np.float32
    c00, c01, c10, c11 = f32(cmat[0] / 16), f32(cmat[1] / 16), f32(cmat[2] / 16), f32(cmat[3] / 16)
    n0, n1, n2 = f32(nrm[0]), f32(nrm[1]), f32(nrm[2])
    u0, u1, u2 = f32(r0[0]), f32(r0[1]), f32(r0[2])
    v0, v1, v2 = f32(r1[0]), f32(r1[1]), f32(r1[2])
    hk = f32(half_k)
    th = f32(thresh)
    two = f32(2.0)
    lit = False
    for i in range(h2):
        ja, jb = sspans[i, 0], sspans[i, 1]
        lit_rng[i, 0] = 0
        lit_rng[i, 1] = 0
        if jb <= ja:
            continue
        m = jb - ja
        rx = rays[0, i, ja:jb]
        ry = rays[1, i, ja:jb]
        rz = rays[2, i, ja:jb]
        q0 = hmap[i, ja:jb + 2]
        q1 = hmap[i + 1, ja:jb + 2]
        q2 = hmap[i + 2, ja:jb + 2]
        tt = t_row[:m]
        cand = 0
        if have_grid:
            for c in range(3):
                _coarse_row(sgrid[c], i, 2, crow, ext, srows[c])
            ax = srows[0, ja:jb]
            ay = srows[1, ja:jb]
            for t in range(m):
                gx = (q0[t + 2] + two * q1[t + 2] + q2[t + 2]) - (q0[t] + two * q1[t] + q2[t])
                gy = (q2[t] + two * q2[t + 1] + q2[t + 2]) - (q0[t] + two * q0[t + 1] + q0[t + 2])
                d1 = (c00 * gx + c01 * gy) + (rx[t] * u0 + ry[t] * u1 + rz[t] * u2) + ax[t]
                d2 = (c10 * gx + c11 * gy) + (rx[t] * v0 + ry[t] * v1 + rz[t] * v2) + ay[t]
                x = hk * (d1 * d1 + d2 * d2)
                tt[t] = x
                cand += np.int32(x < th)
        else:
            for t in range(m):
                gx = (q0[t + 2] + two * q1[t + 2] + q2[t + 2]) - (q0[t] + two * q1[t] + q2[t])   # Sobel x 16
                gy = (q2[t] + two * q2[t + 1] + q2[t + 2]) - (q0[t] + two * q0[t + 1] + q0[t + 2])
                d1 = (c00 * gx + c01 * gy) + (rx[t] * u0 + ry[t] * u1 + rz[t] * u2)
                d2 = (c10 * gx + c11 * gy) + (rx[t] * v0 + ry[t] * v1 + rz[t] * v2)
                x = hk * (d1 * d1 + d2 * d2)
                tt[t] = x
                cand += np.int32(x < th)
        sp = spec[i, ja:jb]
        for t in range(m):
            sp[t] = 0
        lit_rng[i, 0] = 0
        lit_rng[i, 1] = 0
        if cand == 0:
            continue
        first = m
        last = -1
        for t in range(m):
            if tt[t] < th:
                v = 0.0
                if have_grid:
                    wt = srows[2, ja + t]
                    if wt > 0:
                        v = math.exp(-tt[t]) * wt * min(q1[t + 1], 16.0) * (255.0 / 16.0) + 0.5
                else:
                    cs = -(rx[t] * n0 + ry[t] * n1 + rz[t] * n2)
                    if cs > 1e-3:
                        v = math.exp(-tt[t]) * w_scale * cs * cs * cs * min(q1[t + 1], 16.0) * (255.0 / 16.0) + 0.5
                if v > 0:
                    iv = min(int(v), 255)
                    sp[t] = iv
                    if iv > 0:
                        first = min(first, t)
                        last = t
        if last >= 0:
            lit = True
            lit_rng[i, 0] = ja + first
            lit_rng[i, 1] = ja + last + 1
    return lit


@njit(**_JIT)
def _spec_row(spec, y, hv, dst):
    """Row ``y`` of the half-resolution glints upsampled x2 (cv2.resize(INTER_LINEAR)) into ``dst``
    (float32, len 2 * w2); ``hv`` (float32, w2 + 2) is scratch."""
    h2, w2 = spec.shape
    if y == 0:
        i0, i1, wy = 0, 0, np.float32(0.0)
    elif y & 1:
        i0, i1, wy = y >> 1, min((y >> 1) + 1, h2 - 1), np.float32(0.25)
    else:
        i0, i1, wy = (y >> 1) - 1, y >> 1, np.float32(0.75)
    s0 = spec[i0]
    s1 = spec[i1]
    e = hv[1:w2 + 1]
    for j in range(w2):
        a = np.float32(s0[j])
        e[j] = a + wy * (np.float32(s1[j]) - a)
    hv[0] = hv[1]
    hv[w2 + 1] = hv[w2]
    for j in range(w2):
        a, b, c = hv[j], hv[j + 1], hv[j + 2]
        dst[2 * j] = np.float32(0.25) * a + np.float32(0.75) * b
        dst[2 * j + 1] = np.float32(0.75) * b + np.float32(0.25) * c


@njit(**_JIT)
def _spec_row3(spec, y, hv, srow, dst):
    """:func:`_spec_row` repeated for the 3 interleaved colour channels: ``dst`` (len 3 * 2 * w2)."""
    _spec_row(spec, y, hv, srow)
    for i in range(srow.shape[0]):
        v = srow[i]
        dst[3 * i] = v
        dst[3 * i + 1] = v
        dst[3 * i + 2] = v


@njit(**_JIT)
def _add_specular(bgr, spec, spans, hv, srow):
    """bgr += x2-upsampled glints (saturating), over the row spans (used before occluders)."""
    flat = bgr.reshape(-1)
    bw = bgr.shape[1]
    for y in range(spans.shape[0]):
        xa, xb = spans[y, 0], spans[y, 1]
        if xb <= xa:
            continue
        _spec_row(spec, y, hv, srow)
        s = srow[xa:xb]
        p = flat[3 * (y * bw + xa):3 * (y * bw + xb)]
        for i in range(xb - xa):
            for c in range(3):
                p[3 * i + c] = np.int32(min(np.float32(p[3 * i + c]) + s[i], np.float32(255.0)) + np.float32(0.5))


@njit(**_JIT)
def _finish(bgr, spec, lit_rng, use_spec, kw, aspans, alpha3, noise, noy, nox, use_noise, out, oy0, ox0,
            sring, tags, srng, colpad, hacc, srow, hv):
    """Frame = round field of view (``alpha3``, 0..255 per interleaved value) x (sensor noise +
    separable blur (kernel ``kw``) of saturate(``bgr`` + x2-upsampled glints)), written to
    ``out`` at (oy0, ox0). Works on flat interleaved rows (3 values per pixel).

    Per output row: vertical blur of the 2r + 1 source rows into ``colpad`` (value j of column
    x at 3 (r + x) + j), then horizontal blur, noise (``noise`` (bh + 32, 3 (bw + 32)) int at
    (noy, 3 nox)) and the mask. Glints (``spec``, lit columns ``lit_rng`` per half-resolution
    row) are added only where lit; their upsampled rows (x3) live in the ring ``sring`` (row ids
    in ``tags``, lit columns in ``srng``).
    """
    bh, bw = bgr.shape[0], bgr.shape[1]
    h2 = spec.shape[0]
    bflat = bgr.reshape(-1)
    r = (kw.shape[0] - 1) // 2
    nr = 2 * r + 1
    k0 = kw[0]
    k1 = kw[1] if r == 1 else np.float32(0.0)
    top = np.float32(255.0)
    zero = np.float32(0.0)
    half = np.float32(0.5)
    scale = np.float32(1.0 / 255.0)
    for d in range(nr):
        tags[d] = -1
    rows = np.empty(nr, np.int64)
    slots = np.empty(nr, np.int64)
    oflat = out.reshape(-1)
    width = out.shape[1]
    for y in range(bh):
        xa, xb = aspans[y, 0], aspans[y, 1]
        if xb <= xa:
            continue
        for d in range(nr):
            yy = min(max(y + d - r, 0), bh - 1)
            rows[d] = yy
            sl = yy % nr
            slots[d] = sl
            if use_spec and tags[sl] != yy:
                tags[sl] = yy
                i0 = max((yy - 1) >> 1, 0)               # half rows that reach full row yy
                i1 = min((yy + 1) >> 1, h2 - 1)
                a = min(lit_rng[i0, 0], lit_rng[i1, 0]) if lit_rng[i0, 1] > 0 and lit_rng[i1, 1] > 0 else \
                    (lit_rng[i0, 0] if lit_rng[i0, 1] > 0 else lit_rng[i1, 0])
                b = max(lit_rng[i0, 1], lit_rng[i1, 1])
                if b > 0:
                    _spec_row3(spec, yy, hv, srow, sring[sl])
                    srng[sl, 0] = max(2 * a - 1, 0)
                    srng[sl, 1] = min(2 * b + 1, bw)
                else:
                    srng[sl, 0] = 0
                    srng[sl, 1] = 0
        ca = max(xa - r, 0)
        cb = min(xb + r, bw)
        n = 3 * (cb - ca)
        m = 3 * (xb - xa)
        # vertical pass over columns [ca, cb)
        col = colpad[3 * (r + ca):3 * (r + cb)]
        if r == 1:
            p0 = bflat[3 * (rows[0] * bw + ca):3 * (rows[0] * bw + cb)]
            p1 = bflat[3 * (rows[1] * bw + ca):3 * (rows[1] * bw + cb)]
            p2 = bflat[3 * (rows[2] * bw + ca):3 * (rows[2] * bw + cb)]
            for i in range(n):
                col[i] = k0 * (np.float32(p0[i]) + np.float32(p2[i])) + k1 * np.float32(p1[i])
        else:
            for i in range(n):
                col[i] = zero
            for d in range(nr):
                p = bflat[3 * (rows[d] * bw + ca):3 * (rows[d] * bw + cb)]
                kd = kw[d]
                for i in range(n):
                    col[i] += kd * np.float32(p[i])
        if use_spec:                                    # glints, where lit: saturate(value + glint)
            for d in range(nr):
                sl = slots[d]
                g0 = max(srng[sl, 0], ca)
                g1 = min(srng[sl, 1], cb)
                if g1 <= g0:
                    continue
                kd = kw[d]
                p = bflat[3 * (rows[d] * bw + g0):3 * (rows[d] * bw + g1)]
                sd = sring[sl, 3 * g0:3 * g1]
                cd = colpad[3 * (r + g0):3 * (r + g1)]
                for i in range(3 * (g1 - g0)):
                    v = np.float32(p[i])
                    cd[i] += kd * (min(v + sd[i], top) - v)
        for x in range(xa - r, ca):                     # clipped at the buffer edge: replicate
            for c in range(3):
                colpad[3 * (r + x) + c] = colpad[3 * (r + ca) + c]
        for x in range(cb, xb + r):
            for c in range(3):
                colpad[3 * (r + x) + c] = colpad[3 * (r + cb - 1) + c]
        # horizontal pass + noise + field of view, straight into the frame
        nz = noise[y + noy, 3 * (xa + nox):3 * (xb + nox)] if use_noise else noise[0, :m]
        base = ((oy0 + y) * width + ox0 + xa) * 3
        dst = oflat[base:base + m]
        h = hacc[:m]
        if r == 1:
            q0 = colpad[3 * xa:3 * xb]
            q1 = colpad[3 * xa + 3:3 * xb + 3]
            q2 = colpad[3 * xa + 6:3 * xb + 6]
            for i in range(m):
                h[i] = k0 * (q0[i] + q2[i]) + k1 * q1[i] + np.float32(nz[i])
        else:
            for i in range(m):
                h[i] = np.float32(nz[i])
            for e in range(nr):
                qe = colpad[3 * (xa + e):3 * (xb + e)]
                ke = kw[e]
                for i in range(m):
                    h[i] += ke * qe[i]
        al = alpha3[y, 3 * xa:3 * xb]
        for i in range(m):
            dst[i] = min(max(h[i], zero), top) * (np.float32(al[i]) * scale) + half


@njit(**_JIT)
def _mat3(a, b, ta, out):
    """out = a @ b (or a.T @ b if ``ta``) for 3x3 ``a`` and ``b`` (plain loops: no BLAS needed)."""
    for i in range(3):
        for j in range(3):
            acc = 0.0
            for k in range(3):
                acc += (a[k, i] if ta else a[i, k]) * b[k, j]
            out[i, j] = acc


@njit(**_JIT)
def _rot_log(r, out):
    """out = rotation vector (axis * angle) of the 3x3 rotation ``r``; False if the angle is
    90 deg or more (towards 180 deg ill-conditioned; the caller takes the general path)."""
    vx, vy, vz = r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]     # 2 sin(angle) axis
    n = math.sqrt(vx * vx + vy * vy + vz * vz)
    th = math.atan2(0.5 * n, 0.5 * (r[0, 0] + r[1, 1] + r[2, 2] - 1.0))
    k = 0.5 if n < 1e-12 else th / n
    out[0], out[1], out[2] = vx * k, vy * k, vz * k
    return th < 0.5 * math.pi


@njit(**_JIT)
def _rot_exp(rv, f, out):
    """out = the rotation of rotation vector f * ``rv`` (Rodrigues' formula)."""
    th = f * math.sqrt(rv[0] * rv[0] + rv[1] * rv[1] + rv[2] * rv[2])
    for i in range(3):
        for j in range(3):
            out[i, j] = 1.0 if i == j else 0.0
    if th == 0.0:
        return
    n = th / f
    kx, ky, kz = rv[0] / n, rv[1] / n, rv[2] / n
    s, c1 = math.sin(th), 1.0 - math.cos(th)
    k = np.array([[0.0, -kz, ky], [kz, 0.0, -kx], [-ky, kx, 0.0]])
    for i in range(3):
        for j in range(3):
            kk = k[i, 0] * k[0, j] + k[i, 1] * k[1, j] + k[i, 2] * k[2, j]
            out[i, j] += s * k[i, j] + c1 * kk


@njit(**_JIT)
def _subpose_homs(cp0, cp1, tp0, tp1, fractions, tex0, out):
    """out[k] = normalised ray -> level-0 texel homography (3x3) at the sub-pose a fraction
    ``fractions[k]`` through the exposure (camera and target poses interpolated like
    :func:`interpolate_pose`; rigid poses); ``tex0``: plane metres -> level-0 texels.
    Returns False (``out`` unusable) if a rotation over the exposure is too close to pi."""
    m = np.empty((3, 3))
    rvc = np.empty(3)
    rvt = np.empty(3)
    _mat3(cp0, cp1, True, m)
    ok = _rot_log(m, rvc)
    _mat3(tp0, tp1, True, m)
    if not (_rot_log(m, rvt) and ok):
        return False
    e = np.empty((3, 3))
    rc = np.empty((3, 3))
    rt = np.empty((3, 3))
    rot = np.empty((3, 3))
    hn = np.empty((3, 3))
    for k in range(fractions.shape[0]):
        f = fractions[k]
        _rot_exp(rvc, f, e)
        _mat3(cp0, e, False, rc)
        _rot_exp(rvt, f, e)
        _mat3(tp0, e, False, rt)
        _mat3(rc, rt, True, rot)                               # the plane in the camera frame
        for i in range(3):
            t = 0.0
            for j in range(3):
                t += rc[j, i] * ((1.0 - f) * (tp0[j, 3] - cp0[j, 3]) + f * (tp1[j, 3] - cp1[j, 3]))
            hn[i, 0] = rot[i, 0]
            hn[i, 1] = rot[i, 1]
            hn[i, 2] = t
        # inverse of hn by the adjugate
        a, b, c = hn[0, 0], hn[0, 1], hn[0, 2]
        d, g, h = hn[1, 0], hn[1, 1], hn[1, 2]
        p, q, r = hn[2, 0], hn[2, 1], hn[2, 2]
        det = a * (g * r - h * q) - b * (d * r - h * p) + c * (d * q - g * p)
        inv = np.empty((3, 3))
        inv[0, 0], inv[0, 1], inv[0, 2] = (g * r - h * q) / det, (c * q - b * r) / det, (b * h - c * g) / det
        inv[1, 0], inv[1, 1], inv[1, 2] = (h * p - d * r) / det, (a * r - c * p) / det, (c * d - a * h) / det
        inv[2, 0], inv[2, 1], inv[2, 2] = (d * q - g * p) / det, (b * p - a * q) / det, (a * g - b * d) / det
        _mat3(tex0, inv, False, out[k])
    return True


@njit(**_JIT)
def _surface_grid(rays, spans, rot, org, lut_w, lut_d, r_step, lx, ly, aff, out, shade, sgrid, e_ref, amb, inv_gamma,
                  shade_max, w_glint):
    """Intersect the unit rays of the coarse grid (``rays`` (3, ch, cw), camera frame) over the
    row ``spans`` with the surface z = w(x, y) of the target frame, w a radial profile around
    (lx, ly) tabulated at r = k ``r_step`` (``lut_w``, ``lut_d`` = dw/dr; m), by Newton's method
    along each ray (bracketed: it always converges), started from the neighbour's solution; ``rot``: camera ->
    target rotation, ``org``: the camera in the target frame (m). ``out`` (2, ch, cw): level texel
    coordinates u = aff[0] x + aff[1], v = aff[2] y + aff[3] (-1e9, the border, where the ray
    misses). If ``shade`` has rows, also the diffuse shade there (as :func:`_light_grid`: ambient +
    (e_ref cos / distance^2)^(1/gamma), cos between ray and surface normal) and ``sgrid`` (3, ch,
    cw): the surface slope along the texture axes (sign: as the view tilt in :func:`_specular_half`)
    and the glint weight ``w_glint`` x irradiance. Returns the largest glint weight."""
    nl = lut_w.shape[0] - 1
    inv_step = 1.0 / r_step
    with_shade = shade.shape[0] > 0
    sigma = 1.0 if org[2] < 0 else -1.0                  # the camera on the plane's -z side: normal -z
    w_far = lut_w.max() + 1e-3 if sigma > 0 else lut_w.min() - 1e-3
    wmax = 0.0
    for j in range(out.shape[1]):
        s_prev = -1.0
        for i in range(spans[j, 0], spans[j, 1]):
            rx, ry, rz = rays[0, j, i], rays[1, j, i], rays[2, j, i]
            dx = rot[0, 0] * rx + rot[0, 1] * ry + rot[0, 2] * rz
            dy = rot[1, 0] * rx + rot[1, 1] * ry + rot[1, 2] * rz
            dz = rot[2, 0] * rx + rot[2, 1] * ry + rot[2, 2] * rz
            # G(s) = sigma (z - w) along the ray: < 0 at the camera, > 0 past the deepest surface
            # point (w_far); Newton's method, kept inside that bracket by bisection.
            ok = False
            x = y = r = dw = 0.0
            if sigma * dz > 1e-9:
                lo = 0.0
                hi = (w_far - org[2]) / dz
                s = s_prev if lo < s_prev < hi else min(max(-org[2] / dz, 0.0), hi)   # neighbour / plane
                for _ in range(60):
                    x = org[0] + s * dx - lx
                    y = org[1] + s * dy - ly
                    r = math.sqrt(x * x + y * y)
                    tk = min(r * inv_step, nl - 1e-6)
                    k = int(tk)
                    f = tk - k
                    w = lut_w[k] + (lut_w[k + 1] - lut_w[k]) * f
                    dw = lut_d[k] + (lut_d[k + 1] - lut_d[k]) * f
                    g = sigma * (org[2] + s * dz - w)
                    gp = sigma * (dz - dw * (x * dx + y * dy) / max(r, 1e-12))
                    if g < 0.0:
                        lo = s
                    else:
                        hi = s
                    sn = s - g / gp if gp > 0.0 else lo - 1.0
                    if not lo < sn < hi:
                        sn = 0.5 * (lo + hi)
                    done = abs(sn - s) < 1e-7 or hi - lo < 1e-7
                    s = sn
                    if done:
                        ok = True
                        break
            if not ok:
                out[0, j, i] = -1e9
                out[1, j, i] = -1e9
                s_prev = -1.0
                if with_shade:
                    shade[j, i] = 0.0
                    sgrid[0, j, i] = 0.0
                    sgrid[1, j, i] = 0.0
                    sgrid[2, j, i] = 0.0
                continue
            s_prev = s
            out[0, j, i] = aff[0] * (org[0] + s * dx) + aff[1]
            out[1, j, i] = aff[2] * (org[1] + s * dy) + aff[3]
            if with_shade:
                rr = max(r, 1e-12)
                wx = dw * x / rr
                wy = dw * y / rr
                cs = sigma * (dz - dx * wx - dy * wy) / math.sqrt(1.0 + wx * wx + wy * wy)
                wgt = 0.0
                if cs > 1e-3:
                    e = e_ref * cs / (s * s)
                    shade[j, i] = math.floor(min(amb + e ** inv_gamma, shade_max) * 128.0) / 128.0
                    wgt = w_glint * e
                else:
                    shade[j, i] = 0.0
                sgrid[0, j, i] = sigma * wx
                sgrid[1, j, i] = sigma * wy
                sgrid[2, j, i] = wgt
                wmax = max(wmax, wgt)
    return wmax


def _spans(mask: np.ndarray) -> np.ndarray:
    """Per row: [first, last + 1) of the set pixels of a row-convex ``mask`` ((0, 0) for empty rows)."""
    out = np.zeros((mask.shape[0], 2), np.int64)
    rows = mask.any(axis=1)
    out[rows, 0] = np.argmax(mask, axis=1)[rows]
    out[rows, 1] = mask.shape[1] - np.argmax(mask[:, ::-1], axis=1)[rows]
    return out


def _widen(mask: np.ndarray, step: int = 16) -> np.ndarray:
    """Row-convex ``mask`` with each row's span widened to multiples of ``step`` pixels."""
    out = np.zeros_like(mask)
    w = mask.shape[1]
    for y, (a, b) in enumerate(_spans(mask)):
        if b > a:
            out[y, a // step * step:min(w, -(-b // step) * step)] = True
    return out


def _dilate(mask: np.ndarray, r: int) -> np.ndarray:
    if r <= 0:
        return mask
    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)) > 0


def _blur_kernel(sigma: float) -> np.ndarray:
    """Gaussian kernel of the optics' blur (float32, sum 1): the size cv2.GaussianBlur had, the
    weights in 1/256 as its 8-bit path uses them; [1] without blur."""
    if sigma <= 0:
        return np.ones(1, np.float32)
    k = 3 if sigma <= 0.8 else 2 * int(math.ceil(3 * sigma)) + 1
    kw = np.round(cv2.getGaussianKernel(k, sigma).ravel() * 256).astype(np.int32)
    kw[k // 2] += 256 - int(kw.sum())
    return (kw / 256.0).astype(np.float32)


def _gradient_rms(height: np.ndarray, rows: int = 256) -> float:
    """RMS of the 3x3 Sobel gradient (divided by 8: height units per texel) of a uint8 height map (H, W).

    Summed exactly on integers, a strip of ``rows`` rows at a time, and rounded as a float32 mean: the
    whole-image float32 version allocated ~300 MB for the closed loop's 4096² texture and took 0.2-1 s of
    every renderer's setup (a fifth of a 20-s run with vision); this takes ~0.05 s and gives the same value
    (to the float32 rounding of that version's sum)."""
    n = height.shape[0]
    total = 0
    for r0 in range(0, n, rows):
        a, b = max(r0 - 1, 0), min(r0 + rows + 1, n)          # one row of context each side, as on the whole image
        strip = np.ascontiguousarray(height[a:b])
        lo = r0 - a
        for dx, dy in ((1, 0), (0, 1)):
            g = cv2.Sobel(strip, cv2.CV_16S, dx, dy, ksize=3)[lo:lo + min(rows, n - r0)].astype(np.int64)
            total += int(np.sum(g * g))
    return float(np.sqrt(np.float32(total / (64.0 * height.size))))


class Renderer:
    """Renders endoscope frames of a :class:`PlanarTarget` (see the module docstring).

    ``cam``: intrinsics and distortion (use :func:`endoscope_camera` for the usual distorted
    camera); ``settings``: :class:`RenderSettings`; ``target``: the textured plane (default:
    procedural mucosa from ``seed``, 0.2 m x 0.2 m); ``seed``: sensor noise (and default texture);
    ``surface``: the tissue's shape (default the plane; ``kind = "folds"``: the texture lies on a
    lumen with folds that deforms with ``render(time_s=)``, see :class:`SurfaceParams`).

    A renderer owns preallocated work buffers: use one renderer per thread.
    """

    _Q = 4  # lighting is evaluated on a grid this many times coarser than the image
    _MB = 16  # margin (px) of the mid-exposure image: largest image-space motion blur displacement
    _TILE = (16, 64)  # rows, columns of the tiles with one motion-blur displacement
    _IMAGE_BLUR_MIN = 3  # sub-poses from which motion blur shifts the mid-exposure image (fewer: texture)
    _LUT = 4096  # entries of the cos^(3/gamma) table

    def __init__(self, cam: CameraParams, settings: RenderSettings | None = None,
                 target: PlanarTarget | None = None, *, seed: int = 0, surface: SurfaceParams | None = None) -> None:
        self.cam = validate(cam)
        self.settings = validate(settings or RenderSettings())
        self.surface = validate(surface or SurfaceParams())
        self._rng = np.random.default_rng(seed)
        self._build_maps()
        self._build_noise()
        self.set_target(target if target is not None else
                        PlanarTarget.mucosa(seed=seed, texture_px=self.settings.texture_px))

    # ------------------------------------------------------------------ setup
    def _build_maps(self) -> None:
        cam, s, q = self.cam, self.settings, self._Q
        r = s.fov_radius_px
        x0 = max(0, int(math.floor(cam.cx - r - 2)))
        y0 = max(0, int(math.floor(cam.cy - r - 2)))
        x1 = min(cam.width, int(math.ceil(cam.cx + r + 3)))
        y1 = min(cam.height, int(math.ceil(cam.cy + r + 3)))
        x0 = max(0, x1 - (x1 - x0 + q - 1) // q * q)  # box sides: multiples of q
        y0 = max(0, y1 - (y1 - y0 + q - 1) // q * q)
        if (x1 - x0) % q or (y1 - y0) % q:
            raise ValueError("image too small for the field of view")
        self._box = (x0, y0, x1, y1)
        bw, bh = x1 - x0, y1 - y0
        distorted = bool(cam.k1 or cam.k2)

        mg = self._MB
        if distorted:
            # Rays are exact up to the corners of the box + margin where the distortion is
            # invertible there, else up to the field of view + 4 px (beyond: clamped, masked anyway).
            corner = max(math.hypot(u - cam.cx, v - cam.cy) for u in (x0 - mg, x1 + mg) for v in (y0 - mg, y1 + mg))
            rfar = _undistort_radius(np.array([corner / min(cam.fx, cam.fy)]), cam.k1, cam.k2)[0]
            g = np.linspace(0, rfar, 512)
            ok = rfar > 0 and bool(np.all(1 + 3 * cam.k1 * g ** 2 + 5 * cam.k2 * g ** 4 > 0))
            rlim = corner + 1 if ok else r + 4

        def rays(us: np.ndarray, vs: np.ndarray) -> np.ndarray:
            """Undistorted normalised coordinates (..., 2) of distorted pixel grids."""
            xd, yd = (us - cam.cx) / cam.fx, (vs - cam.cy) / cam.fy
            rd = np.hypot(xd, yd)
            if distorted:
                rmax = rlim / min(cam.fx, cam.fy)
                rc = np.minimum(rd, rmax)
                ru = _undistort_radius(rc, cam.k1, cam.k2)
                ru_grid = np.linspace(0, float(_undistort_radius(np.array([(r + 4) / min(cam.fx, cam.fy)]),
                                                                 cam.k1, cam.k2)[0]), 512)
                slope = 1 + 3 * cam.k1 * ru_grid ** 2 + 5 * cam.k2 * ru_grid ** 4
                if np.any(slope <= 0):
                    raise ValueError(f"distortion k1={cam.k1}, k2={cam.k2} is not invertible inside the "
                                     f"field of view ({r} px); reduce fov_radius_px or the distortion")
                f = np.where(rd > 1e-12, ru / np.maximum(rd, 1e-12), 1.0)
                f = np.where(rd > rmax, ru / np.maximum(rc, 1e-12), f)  # outside the circle: masked anyway
                xd, yd = xd * f, yd * f
            return np.stack([xd, yd], axis=-1)

        if distorted:          # undistorted rays of the pixels of the box + motion-blur margin
            vs_e, us_e = np.mgrid[y0 - mg:y1 + mg, x0 - mg:x1 + mg].astype(np.float64)
            xy = rays(us_e, vs_e).astype(np.float32)
            self._rx_map, self._ry_map = np.ascontiguousarray(xy[..., 0]), np.ascontiguousarray(xy[..., 1])
        else:                                                       # affine: computed in the kernel
            self._rx_map = self._ry_map = np.empty((0, 0), np.float32)
        self._ray0 = np.array([(x0 - cam.cx) / cam.fx, (y0 - cam.cy) / cam.fy, 1.0 / cam.fx, 1.0 / cam.fy])
        self._ray0_ext = np.array([(x0 - mg - cam.cx) / cam.fx, (y0 - mg - cam.cy) / cam.fy,
                                   1.0 / cam.fx, 1.0 / cam.fy])
        self._cam6 = np.array([cam.fx, cam.fy, cam.cx - (x0 - mg), cam.cy - (y0 - mg), cam.k1, cam.k2])
        vs, us = np.mgrid[y0:y1, x0:x1].astype(np.float64)
        # Coarse grid: cell (j, i) sits at full-res (q j + (q-1)/2), as cv2.resize(INTER_LINEAR) aligns.
        off = (q - 1) / 2
        vs_c, us_c = np.mgrid[0:bh // q, 0:bw // q].astype(np.float64)
        xy_c = rays(x0 + q * us_c + off, y0 + q * vs_c + off)
        v = np.concatenate([xy_c, np.ones(xy_c.shape[:2] + (1,))], axis=-1)
        self._rays_c = np.ascontiguousarray((v / np.linalg.norm(v, axis=-1, keepdims=True)).transpose(2, 0, 1),
                                            dtype=np.float32)           # unit rays, planar (3, ch, cw)
        # Half-resolution grid (pixel (j, i) at full-res 2 j + 1/2): unit rays, planar (3, h2, w2).
        vs_h, us_h = np.mgrid[0:bh // 2, 0:bw // 2].astype(np.float64)
        xy_h = rays(x0 + 2 * us_h + 0.5, y0 + 2 * vs_h + 0.5)
        v = np.concatenate([xy_h, np.ones(xy_h.shape[:2] + (1,))], axis=-1)
        self._rays_h = np.ascontiguousarray((v / np.linalg.norm(v, axis=-1, keepdims=True)).transpose(2, 0, 1),
                                            dtype=np.float32)
        # Field-of-view mask (soft edge).
        dist = np.hypot(us - cam.cx, vs - cam.cy)
        if s.fov_edge_px > 0:
            alpha = np.clip(0.5 + (r - dist) / s.fov_edge_px, 0.0, 1.0)
        else:
            alpha = (dist <= r).astype(float)
        self._alpha8 = np.round(alpha * 255).astype(np.uint8)
        self._bbox_shape = (bh, bw)
        # Pixel regions (row spans): A the visible disc, B = A +- blur radius (rows that get
        # blurred), S the half-resolution glints B needs, H the averaged heights S needs, P all
        # pixels the sampling pass must fill.
        self._kw = _blur_kernel(s.optical_blur_px)
        rb = (len(self._kw) - 1) // 2
        # Spans are widened to multiples of 16 pixels (whole vectors, no scalar loop remainders).
        a_mask = _widen(self._alpha8 > 0)
        b_mask = _widen(_dilate(a_mask, rb))
        s_mask = _widen(_dilate(b_mask, 3).reshape(bh // 2, 2, bw // 2, 2).any(axis=(1, 3)))
        h_mask = _widen(_dilate(s_mask, 1))
        p_mask = _widen(_dilate(b_mask, rb) | np.repeat(np.repeat(h_mask, 2, axis=0), 2, axis=1))
        self._aspans, self._bspans = _spans(a_mask), _spans(b_mask)
        self._sspans, self._hspans, self._pspans = _spans(s_mask), _spans(h_mask), _spans(p_mask)
        # Work buffers, reused by every frame.
        ch, cw, h2, w2 = bh // q, bw // q, bh // 2, bw // 2
        f32, i32 = np.float32, np.int32
        self._bgr = np.zeros((bh, bw, 3), np.uint8)                   # shaded image (interleaved)
        self._hplane = np.zeros((bh, bw), np.uint8)                   # sampled height
        we = bw + 2 * mg
        self._scratch = dict(rxs=np.zeros(we, f32), rys=np.zeros(we, f32), fus=np.zeros(we + 16, i32),
                             fvs=np.zeros(we + 16, i32), acc=np.zeros((4, we + 16), i32),
                             srow=np.zeros(we, f32), crow=np.zeros(cw, f32), ext=np.zeros(cw + 2, f32))
        self._blur_acc = np.zeros(4 * bw, f32)
        self._shifts = np.zeros((s.max_subframes, -(-bh // self._TILE[0]), -(-bw // self._TILE[1]), 2))
        self._mid = np.zeros((bh + 2 * mg, we, 4), f32)               # mid-exposure image + margin
        self._pspans_ext = np.zeros((bh + 2 * mg, 2), np.int64)
        self._pspans_ext[mg:mg + bh] = self._pspans + mg
        self._espans = np.zeros_like(self._pspans_ext)
        self._espans_full = np.zeros_like(self._pspans_ext)
        self._region_cache: dict[tuple, tuple] = {}
        self._iota = np.arange(we + 16, dtype=f32)
        rp = 0.7 * r                          # where _image_motion_px looks (normalised rays)
        px = np.array([[0, 0], [rp, 0], [-rp, 0], [0, rp], [0, -rp]], float) + [cam.cx, cam.cy]
        self._motion_probes = np.column_stack([(px[:, 0] - cam.cx) / cam.fx, (px[:, 1] - cam.cy) / cam.fy,
                                               np.ones(len(px))])
        self._shade_c = np.zeros((ch, cw), f32)
        self._cs_row = np.zeros(cw, f32)
        # coarse cells the upsampled shade of P reads (+1 cell)
        c_mask = _dilate(_dilate(p_mask, q).reshape(ch, q, cw, q).any(axis=(1, 3)), 1)
        self._cspans = _spans(c_mask)
        self._hmap = np.zeros((h2 + 2, w2 + 2), f32)
        self._t_row = np.zeros(w2, f32)
        self._spec = np.zeros((h2, w2), np.uint8)
        nr = len(self._kw)
        self._sring = np.zeros((nr, 3 * bw), f32)
        self._tags = np.zeros(nr, np.int64)
        self._srng = np.zeros((nr, 2), np.int64)
        self._lit_rng = np.zeros((h2, 2), np.int64)
        self._colpad = np.zeros(3 * (bw + 2 * rb), f32)
        self._srow_f = np.zeros(bw, f32)
        self._hv = np.zeros(w2 + 2, f32)
        self._hacc = np.zeros(3 * bw, f32)
        self._alpha3 = np.repeat(self._alpha8, 3, axis=1)              # (bh, 3 bw): per interleaved value
        self._zero_noise = np.zeros((1, 3 * bw), np.int8)
        g = np.linspace(0.0, 1.0, self._LUT + 1)
        self._cos_lut = g ** (3.0 / s.gamma)                        # cos^3 irradiance -> display gamma
        # Surfaces that are not planes: texel coordinates per sub-pose, glint slopes and weights on
        # the coarse grid (allocated here, small); the empty ones stand for "none" in the kernels.
        self._grids = np.zeros((s.max_subframes, 2, ch, cw), f32)
        self._grid_mid = np.zeros((2, ch, cw), f32)
        self._sgrid = np.zeros((3, ch, cw), f32)
        self._srows = np.zeros((3, w2), f32)
        self._scratch["grow"] = np.zeros((2, bw), f32)
        self._no_grids = np.zeros((0, 2, 1, 1), f32)
        self._no_sgrid = np.zeros((0, 1, 1), f32)
        self._no_shade = np.zeros((0, 1), f32)

    def _region_spans(self, region: Sequence[float] | None) -> tuple[np.ndarray, ...]:
        """Row spans (A, B, S, H, P, P on the motion-blur margin's rows and C, see :meth:`_build_maps`)
        restricted to what the pixels of ``region`` (x0, y0, x1, y1 image px) depend on: each
        region is the previous one's grown by the reach of the step that reads it (blur radius,
        half resolution, Sobel), with a few pixels to spare; outside them the buffers keep stale
        values nobody reads. None: the whole field of view."""
        if region is None:
            return (self._aspans, self._bspans, self._sspans, self._hspans, self._pspans, self._pspans_ext,
                    self._cspans)
        x0, y0, x1, y1 = (float(v) for v in region)
        if not all(map(math.isfinite, (x0, y0, x1, y1))):
            raise ValueError(f"region = {tuple(region)}; needs 4 finite pixel coordinates (x0, y0, x1, y1)")
        # Widened to multiples of 16 px: whole vectors, and a moving region's spans repeat (cached).
        key = (math.floor(x0 / 16), math.floor(y0 / 16), math.ceil(x1 / 16), math.ceil(y1 / 16))
        got = self._region_cache.get(key)
        if got is None:
            if len(self._region_cache) >= 256:
                self._region_cache.clear()
            got = self._region_cache[key] = self._clip_spans(*(16 * k for k in key))
        return got

    def _clip_spans(self, x0: int, y0: int, x1: int, y1: int) -> tuple[np.ndarray, ...]:
        """:meth:`_region_spans` of the region (x0, y0, x1, y1) (image px)."""
        bx, by = self._box[:2]
        rb = (len(self._kw) - 1) // 2

        def clip(spans: np.ndarray, rect: tuple[int, int, int, int], step: int) -> tuple[np.ndarray, tuple]:
            """``spans`` inside ``rect`` (x0, y0, x1, y1; columns widened to multiples of ``step``),
            and that rect."""
            xa, ya, xb, yb = rect
            xa, xb = xa // step * step, -(-xb // step) * step
            out = np.zeros_like(spans)
            ya, yb = max(ya, 0), min(yb, len(spans))
            if yb > ya:
                a = np.maximum(spans[ya:yb, 0], xa)
                b = np.minimum(spans[ya:yb, 1], xb)
                ok = b > a
                out[ya:yb, 0] = np.where(ok, a, 0)
                out[ya:yb, 1] = np.where(ok, b, 0)
            return out, (xa, ya, xb, yb)

        def grow(r: tuple, g: int, k: int = 1) -> tuple[int, int, int, int]:
            """``r`` grown by ``g`` px, then k x smaller (outwards)."""
            return ((r[0] - g) // k, (r[1] - g) // k, -(-(r[2] + g) // k), -(-(r[3] + g) // k))

        # A: the region (whole vectors); B: + blur radius; S (half resolution): what the glints
        # upsampled x2 and blurred at A read; H (half resolution): + 1 for the Sobel; P: all of B
        # + blur radius and of H at full resolution.
        A, ra = clip(self._aspans, (x0 - bx, y0 - by, x1 - bx, y1 - by), 16)
        B, rb_ = clip(self._bspans, grow(ra, rb), 16)
        S, rs = clip(self._sspans, grow(ra, rb + 3, 2), 1)     # (tight: P, the costly pass, covers H)
        H, rh = clip(self._hspans, grow(rs, 1), 1)
        P, rp = clip(self._pspans, (min(rb_[0] - rb, 2 * rh[0]), min(rb_[1] - rb, 2 * rh[1]),
                                   max(rb_[2] + rb, 2 * rh[2]), max(rb_[3] + rb, 2 * rh[3])), 16)
        mg = self._MB
        PE = np.zeros_like(self._pspans_ext)
        PE[mg:mg + len(P)] = P + mg
        # C (coarse grid): the shade cells P + the motion-blur margin upsample from.
        C, _ = clip(self._cspans, grow(grow(rp, mg + self._Q, self._Q), 1), 1)
        return A, B, S, H, P, PE, C

    def _build_noise(self) -> None:
        """A small bank of seeded noise images; each frame takes a random window of one of them."""
        bh, bw = self._bbox_shape
        sig = self.settings.noise_sigma
        self._noise = []
        if sig <= 0:
            return
        for _ in range(3):
            n = np.clip(np.round(self._rng.normal(0.0, sig, (bh + 32, bw + 32, 3))), -255, 255)
            n = n.reshape(bh + 32, 3 * (bw + 32))                        # flat interleaved rows
            self._noise.append(n.astype(np.int8 if np.abs(n).max() <= 127 else np.int16))

    def reseed(self, seed) -> None:
        """Restart the sensor-noise random stream from ``seed`` (int or sequence of ints)."""
        self._rng = np.random.default_rng(seed)

    def set_target(self, target: PlanarTarget) -> None:
        """Use ``target`` from now on; builds its texture pyramid (mip levels) once."""
        tex = target.texture
        levels = [np.ascontiguousarray(tex)]
        if self.settings.mipmap:
            while min(levels[-1].shape[:2]) >= 64:
                levels.append(cv2.pyrDown(levels[-1]))
        self.target = target
        self._levels = levels
        # A surface's radial profile is tabulated out to the farthest texture corner (+ 5 cm).
        off = self.surface.lumen_offset
        r_max = math.hypot(target.size_m[0] / 2 + abs(off[0]), target.size_m[1] / 2 + abs(off[1])) + 0.05
        self._lut_r = np.linspace(0.0, r_max, self._LUT_R + 1)
        self._lut_step = r_max / self._LUT_R
        self._lut_key: tuple | None = None
        self._padded: dict[int, tuple] = {}                          # built on first use
        rms = _gradient_rms(tex[..., 3])  # height units per texel
        # slope (rad) = bump_slope * (grad h per level-0 texel) / rms
        self._slope_per_grad = self.settings.bump_slope / rms if rms > 1e-6 else 0.0
        bg = tuple(int(c) for c in self.settings.background_bgr)
        self._border = (bg[0], bg[1], bg[2], 128)

    def _padded_level(self, level: int) -> tuple:
        """Texture level ``level`` padded with _PAD texels of the border colour (+ 1 on the right),
        as the kernels read it: (bytes, row pitch in bytes, height, width). Built on first use."""
        got = self._padded.get(level)
        if got is None:
            lv = self._levels[level]
            p = cv2.copyMakeBorder(lv, _PAD, _PAD, _PAD, _PAD + 1, cv2.BORDER_CONSTANT, value=self._border)
            got = (p.reshape(-1), 4 * p.shape[1], lv.shape[0], lv.shape[1])
            self._padded[level] = got
        return got

    # --------------------------------------------------------------- geometry
    def _plane_in_camera(self, camera_pose: np.ndarray, target_pose: np.ndarray) -> np.ndarray:
        return np.linalg.solve(np.asarray(camera_pose, float), np.asarray(target_pose, float))

    def _texel_from_plane(self, level: int) -> np.ndarray:
        """3x3: homogeneous plane metres -> level-``level`` texel coordinates.

        Level 0 has texel centres at integers; cv2.pyrDown centres level-l texel j on level-0
        coordinate 2^l j, so level-l coordinates are level-0 coordinates / 2^l.
        """
        h, w = self.target.texture.shape[:2]
        sw, sh = self.target.size_m
        k = 0.5 ** level
        return np.array([[k * w / sw, 0.0, k * (w / 2 - 0.5)], [0.0, k * h / sh, k * (h / 2 - 0.5)], [0.0, 0.0, 1.0]])

    def truth(self, camera_pose: np.ndarray, target_pose: np.ndarray,
              point_m: Sequence[float] | None = None, time_s: float = 0.0) -> np.ndarray:
        """Pixel position (x, y; with distortion) of a plane point (default: the selected point), on
        the surface as it is at ``time_s`` (s)."""
        p = self.target.selected_point_m if point_m is None else point_m
        w = 0.0 if self.surface.flat else float(self.surface.height(p[0], p[1], time_s))
        world = np.asarray(target_pose, float) @ np.array([p[0], p[1], w, 1.0])
        return project(world_to_camera(np.asarray(camera_pose, float), world[:3]), self.cam)

    def _texel_homography(self, rel: np.ndarray, level: int) -> np.ndarray:
        """3x3: undistorted normalised image coordinates -> level-``level`` texel coordinates."""
        hn = np.column_stack([rel[:3, 0], rel[:3, 1], rel[:3, 3]])  # plane (x, y, 1) -> normalised
        return self._texel_from_plane(level) @ np.linalg.inv(hn)

    def _subpose_homographies(self, cp0: np.ndarray, cp1: np.ndarray, tp0: np.ndarray, tp1: np.ndarray,
                              fractions: np.ndarray) -> np.ndarray:
        """(n, 3, 3) normalised ray -> level-0 texel homographies at the sub-poses a fraction of
        the way through the exposure (:func:`interpolate_pose` of camera and target)."""
        f = np.ascontiguousarray(fractions, dtype=float)
        out = np.empty((len(f), 3, 3))
        if _subpose_homs(np.ascontiguousarray(cp0), np.ascontiguousarray(cp1), np.ascontiguousarray(tp0),
                         np.ascontiguousarray(tp1), f, self._texel_from_plane(0), out):
            return out
        for k, fk in enumerate(f):                      # rotations near pi: the general path
            rel = self._plane_in_camera(interpolate_pose(cp0, cp1, fk), interpolate_pose(tp0, tp1, fk))
            out[k] = self._texel_homography(rel, 0)
        return out

    _LUT_R = 4096  # entries of a surface's radial profile table

    def _surface_args(self, rel: np.ndarray, time_s: float, level: int, spans: np.ndarray) -> tuple:
        """The first arguments of :func:`_surface_grid` for the target seen at ``rel`` (target in
        camera, 4x4) at scene time ``time_s``, in level-``level`` texels, over the coarse ``spans``."""
        surf = self.surface
        key = float(time_s)
        if self._lut_key != key:                  # the profile at this time (shared by the sub-poses)
            w, d = surf.profile(self._lut_r, time_s)
            self._lut = (np.ascontiguousarray(w), np.ascontiguousarray(d))
            self._lut_key = key
        tex = self._texel_from_plane(level)
        aff = np.array([tex[0, 0], tex[0, 2], tex[1, 1], tex[1, 2]])
        rot = np.ascontiguousarray(rel[:3, :3].T)
        org = -rot @ rel[:3, 3]
        return (self._rays_c, spans, rot, org, self._lut[0], self._lut[1], self._lut_step,
                float(surf.lumen_offset[0]), float(surf.lumen_offset[1]), aff)

    def _centre_jacobian(self, hom0: np.ndarray) -> np.ndarray:
        """2x2 d(level-0 texel) / d(pixel) at the image centre (one-pixel differences) from the
        normalised-ray -> level-0 texel homography ``hom0``."""
        d = 1.0 / self.cam.fx
        t = np.array([[0.0, 0.0, 1.0], [d, 0.0, 1.0], [0.0, d * self.cam.fx / self.cam.fy, 1.0]]) @ hom0.T
        t = t[:, :2] / t[:, 2:3]
        return np.column_stack([t[1] - t[0], t[2] - t[0]])

    def _image_motion_px(self, rel0: np.ndarray, rel1: np.ndarray) -> float:
        """Largest image motion (px) of plane points seen at five places in the field of view."""
        n = self._motion_probes
        cols = [0, 1, 3]
        try:      # q = n (H1 H0^-1)^T with H = the plane's (x, y, 1) -> ray homography
            q = n @ np.linalg.solve(rel0[:3, cols].T, rel1[:3, cols].T)
        except np.linalg.LinAlgError:
            return float("inf")
        w = q[:, 2]
        if not np.all(np.abs(w) > 1e-300):
            return float("inf")
        d = np.hypot(q[:, 0] / w - n[:, 0], q[:, 1] / w - n[:, 1]) * self.cam.fx
        return float(d.max()) if np.all(np.isfinite(d)) else float("inf")

    # ----------------------------------------------------------------- render
    def render(self, camera_pose: np.ndarray, target_pose: np.ndarray, *,
               camera_pose_end: np.ndarray | None = None, target_pose_end: np.ndarray | None = None,
               light_gain: float = 1.0, occluders: Sequence[np.ndarray] = (),
               point_m: Sequence[float] | None = None, region: Sequence[float] | None = None,
               time_s: float = 0.0) -> Frame:
        """Render one frame.

        ``camera_pose``, ``target_pose``: 4x4 poses in the world frame (m) at the start of the
        exposure; ``*_end``: at its end (None: no motion, no blur). ``light_gain`` multiplies the
        light (lighting change). ``occluders``: polygons (N, 2) in image pixels drawn in front of
        the tissue (e.g. an instrument). ``point_m``: plane point (m) whose ground truth is
        reported (default: the target's ``selected_point_m``). Ground truth is taken at
        mid-exposure. ``region``: (x0, y0, x1, y1) image pixels: only these (and a few more, to
        whole vectors) are rendered, with the same values as in the whole frame; the rest stays
        black. For a consumer that reads only part of the frame (None: the whole frame).
        ``time_s``: the scene time (s) at mid-exposure, which shapes a deforming surface (its shape
        is held over the exposure: it moves < 0.1 mm in one); the plane ignores it.
        """
        if not (light_gain >= 0 and math.isfinite(light_gain)):
            raise ValueError(f"light_gain = {light_gain!r}; allowed: [0, inf)")
        if not math.isfinite(time_s):
            raise ValueError(f"time_s = {time_s!r}; must be a finite time (s)")
        folded = not self.surface.flat
        s, cam = self.settings, self.cam
        cp0 = np.asarray(camera_pose, float)
        tp0 = np.asarray(target_pose, float)
        cp1 = cp0 if camera_pose_end is None else np.asarray(camera_pose_end, float)
        tp1 = tp0 if target_pose_end is None else np.asarray(target_pose_end, float)
        moving = camera_pose_end is not None or target_pose_end is not None
        rel0 = self._plane_in_camera(cp0, tp0)
        n_sub = 1
        if moving:
            rel1 = self._plane_in_camera(cp1, tp1)
            motion = self._image_motion_px(rel0, rel1)
            n_sub = int(min(s.max_subframes, max(1, math.ceil(motion / s.blur_step_px))))
        cp_mid = interpolate_pose(cp0, cp1, 0.5) if moving else cp0
        tp_mid = interpolate_pose(tp0, tp1, 0.5) if moving else tp0
        rel_mid = self._plane_in_camera(cp_mid, tp_mid)
        if abs(float(rel_mid[:3, 2] @ rel_mid[:3, 3])) < 1e-6 or (moving and abs(float(rel1[:3, 2] @ rel1[:3, 3])) < 1e-6) \
                or abs(float(rel0[:3, 2] @ rel0[:3, 3])) < 1e-6:
            # The camera lies in the target plane: nothing sensible to see (black frame).
            truth = self.truth(cp_mid, tp_mid, point_m, time_s)
            return Frame(np.zeros((cam.height, cam.width, 3), np.uint8), truth, False, False, n_sub)

        A, B, S, H, P, PE, C = self._region_spans(region)
        hom0 = self._texel_homography(rel_mid, 0)
        jac = self._centre_jacobian(hom0)
        tpp = float(np.sqrt(abs(np.linalg.det(jac))))
        level = 0
        if s.mipmap and tpp > 1.0:
            level = min(len(self._levels) - 1, int(math.floor(math.log2(tpp))))
        lscale = np.diag([0.5 ** level, 0.5 ** level, 1.0])       # level-0 texels -> level texels

        # Motion blur: the exposure is integrated over n_sub sub-poses. With 2 the texture is sampled
        # at each; with 3 or more (cheaper so) the mid-exposure image (sampled once, with a margin) is
        # resampled where each sub-pose sees its plane points: per tile of 16 x 64 px one shift,
        # bilinear, unless a shift exceeds the margin (then the texture is sampled per sub-pose).
        mid_hom = lscale @ hom0
        mats = mid_hom.astype(np.float32).reshape(1, 9)
        image_blur = False
        if n_sub > 1 and not folded:     # (a surface is sampled at each sub-pose: _surface_grids)
            inv_mid = np.linalg.inv(mid_hom)
            reach = math.inf
            homs = lscale @ self._subpose_homographies(cp0, cp1, tp0, tp1, (np.arange(n_sub) + 0.5) / n_sub)
            if n_sub >= self._IMAGE_BLUR_MIN:
                gmats = (inv_mid @ homs).reshape(n_sub, 9)                 # sub-pose ray -> mid ray
                shifts = self._shifts[:n_sub]
                reach = _tile_shifts(gmats, self._rx_map, self._ry_map, self._ray0, self._cam6, self._MB,
                                     self._TILE[1], self._TILE[0], shifts)
                image_blur = reach <= self._MB - 3
            if not image_blur:
                mats = homs.reshape(n_sub, 9).astype(np.float32)

        # Lighting on the coarse grid (at mid-exposure).
        gain = s.light_gain * float(light_gain)
        rmat, t = rel_mid[:3, :3], rel_mid[:3, 3]
        nrm = rmat[:, 2] if float(rmat[:, 2] @ t) < 0 else -rmat[:, 2]   # plane normal towards the camera
        d_perp = float(-(nrm @ t))
        e0 = gain * (s.light_ref_distance_m / d_perp) ** 2 if d_perp > 0 else 0.0   # irradiance / cos^3
        amb = s.ambient * gain if d_perp > 0 else 0.0
        spec_on = s.specular_strength > 0 and self._slope_per_grad > 0
        w_scale = s.specular_strength if spec_on else 0.0   # x e0 below: glints scale with the light once, fall off as cos/d^2
        if folded:   # texels, shade and glint grids at mid-exposure; texels at each sub-pose if blurred
            grids, sgrid = self._grids[:n_sub], self._sgrid
            wmax = _surface_grid(*self._surface_args(rel_mid, time_s, level, C),
                                 grids[0] if n_sub == 1 else self._grid_mid, self._shade_c, sgrid,
                                 gain * s.light_ref_distance_m ** 2, s.ambient * gain, 1.0 / s.gamma, 255.0 / 128.0,
                                 w_scale)
            for k, f in enumerate((np.arange(n_sub) + 0.5) / n_sub if n_sub > 1 else ()):
                rel = self._plane_in_camera(interpolate_pose(cp0, cp1, f), interpolate_pose(tp0, tp1, f))
                _surface_grid(*self._surface_args(rel, time_s, level, C), grids[k], self._no_shade, self._no_sgrid,
                              0.0, 0.0, 1.0, 1.0, 0.0)
        else:
            grids, sgrid = self._no_grids, self._no_sgrid
            cmax = _light_grid(self._rays_c, self._cspans, C, nrm, amb, e0 ** (1.0 / s.gamma), 255.0 / 128.0,
                               self._cos_lut, self._shade_c, self._cs_row)
            wmax = w_scale * e0 * cmax ** 3                             # largest glint weight

        # Texture sampling x shade -> planes B, G, R, height.
        tex, rowb, th, tw = self._padded_level(level)
        sc = self._scratch
        mg = self._MB
        scratch = (self._iota, sc["rxs"], sc["rys"], sc["fus"], sc["fvs"], sc["acc"], sc["srow"], sc["crow"], sc["ext"],
                   grids, sc["grow"])
        if image_blur:
            r_ext = int(math.ceil(reach)) + 2
            _dilate_spans(PE, r_ext, self._mid.shape[1], self._espans)
            full = self._espans
            if region is not None:                  # rays computed as in the whole frame
                full = self._espans_full
                _dilate_spans(self._pspans_ext, r_ext, self._mid.shape[1], full)
            _sample_shade(tex, rowb, np.float32(tw * _FIX), np.float32(th * _FIX), mats, self._rx_map, self._ry_map,
                          0, self._ray0_ext, self._espans, full, self._shade_c, self._Q, mg, self._mid, self._hplane,
                          True, *scratch)
            _motion_blur(self._mid, mg, shifts, self._TILE[1], self._TILE[0], P, self._bgr,
                         self._hplane, self._blur_acc)
        else:
            _sample_shade(tex, rowb, np.float32(tw * _FIX), np.float32(th * _FIX), mats, self._rx_map, self._ry_map,
                          mg, self._ray0, P, self._pspans, self._shade_c, self._Q, 0, self._bgr, self._hplane,
                          False, *scratch)

        # Glints (half resolution).
        use_spec = False
        if spec_on and wmax > 0:
            thresh = min(30.0, math.log(510.0 * wmax))   # beyond: the glint rounds to 0
            if thresh > 0:
                # Height gradient per image pixel -> slope along texture x, y: grad_texel = J^-T grad_px.
                c = np.linalg.inv(jac).T * self._slope_per_grad
                use_spec = _specular_half(self._hplane, H, S, self._rays_h, nrm, rmat[:, 0],
                                          rmat[:, 1], w_scale * e0, c.ravel(), 0.5 * s.specular_exponent, thresh,
                                          self._hmap, self._t_row, self._spec, self._lit_rng, sgrid, self._srows,
                                          sc["crow"], sc["ext"])
        if occluders:
            if use_spec:
                _add_specular(self._bgr, self._spec, B, self._hv, self._srow_f)
                use_spec = False
            self._draw_occluders(self._bgr, occluders, gain)

        # Blur, noise, field of view.
        if self._noise and self.settings.fresh_noise:
            noise = self._noise[0]  # overwritten: seeded from the renderer's stream, new every frame
            cv2.setRNGSeed(int(self._rng.integers(2 ** 31)))
            cv2.randn(noise, 0.0, self.settings.noise_sigma)  # saturates at the dtype's range, like the bank's clip
            oy, ox = (int(v) for v in self._rng.integers(0, 32, 2))
        elif self._noise:
            noise = self._noise[int(self._rng.integers(len(self._noise)))]
            oy, ox = (int(v) for v in self._rng.integers(0, 32, 2))
        else:
            noise, oy, ox = self._zero_noise, 0, 0
        out = np.zeros((cam.height, cam.width, 3), np.uint8)
        x0, y0 = self._box[:2]
        _finish(self._bgr, self._spec, self._lit_rng, use_spec, self._kw, A, self._alpha3, noise, oy, ox,
                bool(self._noise), out, y0, x0, self._sring, self._tags, self._srng, self._colpad, self._hacc,
                self._srow_f, self._hv)

        truth = self.truth(cp_mid, tp_mid, point_m, time_s)
        occluded = bool(np.all(np.isfinite(truth)) and any(
            cv2.pointPolygonTest(np.asarray(p, np.float32).reshape(-1, 1, 2), (float(truth[0]), float(truth[1])), False) >= 0
            for p in occluders))
        in_fov = bool(np.all(np.isfinite(truth)) and
                      math.hypot(truth[0] - cam.cx, truth[1] - cam.cy) <= s.fov_radius_px and
                      0 <= truth[0] <= cam.width - 1 and 0 <= truth[1] <= cam.height - 1)
        return Frame(out, truth, in_fov and not occluded, occluded, n_sub)

    def _draw_occluders(self, img: np.ndarray, occluders: Sequence[np.ndarray], gain: float) -> None:
        """Occluder polygons (image pixels), anti-aliased, drawn on the box image ``img`` (BGR)."""
        x0, y0 = self._box[:2]
        col = tuple(float(min(255.0, c * max(gain, 0.0) ** (1 / self.settings.gamma))) for c in self.settings.occluder_bgr)
        dark = tuple(0.45 * c for c in col)
        for p in occluders:
            pts = np.round((np.asarray(p, float) - [x0, y0]) * 16).astype(np.int32).reshape(-1, 1, 2)
            cv2.fillPoly(img, [pts], col, lineType=cv2.LINE_AA, shift=4)
            cv2.polylines(img, [pts], True, dark, thickness=2, lineType=cv2.LINE_AA, shift=4)



def render_benchmark(frames: int = 200, *, distorted: bool = False, subposes: Sequence[int] = (1, 2, 4),
                     texture_px: int = 4096, distance_m: float = 0.12, tilt_deg: float = 30.0,
                     settings: RenderSettings | None = None, seed: int = 0) -> dict:
    """Time :meth:`Renderer.render` on the closed loop's typical frame, single-threaded.

    A 0.4 m x 0.4 m mucosa plane (``texture_px``) ``distance_m`` in front of the camera
    (:class:`CameraParams` defaults, or :func:`endoscope_camera` if ``distorted``), tilted by
    ``tilt_deg`` about an axis that turns from frame to frame; for each entry n of ``subposes``
    the target moves during the exposure so that motion blur integrates exactly n sub-poses
    (1: a still frame). Returns {"camera", "frames", "ms": {n: {"median", "mean", "p95"}}} with
    milliseconds per frame (the first frames, which compile or load the kernels, are not timed).
    """
    import time
    cam = endoscope_camera() if distorted else CameraParams()
    rs = settings or RenderSettings()
    renderer = Renderer(cam, rs, PlanarTarget.mucosa((0.4, 0.4), seed=seed, texture_px=texture_px), seed=seed)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    tilt = math.radians(tilt_deg)
    out: dict = {"camera": "distorted" if distorted else "pinhole", "frames": int(frames), "ms": {}}
    try:
        for n in subposes:
            times = []
            for i in range(frames + 3):
                pose = make_pose((0.003 * math.sin(0.1 * i), 0.002 * math.cos(0.13 * i), distance_m),
                                 (tilt * math.cos(0.05 * i), tilt * math.sin(0.05 * i), 0.1 * i))
                kw = {}
                if n > 1:   # move the target along x so that the image motion asks for n sub-poses
                    probe = pose.copy()
                    probe[0, 3] += 1e-3
                    px_per_mm = renderer._image_motion_px(renderer._plane_in_camera(np.eye(4), pose),
                                                          renderer._plane_in_camera(np.eye(4), probe))
                    end = pose.copy()
                    end[0, 3] += 1e-3 * (n - 0.5) * rs.blur_step_px / px_per_mm
                    kw = {"target_pose_end": end}
                t0 = time.perf_counter()
                frame = renderer.render(np.eye(4), pose, **kw)
                dt = time.perf_counter() - t0
                if i >= 3:
                    times.append(dt * 1e3)
                    if frame.subframes != n:
                        raise RuntimeError(f"benchmark asked for {n} sub-poses, the renderer used {frame.subframes}")
            t = np.asarray(times)
            out["ms"][int(n)] = {"median": float(np.median(t)), "mean": float(t.mean()),
                                 "p95": float(np.percentile(t, 95))}
    finally:
        cv2.setNumThreads(threads)
    return out
