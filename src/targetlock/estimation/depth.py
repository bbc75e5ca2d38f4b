"""Target depth (m along the optical axis), where it is observable (issue 9 §2).

Two sources, each with its observability condition:

(a) **From the image Jacobian.** J of a point on the optical axis grows as the target comes nearer
    (a bend turns the camera, f px/rad, and moves it sideways by about L/2 per rad:
    |J| ≈ g·f·(1 + L/(2·d))). The depth is the one whose prior Jacobian (nominal camera and tip
    geometry, assumed handle→tip gain g) has the estimated size (geometric mean of the singular
    values). It confounds the depth with the assumed gains: a handle gain or focal length wrong by a
    factor (1 + e) scales |J| by (1 + e), read as a depth ``d' = d / (1 + e·(1 + 2d/L))`` — e.g. +15 %
    handle gain reads 12 cm as 7.1 cm and 1.5 cm as 1.2 cm; so (a) is good to ~20 % only near the
    scope (d ≲ L/2), and beyond ~15 cm |J| hardly changes with depth (not observable: the estimate is
    clamped, and its ``observable_j`` flag is False where |dJ/dd|·d/|J| < 0.1).
(b) **From the target's apparent scale** (``Observation.scale``, relative size, ∝ 1/z). When the tip
    moves along its optical axis by Δ, a static target's scale changes by z/(z − Δ): the depth is the
    one for which the camera motion (from the motor angles through the assumed kinematics) predicts
    the scales seen, fitted over a sliding window. Observable only when the window's camera motion
    along the axis is at least ``min_axial`` × depth (a bend of 0.3 rad moves a 12 cm tip ~2 mm along
    its axis: enough at 1–2 cm, marginal at 10 cm) and the target does not move in depth itself
    (confounded with it). Confounds depth with the assumed tip gain about linearly (Δ scales with it).

The estimate is (a), always within [``lo``, ``hi``] (default 0.5–30 cm); with ``use_scale`` it is (b)
while that is observable. On the twin (static target, after the engage probe) (b) finds 1.5 cm
exactly when fed the tip angles (a rig that measures the tip), and says "not observable" at 10 cm;
fed the handle angles through the assumed gain and an estimated backlash it was biased (3.5 cm for
1.5) or not observable, so it is off by default; (a) gave 1.8–2.0 cm for 1.5 and 8.7 for 10.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from ..model.camera import CameraParams, unproject
from ..model.kinematics import tip_pose
from .jacobian import prior_jacobian

__all__ = ["DepthEstimator"]


class DepthEstimator:
    """Bounded target depth (m) from the estimated Jacobian and, where observable, the tracker's scale."""

    def __init__(self, *, camera: CameraParams, tip_gain: float, tip_length: float, n_elements: int,
                 initial: float = 0.12, lo: float = 0.005, hi: float = 0.30, window: int = 120,
                 min_axial: float = 0.03, every: int = 10, use_scale: bool = False) -> None:
        if not 0 < lo < hi:
            raise ValueError(f"DepthEstimator: need 0 < lo = {lo} < hi = {hi} (m)")
        self.camera, self.tip_gain = camera, tip_gain
        self.tip_length, self.n_elements = tip_length, n_elements
        self.lo, self.hi = lo, hi
        self.depth = float(np.clip(initial, lo, hi))
        self.depth_j = self.depth            # m, from (a)
        self.depth_scale = math.nan          # m, from (b); NaN while not observable
        self.observable_j = False
        self.candidates = np.geomspace(lo, hi, 120)
        self.frames: deque[tuple[np.ndarray, np.ndarray, float]] = deque(maxlen=window)   # (motor, offset, scale)
        self.min_axial, self.every = min_axial, every
        self.use_scale = use_scale
        self._count = 0

    def _size(self, motor: np.ndarray, depth: float) -> float:
        j = prior_jacobian(motor, camera=self.camera, depth=depth, tip_gain=self.tip_gain,
                           tip_length=self.tip_length, n_elements=self.n_elements)
        return math.sqrt(abs(np.linalg.det(j)))

    def from_jacobian(self, jacobian: np.ndarray, motor: np.ndarray) -> float:
        """(a): the depth (m) whose prior Jacobian at ``motor`` (handle rad) has the size of ``jacobian``."""
        jacobian = np.asarray(jacobian, dtype=float)
        motor = np.asarray(motor, dtype=float)
        if not (np.all(np.isfinite(jacobian)) and np.all(np.isfinite(motor))):
            return self.depth_j
        size = math.sqrt(abs(float(np.linalg.det(jacobian))))
        if not math.isfinite(size):
            return self.depth_j
        sizes = np.array([self._size(motor, d) for d in self.candidates[::8]])   # decreasing with depth
        depths = self.candidates[::8]
        d = float(np.interp(-size, -sizes, depths))                                 # clamps at the ends
        k = int(np.clip(np.searchsorted(depths, d), 1, depths.size - 1))
        sensitivity = abs((math.log(sizes[k]) - math.log(sizes[k - 1])) / (math.log(depths[k]) - math.log(depths[k - 1])))
        self.observable_j = sensitivity >= 0.1
        self.depth_j = float(np.clip(d, self.lo, self.hi))
        return self.depth_j

    def add(self, motor: np.ndarray, offset: np.ndarray, scale: float, jacobian: np.ndarray) -> float:
        """One frame: motor (handle rad) at its capture time, offset (px), the tracker's relative scale
        (NaN if none) and the current Jacobian estimate (px/rad). Returns the depth estimate (m)."""
        motor = np.asarray(motor, dtype=float)
        offset = np.asarray(offset, dtype=float)
        self.from_jacobian(jacobian, motor)
        if np.all(np.isfinite(motor)) and np.all(np.isfinite(offset)) and math.isfinite(scale) and 0.05 < scale < 20.0:
            self.frames.append((motor, offset, float(scale)))
            self._count += 1
            if self._count % self.every == 0 and len(self.frames) >= 20:
                self._fit_scale()
        self.depth = self.depth_scale if self.use_scale and math.isfinite(self.depth_scale) else self.depth_j
        self.depth = float(np.clip(self.depth, self.lo, self.hi))
        return self.depth

    def _fit_scale(self) -> None:
        cam = self.camera
        m0, x0, s0 = self.frames[0]
        phi0 = self.tip_gain * m0
        pose0 = tip_pose(phi0[0], phi0[1], self.tip_length, self.n_elements)
        ray = unproject(np.asarray(x0) + (cam.cx, cam.cy), 1.0, cam, distort=False)    # point at depth 1 m
        g = self.tip_gain
        poses = [tip_pose(g * f[0][0], g * f[0][1], self.tip_length, self.n_elements) for f in self.frames]
        s = np.array([f[2] for f in self.frames]) / s0
        # Depth of the reference frame's target point, seen from each later camera, per candidate depth.
        pts = pose0[:3, :3] @ (ray[:, None] * self.candidates[None, :]) + pose0[:3, 3:4]         # (3, k)
        z = np.array([(p[:3, :3].T @ (pts - p[:3, 3:4]))[2] for p in poses])                    # (n, k)
        if np.any(z <= 0):
            z = np.where(z > 0, z, np.nan)
        pred = self.candidates[None, :] / z                                                     # relative scale
        axial = np.nanmax(np.abs(z - self.candidates[None, :]), axis=0)                          # camera motion along the axis
        cost = np.nanmean(np.abs(s[:, None] - pred), axis=0)
        best = int(np.nanargmin(cost))
        if axial[best] >= self.min_axial * self.candidates[best]:
            self.depth_scale = float(self.candidates[best])
        else:
            self.depth_scale = math.nan       # not observable in this window: fall back to (a)
