"""Image Jacobian relative to the modelled tip, by windowed batch least squares (issue 9 §2).

:class:`JacobianEstimator` regresses image increments on motor increments through a play operator
with one constant J. In closed-loop tracking that comes out 20-45 % off, for two reasons measured on
the twin: (1) J is not one matrix — the lock holds the target 100-200 px off centre, and the image
motion per tip radian of a point there is up to 1.4× that of the centre (the pinhole's
``f·(1 + x²/f²)`` and the cross term ``x·y/f``), so a J fitted over a window is none of the frames'
J; (2) the motor follows the target, and what tells the tip's motion from the target's is the tip's
start, stop and stick-slip, which a play operator places coarsely.

This estimator instead uses what the controller knows: the camera intrinsics and the tip geometry
(nominal), and the tip angles of an online model of the assumed endoscope (:class:`.TipModel`) at
each frame's capture time. For a target seen at offset ``x`` with the (modelled) tip at ``φ``, the
image motion per tip radian is, exactly to first order (the pinhole's interaction matrix),

    J_tip(x, φ) = A(x, φ) / Z + R(x, φ)        (px per tip rad, per column = tip axis)

A: the part from the camera's translation, R: from its rotation, both computed from the kinematics
(:func:`image_jacobian_parts`); Z the target depth (unknown). With a per-axis gain ``g_a`` between
the true and the modelled tip motion (the model's parameters are only nominal), the image increment
between two frames is

    Δx = Σ_a (A_a·ρ_a + R_a·g_a)·Δφ_a + (the target's own motion),     ρ_a = g_a / Z,

linear in θ = (ρ_x, ρ_y, g_x, g_y). Over a sliding window (``window`` s) the target's own motion is
removed by projecting both sides onto the complement of a cubic spline in time times each increment's
span (knots every ``knot`` s: a target has mass, its image velocity is smooth on that scale; the tip's
stick-slip and reversals are not), then θ is fitted by least squares with one robust reweighting
(tracker outliers and jumps dropped at 3× the median residual). The modelled tip is read at each
frame's capture time minus the caller's delay minus a small extra shift; the shift (within
``max_shift``, ±60 ms) that fits best is chosen per window and the median over recent windows used (a
30 ms misalignment costs ~10 % of J; the play-based delay estimate is that far off). A window updates θ
only if the modelled tip moved on both axes.

Output: J in px per *handle* rad, ``J_tip · diag(slope)`` with the assumed scope's moving-branch slope
(tip per handle rad, :meth:`.TipModel.sweep`), at the newest frame's offset and modelled tip
(:attr:`j`) or anywhere (:meth:`j_at`, e.g. at the image centre). Bounded: the gains within
``gain_range``, the depth within ``depth_range``, and J made physically possible
(:func:`.bound_jacobian`: orientation, coupling, singular values within [sv_min, sv_max]); a window
that gives anything else keeps the last good θ.

Measured on the twin (tests/estimation: closed-loop tracking of a target on an ellipse as large as its
distance, nominal knowledge, 3 noise seeds; Frobenius error of the whole matrix against the twin's,
median over 15-30 s): calibrated scope at 5 cm 9-11 %, at 1.5 cm 4.5-5 %, at 12 cm 8-10 %, depth within
10 % (the play-operator RLS: 38 %, 23-26 %, 43 %); with 1.5 px noise, 10 % drops and 5 % outliers at
1.5 cm 6-13 % (the target's own motion is modelled as a smooth velocity times each increment's span:
with 20 ms jitter and 10 % drops, a smooth increment instead gave 7-18 %). It needs the model's
hysteresis about right (measured at 5 cm, one seed): robust to the handle gain (+15 %: 13 %) and the
tip stiffness (+30 %: 9 %), not to a loop width off by 25 % or more (friction ±30 %, cable stiffness
−30 %, the uncalibrated scope: 30-39 %; the looped shaft, 3 seeds: 48-55 %; the RLS there 34-49 %,
38-40 %). :attr:`explained` tells: 0.88-0.96 where J is right, 0.37-0.79 in those cases, about 0 on the
looped shaft. A bank of five tip models with the friction scaled ×0.6-1.7, the best explained one
chosen, brought the looped shaft to 20 %, the cable stiffness −30 % to 10 %, the uncalibrated scope to
24 % (such a bank, of 32 candidates, now chooses ``adaptive``'s tip model: :mod:`.scope_bank`)."""
from __future__ import annotations

import math
from collections import deque
from typing import Callable

import numpy as np
from scipy.interpolate import BSpline

from ..model.camera import CameraParams, project, unproject
from ..model.kinematics import tip_pose
from .jacobian import bound_jacobian

__all__ = ["TipJacobianEstimator", "image_jacobian_parts"]

_FAR = 1e4          # m: a depth at which the translation's image motion is negligible
_NEAR = 0.05        # m: the depth A is read at


def image_jacobian_parts(offset: np.ndarray, tip: np.ndarray, *, camera: CameraParams, tip_length: float,
                         n_elements: int, eps: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    """(A, R), each 2×2, with ``A / Z + R`` the image motion (px per tip rad, column = tip axis) of a
    point seen at ``offset`` (px from the principal point) at depth ``Z`` (m, along the optical axis)
    with the tip at ``tip`` (rad): A (px·m/rad) from the camera's translation, R (px/rad) from its
    rotation. Finite differences through the kinematics and the camera (distortion included)."""
    c = np.array([camera.cx, camera.cy])
    base = tip_pose(float(tip[0]), float(tip[1]), tip_length, n_elements)
    moved = [tip_pose(float(tip[0]) + eps, float(tip[1]), tip_length, n_elements),
             tip_pose(float(tip[0]), float(tip[1]) + eps, tip_length, n_elements)]
    pixel = np.asarray(offset, dtype=float) + c
    out = []
    for depth in (_NEAR, _FAR):
        p_cam = unproject(pixel, depth, camera)
        p_world = base[:3, :3] @ p_cam + base[:3, 3]
        start = project(p_cam, camera)
        j = np.empty((2, 2))
        for a, pose in enumerate(moved):
            j[:, a] = (project(pose[:3, :3].T @ (p_world - pose[:3, 3]), camera) - start) / eps
        out.append(j)
    r = out[1]
    return (out[0] - r) * _NEAR, r


class TipJacobianEstimator:
    """Bounded windowed estimate of the image Jacobian (px per handle rad) relative to the modelled
    tip, position-dependent through the camera model (module docstring).

    ``slope``: tip rad per handle rad of the assumed scope per axis (e.g. ``TipModel.sweep``);
    ``depth``: the assumed target depth (m), the prior until a window is informative."""

    def __init__(self, *, camera: CameraParams, tip_length: float, n_elements: int, slope: np.ndarray,
                 depth: float, sv_min: float = 50.0, sv_max: float = 8000.0, window: float = 8.0,
                 knot: float = 0.75, every: int = 5, min_frames: int = 40,
                 delays: np.ndarray = np.arange(-0.3, 0.8001, 0.01), max_shift: float = 0.06, answers: int = 9,
                 max_coupling: float = 0.5, gain_range: tuple[float, float] = (0.5, 2.0),
                 depth_range: tuple[float, float] = (0.005, 0.5), min_tip_motion: float = 0.02,
                 max_gap: float = 0.5, gain_ridge: float = 0.1) -> None:
        slope = np.broadcast_to(np.asarray(slope, dtype=float), (2,)).copy()
        if not np.all((slope > 0) & np.isfinite(slope)):
            raise ValueError(f"TipJacobianEstimator: slope = {slope} tip rad per handle rad; allowed: > 0")
        if not depth_range[0] <= depth <= depth_range[1] or not 0 < depth_range[0] < depth_range[1]:
            raise ValueError(f"TipJacobianEstimator: depth = {depth} m; allowed: within depth_range = {depth_range} m")
        if not 0 < gain_range[0] <= 1.0 <= gain_range[1]:
            raise ValueError(f"TipJacobianEstimator: gain_range = {gain_range}; allowed: lo in (0, 1], hi ≥ 1")
        if not (window > 4 * knot > 0 and every >= 1 and min_frames >= 8):
            raise ValueError(f"TipJacobianEstimator: window = {window} s must exceed 4 × knot = {knot} s > 0, "
                             f"every = {every} ≥ 1, min_frames = {min_frames} ≥ 8")
        self.camera, self.geometry = camera, (float(tip_length), int(n_elements))
        self.slope = slope
        self.sv_min, self.sv_max, self.max_coupling = sv_min, sv_max, max_coupling
        self.window, self.knot, self.every, self.min_frames = float(window), float(knot), int(every), int(min_frames)
        self.delays = np.asarray(delays, dtype=float)
        self.max_shift = float(max_shift)
        self.gain_range, self.depth_range = gain_range, depth_range
        self.min_tip_motion, self.max_gap, self.gain_ridge = min_tip_motion, max_gap, gain_ridge
        self.theta = np.array([1.0 / depth, 1.0 / depth, 1.0, 1.0])
        """(ρ_x, ρ_y, g_x, g_y): g the true per modelled tip motion per axis, ρ = g / depth (1/m)."""
        self._prior_j: np.ndarray | None = None
        self.j = np.full((2, 2), np.nan)
        """px per handle rad at the newest frame (NaN before the first frame)."""
        self.delay = math.nan
        """s, the delay of the image behind the stamps this fit uses (the tip's lag excluded): the
        median over recent windows of the best within ±``max_shift`` of the caller's; NaN before any."""
        self._caller_delay = 0.0
        self.updates = 0
        """Windows that moved θ."""
        self.rejected = 0
        """Windows whose fit was physically impossible (kept the last θ)."""
        self.explained = 0.0
        """Fraction [0, 1] of the last window's image motion (the target's smooth motion removed, outliers
        dropped) that the fitted model explains (0 for a rejected window): how well the modelled tip
        accounts for what the camera shows — a supervisor's measure of trust."""
        # Per frame: capture time, offset, modelled tip at each shift (k, 2), A and R at the frame.
        self.frames: deque[tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = deque()
        self._answers: deque[float] = deque(maxlen=answers)
        self._count = 0

    # ------------------------------------------------------------------------------------ outputs
    @property
    def depth(self) -> float:
        """Target depth (m) the fit implies (the prior before any window)."""
        return float(np.clip((self.theta[2] + self.theta[3]) / (self.theta[0] + self.theta[1]), *self.depth_range))

    @property
    def gain(self) -> np.ndarray:
        """True tip motion per modelled tip motion, per axis."""
        return self.theta[2:].copy()

    def j_tip_at(self, offset: np.ndarray, tip: np.ndarray) -> np.ndarray:
        """px per (modelled) tip rad for a target at ``offset`` (px) with the modelled tip at ``tip`` (rad)."""
        a, r = self._parts(offset, tip)
        return a * self.theta[:2] + r * self.theta[2:]

    def j_at(self, offset: np.ndarray, tip: np.ndarray) -> np.ndarray:
        """px per handle rad (bounded) for a target at ``offset`` (px) with the modelled tip at ``tip`` (rad)."""
        return self._bounded(self.j_tip_at(offset, tip) * self.slope)

    @property
    def gain_scale(self) -> float:
        """Geometric mean of the singular values of :attr:`j` (px/rad): the 'size' of J."""
        return float(math.sqrt(abs(np.linalg.det(self.j))))

    # ------------------------------------------------------------------------------------ input
    def add(self, capture_time: float, offset: np.ndarray, tip_at: Callable[[np.ndarray], np.ndarray],
            delay: float = 0.0) -> None:
        """A new frame: capture time (s), offset (px), ``tip_at(times)`` the modelled tip angles (rad,
        shape (n, 2), e.g. ``TipModel.tips_at``), ``delay`` (s) of the image behind the stamps, the
        tip's lag excluded (the model has it). Bad frames (non-finite, > 1e5 px, not newer) are ignored."""
        offset = np.asarray(offset, dtype=float)
        if not (np.all(np.isfinite(offset)) and math.isfinite(capture_time) and math.isfinite(delay)):
            return
        if np.max(np.abs(offset)) > 1e5 or (self.frames and capture_time <= self.frames[-1][0]):
            return
        # The modelled tip at every candidate delay, read now (the model keeps a few seconds): a later
        # change of the caller's delay estimate does not invalidate the frames already stored.
        tips = np.asarray(tip_at(capture_time - self.delays), dtype=float).reshape(self.delays.size, 2)
        if not np.all(np.isfinite(tips)):
            return
        self._caller_delay = float(np.clip(delay, self.delays[0], self.delays[-1]))
        centre = tips[self._nearest(self.delay if math.isfinite(self.delay) else self._caller_delay)]
        a, r = self._parts(offset, centre)
        self.frames.append((float(capture_time), offset, tips, a, r))
        while self.frames[0][0] < capture_time - self.window:
            self.frames.popleft()
        self._count += 1
        if self._count % self.every == 0 and len(self.frames) >= self.min_frames:
            self._estimate()
        # J where the target is now: the median of the last 3 offsets (one tracker outlier does not move it).
        recent = np.median(np.array([f[1] for f in list(self.frames)[-3:]]), axis=0)
        j = self.j_at(recent, centre)
        self.j = j if np.all(np.isfinite(j)) else self.j

    # ------------------------------------------------------------------------------------ fit
    def _parts(self, offset, tip):
        return image_jacobian_parts(offset, tip, camera=self.camera, tip_length=self.geometry[0],
                                    n_elements=self.geometry[1])

    def _nearest(self, delay: float) -> int:
        return int(np.argmin(np.abs(self.delays - delay)))

    @property
    def shift(self) -> float:
        """s, :attr:`delay` less the caller's latest delay (0 before any window)."""
        return self.delay - self._caller_delay if math.isfinite(self.delay) else 0.0

    def _bounded(self, j: np.ndarray) -> np.ndarray:
        if self._prior_j is None:
            self._prior_j = j.copy()                # the first J: the assumed depth and gains
        out = bound_jacobian(j, self._prior_j, sv_min=self.sv_min, sv_max=self.sv_max, max_coupling=self.max_coupling)
        return self.j if out is None else out

    def _estimate(self) -> None:
        t = np.array([f[0] for f in self.frames])
        x = np.array([f[1] for f in self.frames])
        tips = np.array([f[2] for f in self.frames])             # (n, k, 2)
        a = np.array([f[3] for f in self.frames])
        r = np.array([f[4] for f in self.frames])
        ok = np.diff(t) <= self.max_gap                          # increments across a long gap say nothing
        if np.count_nonzero(ok) < self.min_frames // 2:
            return
        mid = 0.5 * (t[1:] + t[:-1])[ok]
        dx = np.diff(x, axis=0)[ok]                              # (m, 2)
        dphi = np.diff(tips, axis=0)[ok]                         # (m, k, 2)
        a_mid = 0.5 * (a[1:] + a[:-1])[ok]                       # (m, 2, 2)
        r_mid = 0.5 * (r[1:] + r[:-1])[ok]
        q = self._smooth_basis(mid, np.diff(t)[ok])

        def residual(z):                                         # z less its projection on the smooth basis
            return z - np.tensordot(q, np.tensordot(q, z, axes=(0, 0)), axes=(1, 0))

        y = residual(dx).reshape(-1)
        fits = {}
        for c in np.flatnonzero(np.abs(self.delays - self._caller_delay) <= self.max_shift + 1e-9):
            d = dphi[:, c, :]                                    # (m, 2) modelled tip increments
            if np.any(np.sum(np.abs(residual(d)), axis=0) < self.min_tip_motion):
                return                                           # an axis' modelled tip hardly moved: no information
            m = residual(np.concatenate([a_mid * d[:, None, :], r_mid * d[:, None, :]], axis=2)).reshape(-1, 4)
            keep = np.ones(y.size, dtype=bool)
            for _ in range(2):
                theta, *_ = np.linalg.lstsq(m[keep], y[keep], rcond=None)
                res = np.abs(y - m @ theta)
                limit = 3.0 * float(np.median(res)) + 1e-9
                keep = res <= limit
            fits[int(c)] = (float(np.sum(np.minimum(res, limit) ** 2)), m, keep)
        best = min(fits, key=lambda c: fits[c][0])
        self._answers.append(float(self.delays[best]))
        self.delay = float(np.median(self._answers))
        _, m, keep = fits[min(fits, key=lambda c: abs(self.delays[c] - self.delay))]
        theta = self._common_depth(m[keep], y[keep])
        if theta is None:
            self.rejected += 1
            self.explained = 0.0
            return
        fitted = m[keep] @ theta
        self.explained = float(np.clip(1.0 - np.sum((y[keep] - fitted) ** 2) / max(float(np.sum(y[keep] ** 2)), 1e-12),
                                       0.0, 1.0))
        self.theta = theta
        self.updates += 1

    def _common_depth(self, m: np.ndarray, y: np.ndarray) -> np.ndarray | None:
        """θ with one depth for both axes (one target): for each candidate 1/Z on a log grid over
        ``depth_range`` the gains are linear least squares, the residual in closed form from the 2×2
        normal equations; the best candidate's θ, or None if its gains are not positive."""
        ma, mr = m[:, :2], m[:, 2:]
        aa, ar, rr = ma.T @ ma, ma.T @ mr, mr.T @ mr
        ay, ry = ma.T @ y, mr.T @ y
        inv = 1.0 / np.geomspace(self.depth_range[0], self.depth_range[1], 120)
        g_mat = inv[:, None, None] ** 2 * aa + inv[:, None, None] * (ar + ar.T) + rr        # (c, 2, 2)
        rhs = inv[:, None] * ay + ry                                                          # (c, 2)
        # The gains are pulled towards 1 (the model's amplitude), relative to the information: with the
        # image motion's size alone a larger gain and a larger depth fit alike.
        lam = self.gain_ridge * np.trace(g_mat, axis1=1, axis2=2)[:, None] / 2.0
        try:
            gains = np.linalg.solve(g_mat + lam[..., None] * np.eye(2), (rhs + lam)[..., None])[..., 0]
        except np.linalg.LinAlgError:
            return None
        # Cost ||y - M g||² + λ||g - 1||², up to the constant y·y.
        cost = (np.einsum("ci,cij,cj->c", gains, g_mat, gains) - 2 * np.einsum("ci,ci->c", gains, rhs)
                + lam[:, 0] * np.sum((gains - 1.0) ** 2, axis=1))
        c = int(np.argmin(cost))
        gain = gains[c]
        if not (np.all(np.isfinite(gain)) and np.all(gain > 0)):
            return None
        gain = np.clip(gain, *self.gain_range)
        return np.concatenate([gain * inv[c], gain])

    def _smooth_basis(self, t: np.ndarray, span: np.ndarray) -> np.ndarray:
        """Orthonormal basis (m, b) of what the target's own motion can add to increments at midpoints
        ``t`` (s) spanning ``span`` (s): a smooth image velocity (cubic splines in time, knots every
        ``knot`` s) times the span — frames come irregularly (jitter, drops)."""
        t0, t1 = float(t[0]), float(t[-1])
        n = max(int(math.ceil((t1 - t0) / self.knot)), 1)
        knots = np.concatenate([[t0] * 3, np.linspace(t0, t1, n + 1), [t1] * 3])
        b = BSpline.design_matrix(np.clip(t, t0, t1), knots, 3).toarray() * span[:, None]
        q, _ = np.linalg.qr(b)
        return q
