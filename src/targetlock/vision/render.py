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
are given in metres in that frame: (x right, y down from the centre).

Speed: the distorted-pixel -> undistorted-ray map is computed once; per frame one
``cv2.perspectiveTransform`` gives the pixel -> texel map, one ``cv2.remap`` samples the
(mip-mapped) texture, lighting is evaluated on a 4x coarser grid and upsampled, and all
per-pixel work runs in OpenCV.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from ..config import param, validate
from ..model.camera import CameraParams, project, world_to_camera
from .texture import aruco_texture, mucosa_texture, with_height

__all__ = ["RenderSettings", "PlanarTarget", "Frame", "Renderer", "make_pose", "interpolate_pose",
           "endoscope_camera"]


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
    rel = a[:3, :3].T @ b[:3, :3]
    rv = cv2.Rodrigues(rel)[0].ravel()
    out = np.eye(4)
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


class Renderer:
    """Renders endoscope frames of a :class:`PlanarTarget` (see the module docstring).

    ``cam``: intrinsics and distortion (use :func:`endoscope_camera` for the usual distorted
    camera); ``settings``: :class:`RenderSettings`; ``target``: the textured plane (default:
    procedural mucosa from ``seed``, 0.2 m x 0.2 m); ``seed``: sensor noise (and default texture).
    """

    _Q = 4  # lighting is evaluated on a grid this many times coarser than the image

    def __init__(self, cam: CameraParams, settings: RenderSettings | None = None,
                 target: PlanarTarget | None = None, *, seed: int = 0) -> None:
        self.cam = validate(cam)
        self.settings = validate(settings or RenderSettings())
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

        def rays(us: np.ndarray, vs: np.ndarray) -> np.ndarray:
            """Undistorted normalised coordinates (..., 2) of distorted pixel grids."""
            xd, yd = (us - cam.cx) / cam.fx, (vs - cam.cy) / cam.fy
            rd = np.hypot(xd, yd)
            if cam.k1 or cam.k2:
                rmax = (r + 4) / min(cam.fx, cam.fy)
                rc = np.minimum(rd, rmax)
                ru = _undistort_radius(rc, cam.k1, cam.k2)
                ru_grid = np.linspace(0, float(ru.max()), 512)
                slope = 1 + 3 * cam.k1 * ru_grid ** 2 + 5 * cam.k2 * ru_grid ** 4
                if np.any(slope <= 0):
                    raise ValueError(f"distortion k1={cam.k1}, k2={cam.k2} is not invertible inside the "
                                     f"field of view ({r} px); reduce fov_radius_px or the distortion")
                f = np.where(rd > 1e-12, ru / np.maximum(rd, 1e-12), 1.0)
                f = np.where(rd > rmax, ru / np.maximum(rc, 1e-12), f)  # outside the circle: masked anyway
                xd, yd = xd * f, yd * f
            return np.stack([xd, yd], axis=-1)

        vs, us = np.mgrid[y0:y1, x0:x1].astype(np.float64)
        self._xy = rays(us, vs).astype(np.float32)                  # (bh, bw, 2)
        # Coarse grid: cell (j, i) sits at full-res (q j + (q-1)/2) so cv2.resize(INTER_LINEAR) aligns.
        off = (q - 1) / 2
        vs_c, us_c = np.mgrid[0:bh // q, 0:bw // q].astype(np.float64)
        xy_c = rays(x0 + q * us_c + off, y0 + q * vs_c + off)
        v = np.concatenate([xy_c, np.ones(xy_c.shape[:2] + (1,))], axis=-1)
        self._rays_c = v / np.linalg.norm(v, axis=-1, keepdims=True)  # unit rays on the coarse grid
        # Field-of-view mask (soft edge), 3 channels for cv2.multiply(scale=1/255).
        dist = np.hypot(us - cam.cx, vs - cam.cy)
        if s.fov_edge_px > 0:
            alpha = np.clip(0.5 + (r - dist) / s.fov_edge_px, 0.0, 1.0)
        else:
            alpha = (dist <= r).astype(float)
        self._fov_alpha = alpha
        self._mask3 = np.repeat(np.round(alpha * 255).astype(np.uint8)[..., None], 3, axis=2)
        self._bbox_shape = (bh, bw)

    def _build_noise(self) -> None:
        """A small bank of seeded noise images; each frame takes a random window of one of them."""
        bh, bw = self._bbox_shape
        sig = self.settings.noise_sigma
        self._noise = []
        if sig <= 0:
            return
        for _ in range(3):
            n = np.round(self._rng.normal(0.0, sig, (bh + 32, bw + 32, 3)))
            n = np.clip(n, -255, 255)
            self._noise.append((np.maximum(n, 0).astype(np.uint8), np.maximum(-n, 0).astype(np.uint8)))

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
        h = tex[..., 3].astype(np.float32)
        gx = cv2.Sobel(h, cv2.CV_32F, 1, 0, ksize=3) / 8.0
        gy = cv2.Sobel(h, cv2.CV_32F, 0, 1, ksize=3) / 8.0
        rms = float(np.sqrt(np.mean(gx * gx + gy * gy)))  # height units per texel
        # slope (rad) = bump_slope * (grad h per level-0 texel) / rms
        self._slope_per_grad = self.settings.bump_slope / rms if rms > 1e-6 else 0.0
        bg = tuple(int(c) for c in self.settings.background_bgr)
        self._border = (bg[0], bg[1], bg[2], 128)

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
              point_m: Sequence[float] | None = None) -> np.ndarray:
        """Pixel position (x, y; with distortion) of a plane point (default: the selected point)."""
        p = self.target.selected_point_m if point_m is None else point_m
        world = np.asarray(target_pose, float) @ np.array([p[0], p[1], 0.0, 1.0])
        return project(world_to_camera(np.asarray(camera_pose, float), world[:3]), self.cam)

    def _texel_map(self, rel: np.ndarray, level: int) -> np.ndarray:
        hn = np.column_stack([rel[:3, 0], rel[:3, 1], rel[:3, 3]])  # plane (x, y, 1) -> normalised
        m = self._texel_from_plane(level) @ np.linalg.inv(hn)
        return cv2.perspectiveTransform(self._xy, m)

    def _texels_per_px(self, rel: np.ndarray) -> float:
        """Level-0 texels per image pixel near the image centre (geometric mean of both axes)."""
        hn = np.column_stack([rel[:3, 0], rel[:3, 1], rel[:3, 3]])
        m = self._texel_from_plane(0) @ np.linalg.inv(hn)
        d = 1.0 / self.cam.fx
        pts = np.array([[[0.0, 0.0], [d, 0.0], [0.0, d * self.cam.fx / self.cam.fy]]])
        t = cv2.perspectiveTransform(pts, m)[0]
        j = np.array([t[1] - t[0], t[2] - t[0]])
        return float(np.sqrt(abs(np.linalg.det(j))))

    def _image_motion_px(self, rel0: np.ndarray, rel1: np.ndarray) -> float:
        """Largest image motion (px) of plane points seen at five places in the field of view."""
        r = 0.7 * self.settings.fov_radius_px
        px = np.array([[0, 0], [r, 0], [-r, 0], [0, r], [0, -r]], float) + [self.cam.cx, self.cam.cy]
        n = np.column_stack([(px[:, 0] - self.cam.cx) / self.cam.fx, (px[:, 1] - self.cam.cy) / self.cam.fy,
                             np.ones(len(px))])
        h0 = np.column_stack([rel0[:3, 0], rel0[:3, 1], rel0[:3, 3]])
        h1 = np.column_stack([rel1[:3, 0], rel1[:3, 1], rel1[:3, 3]])
        m = h1 @ np.linalg.inv(h0)
        q = n @ m.T
        with np.errstate(divide="ignore", invalid="ignore"):
            q = q[:, :2] / q[:, 2:3]
        d = np.hypot(*(q - n[:, :2]).T) * self.cam.fx
        return float(np.nanmax(d)) if np.all(np.isfinite(d)) else float("inf")

    # ---------------------------------------------------------------- shading
    def _lighting(self, rel: np.ndarray, gain: float, texels_per_px: float, level: int):
        """Coarse-grid diffuse shade (4 channels, x128 uint8), specular weight and ray-tangent fields."""
        s = self.settings
        rmat, t = rel[:3, :3], rel[:3, 3]
        n = rmat[:, 2] if float(rmat[:, 2] @ t) < 0 else -rmat[:, 2]   # plane normal towards the camera
        d_perp = float(-(n @ t))
        rays = self._rays_c
        cos = -(rays @ n)                                             # cos of incidence (= emergence)
        hit = (cos > 1e-3) & (d_perp > 0)
        cos = np.where(hit, cos, 0.0)
        e = gain * cos ** 3 * (s.light_ref_distance_m / max(d_perp, 1e-9)) ** 2
        shade = s.ambient * gain * hit + e ** (1.0 / s.gamma)
        shade_u8 = np.clip(shade * 128.0, 0, 255).astype(np.uint8)
        shade4 = np.repeat(shade_u8[..., None], 4, axis=2)
        spec = None
        if s.specular_strength > 0 and self._slope_per_grad > 0:
            w_spec = (s.specular_strength * gain * e).astype(np.float32)  # specular also falls off as cos/d^2
            a1 = -(rays @ rmat[:, 0]).astype(np.float32)                 # view-direction tilt along texture x
            a2 = -(rays @ rmat[:, 1]).astype(np.float32)                 # ... and along texture y
            spec = (w_spec, a1, a2)
        return shade4, spec

    # ----------------------------------------------------------------- render
    def render(self, camera_pose: np.ndarray, target_pose: np.ndarray, *,
               camera_pose_end: np.ndarray | None = None, target_pose_end: np.ndarray | None = None,
               light_gain: float = 1.0, occluders: Sequence[np.ndarray] = (),
               point_m: Sequence[float] | None = None) -> Frame:
        """Render one frame.

        ``camera_pose``, ``target_pose``: 4x4 poses in the world frame (m) at the start of the
        exposure; ``*_end``: at its end (None: no motion, no blur). ``light_gain`` multiplies the
        light (lighting change). ``occluders``: polygons (N, 2) in image pixels drawn in front of
        the tissue (e.g. an instrument). ``point_m``: plane point (m) whose ground truth is
        reported (default: the target's ``selected_point_m``). Ground truth is taken at
        mid-exposure.
        """
        if not (light_gain >= 0 and math.isfinite(light_gain)):
            raise ValueError(f"light_gain = {light_gain!r}; allowed: [0, inf)")
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
            truth = self.truth(cp_mid, tp_mid, point_m)
            return Frame(np.zeros((cam.height, cam.width, 3), np.uint8), truth, False, False, n_sub)

        tpp = self._texels_per_px(rel_mid)
        level = 0
        if s.mipmap and tpp > 1.0:
            level = min(len(self._levels) - 1, int(math.floor(math.log2(tpp))))
        tex = self._levels[level]

        # Texture sampling, integrated over the exposure.
        if n_sub == 1:
            img4 = cv2.remap(tex, self._texel_map(rel_mid, level), None, cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=self._border)
        else:
            acc = None
            for k in range(n_sub):
                f = (k + 0.5) / n_sub
                rel = self._plane_in_camera(interpolate_pose(cp0, cp1, f), interpolate_pose(tp0, tp1, f))
                smp = cv2.remap(tex, self._texel_map(rel, level), None, cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=self._border)
                acc = smp.astype(np.uint16) if acc is None else cv2.add(acc, smp, dtype=cv2.CV_16U)
            img4 = cv2.convertScaleAbs(acc, alpha=1.0 / n_sub)

        gain = s.light_gain * float(light_gain)
        bh, bw = self._bbox_shape
        shade4_c, spec = self._lighting(rel_mid, gain, tpp, level)
        shade4 = cv2.resize(shade4_c, (bw, bh), interpolation=cv2.INTER_LINEAR)
        img = cv2.cvtColor(cv2.multiply(img4, shade4, scale=1.0 / 128.0), cv2.COLOR_BGRA2BGR)

        if spec is not None:
            img = cv2.add(img, self._specular(img4, spec, rel_mid, level))
        if occluders:
            img = self._draw_occluders(img, occluders, gain)
        if s.optical_blur_px > 0:
            k = 3 if s.optical_blur_px <= 0.8 else 2 * int(math.ceil(3 * s.optical_blur_px)) + 1
            img = cv2.GaussianBlur(img, (k, k), s.optical_blur_px)
        if self._noise:
            pos, neg = self._noise[int(self._rng.integers(len(self._noise)))]
            oy, ox = (int(v) for v in self._rng.integers(0, 32, 2))
            img = cv2.subtract(cv2.add(img, pos[oy:oy + bh, ox:ox + bw]), neg[oy:oy + bh, ox:ox + bw])
        img = cv2.multiply(img, self._mask3, scale=1.0 / 255.0)

        out = np.zeros((cam.height, cam.width, 3), np.uint8)
        x0, y0, x1, y1 = self._box
        out[y0:y1, x0:x1] = img

        truth = self.truth(cp_mid, tp_mid, point_m)
        occluded = bool(np.all(np.isfinite(truth)) and any(
            cv2.pointPolygonTest(np.asarray(p, np.float32).reshape(-1, 1, 2), (float(truth[0]), float(truth[1])), False) >= 0
            for p in occluders))
        in_fov = bool(np.all(np.isfinite(truth)) and
                      math.hypot(truth[0] - cam.cx, truth[1] - cam.cy) <= s.fov_radius_px and
                      0 <= truth[0] <= cam.width - 1 and 0 <= truth[1] <= cam.height - 1)
        return Frame(out, truth, in_fov and not occluded, occluded, n_sub)

    def _specular(self, img4: np.ndarray, spec, rel: np.ndarray, level: int) -> np.ndarray:
        """Specular glints (BGR uint8): lobe exp(-k/2 |a - g|^2) of the angle between the bumped
        normal and the view direction, with g the surface slope from the height channel."""
        w_c, a1_c, a2_c = spec
        bh, bw = self._bbox_shape
        half = (bw // 2, bh // 2)  # glints are computed at half resolution, then upsampled
        # Height gradient in image pixels -> per level-0 texel along texture x, y via the local
        # Jacobian (texel <- pixel) at the image centre.
        hmap = cv2.resize(cv2.extractChannel(img4, 3), half, interpolation=cv2.INTER_AREA)
        gxp = cv2.Sobel(hmap, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 16.0)  # per full-res pixel
        gyp = cv2.Sobel(hmap, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 16.0)
        hn = np.column_stack([rel[:3, 0], rel[:3, 1], rel[:3, 3]])
        m = self._texel_from_plane(0) @ np.linalg.inv(hn)
        d = 1.0 / self.cam.fx
        t = cv2.perspectiveTransform(np.array([[[0.0, 0.0], [d, 0.0], [0.0, d * self.cam.fx / self.cam.fy]]]), m)[0]
        jac = np.column_stack([t[1] - t[0], t[2] - t[0]])             # d texel / d pixel (2x2)
        c = np.linalg.inv(jac).T * self._slope_per_grad                # grad_texel = J^-T grad_px
        g1 = cv2.addWeighted(gxp, float(c[0, 0]), gyp, float(c[0, 1]), 0.0)
        g2 = cv2.addWeighted(gxp, float(c[1, 0]), gyp, float(c[1, 1]), 0.0)
        d1 = cv2.subtract(cv2.resize(a1_c, half, interpolation=cv2.INTER_LINEAR), g1)
        d2 = cv2.subtract(cv2.resize(a2_c, half, interpolation=cv2.INTER_LINEAR), g2)
        th2 = cv2.add(cv2.multiply(d1, d1), cv2.multiply(d2, d2))
        # exp of very negative arguments hits slow denormal paths: clamp (exp(-30) ~ 1e-13)
        lobe = cv2.exp(cv2.max(cv2.multiply(th2, -0.5 * self.settings.specular_exponent), -30.0))
        w = cv2.resize(w_c, half, interpolation=cv2.INTER_LINEAR)
        # Height 0 marks matte material (e.g. a printed marker): gloss ramps up over heights 0..16.
        gloss = cv2.min(hmap, 16).astype(np.float32)
        spec = cv2.convertScaleAbs(cv2.multiply(cv2.multiply(lobe, w), gloss), alpha=255.0 / 16.0)
        spec = cv2.resize(spec, (bw, bh), interpolation=cv2.INTER_LINEAR)
        return cv2.cvtColor(spec, cv2.COLOR_GRAY2BGR)

    def _draw_occluders(self, img: np.ndarray, occluders: Sequence[np.ndarray], gain: float) -> np.ndarray:
        x0, y0 = self._box[:2]
        col = tuple(float(min(255.0, c * max(gain, 0.0) ** (1 / self.settings.gamma))) for c in self.settings.occluder_bgr)
        dark = tuple(0.45 * c for c in col)
        for p in occluders:
            pts = np.round((np.asarray(p, float) - [x0, y0]) * 16).astype(np.int32).reshape(-1, 1, 2)
            cv2.fillPoly(img, [pts], col, lineType=cv2.LINE_AA, shift=4)
            cv2.polylines(img, [pts], True, dark, thickness=2, lineType=cv2.LINE_AA, shift=4)
        return img
