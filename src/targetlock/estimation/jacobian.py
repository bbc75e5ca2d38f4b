"""Image Jacobian by recursive least squares with forgetting (uncalibrated visual servoing).

Model between two frames k-1, k (capture-time motor angles m, image offsets x, capture times t):

    x_k - x_{k-1} = J · (m_k - m_{k-1}) + v · (t_k - t_{k-1}) + noise

J (px/rad, 2×2) and the target's own image velocity v (px/s, slowly varying) are estimated together
row-wise by RLS with exponential forgetting — without v, a moving target followed in closed loop
biases J towards zero (the motor moves *because* the image moves), which would make any gain
scheduled by J too high. Pairs where the motor moved but the image did
not (a stuck tip: friction, backlash) update only v — they say nothing about J, and reading them as
a small J would make the loop gain too high. Safeguards: Huber-clipped residuals at a multiple of their running scale and
outright rejection of very large ones (tracker outliers, target jumps); the covariance kept within
bounds (no wind-up without excitation); the singular values of J kept within [sv_min, sv_max] and its
orientation (sign of the determinant and of the diagonal) that of the prior, the cross coupling at
most ``max_coupling`` of the direct effect, and each update's relative change of J
capped — a physically impossible estimate is never
handed to a controller.
"""
from __future__ import annotations

import math

import numpy as np

from ..model.camera import CameraParams, project, unproject
from ..model.kinematics import tip_pose

__all__ = ["JacobianEstimator", "prior_jacobian", "bound_jacobian"]


def prior_jacobian(motor: np.ndarray, *, camera: CameraParams, depth: float, tip_gain: float, tip_length: float,
                   n_elements: int, eps: float = 1e-3) -> np.ndarray:
    """J (px per handle rad) of a point on the optical axis at ``depth`` (m), from the kinematics with
    the assumed tip gain: the prior the estimator starts from."""
    phi = tip_gain * np.asarray(motor, dtype=float)
    pose = tip_pose(phi[0], phi[1], tip_length, n_elements)
    p_world = pose[:3, :3] @ unproject(np.array([camera.cx, camera.cy]), depth, camera, distort=False) + pose[:3, 3]
    j = np.empty((2, 2))
    for a in range(2):
        d = np.zeros(2)
        d[a] = eps * tip_gain
        pose_d = tip_pose(phi[0] + d[0], phi[1] + d[1], tip_length, n_elements)
        pc = pose_d[:3, :3].T @ (p_world - pose_d[:3, 3])
        j[:, a] = (project(pc, camera, distort=False) - (camera.cx, camera.cy)) / eps
    return j


def bound_jacobian(j: np.ndarray, prior: np.ndarray, *, sv_min: float, sv_max: float,
                   max_coupling: float) -> np.ndarray | None:
    """``j`` (px/rad, 2×2) made physically possible, or None if it cannot be: each handle axis moves
    the image mostly along the axis the ``prior`` says (same sign of the direct term, the cross term at
    most ``max_coupling`` of it: the bending planes are the image axes, up to a moderate coupling when
    both axes are bent), singular values within [``sv_min``, ``sv_max``], not mirrored against the prior."""
    j = np.array(j, dtype=float)
    if not np.all(np.isfinite(j)):
        return None
    diag_p = np.diag(prior)
    for a in range(2):
        if np.sign(j[a, a]) != np.sign(diag_p[a]):
            return None
        b = 1 - a
        j[b, a] = np.clip(j[b, a], -max_coupling * abs(j[a, a]), max_coupling * abs(j[a, a]))
    u, s, vt = np.linalg.svd(j)
    out = (u * np.clip(s, sv_min, sv_max)) @ vt
    det_p = np.linalg.det(prior)
    if math.copysign(1.0, np.linalg.det(out)) != (math.copysign(1.0, det_p) if det_p != 0 else 1.0):
        return None                              # mirrored image: impossible
    return out


class JacobianEstimator:
    """Bounded RLS estimate of the image Jacobian J (px/rad) and the target's image velocity (px/s)."""

    def __init__(self, prior: np.ndarray, *, forgetting: float = 0.97, prior_weight: float = 1e-4,
                 sv_min: float = 50.0, sv_max: float = 8000.0, min_motion: float = 1e-3, huber: float = 3.0,
                 max_change: float = 0.1, min_image_motion: float = 3.0, max_coupling: float = 0.5,
                 max_growth: float = 0.6, growth_ratio: float = 1.2) -> None:
        self.j = np.array(prior, dtype=float)
        self.prior = self.j.copy()
        self.max_coupling = max_coupling
        self.velocity = np.zeros(2)                        # px/s
        self.p = np.diag([1.0 / prior_weight, 1.0 / prior_weight, 100.0])
        self.forgetting = forgetting
        self.sv_min, self.sv_max = sv_min, sv_max
        self.min_motion = min_motion
        self.max_change = max_change                       # largest relative change of J per update
        # A pair whose image moved clearly further along the predicted motion than J predicts (more
        # than ``growth_ratio`` times, little sideways) says J is too small: it is neither clipped nor
        # rejected as an outlier, and J may grow by ``max_growth`` on it (see :meth:`update`).
        self.max_growth = max_growth
        self.growth_ratio = growth_ratio
        self.min_image_motion = min_image_motion           # px: less, and the tip is taken as stuck
        self.huber = huber
        self.scale = 10.0                                  # running scale of the residual (px)
        self.updates = 0
        self.rejected = 0
        self.last_residual = 0.0                           # px, a priori, of the newest pair
        # What the pairs say of J's size against the prior, by themselves (no fit, no velocity): over the
        # pairs for which the prior predicts at least ``ratio_min_px`` of image motion, the image motion
        # seen along that prediction (px, summed; a pair that moved backwards adds nothing) and the largest
        # ratio of it to the prediction (see :meth:`size_bound`).
        self.ratio_min_px = 1.0
        self.seen_along_prior = 0.0
        self.largest_ratio = 0.0

    def predict(self, dm: np.ndarray) -> np.ndarray:
        """Image motion (px) the motor motion ``dm`` (rad) should cause."""
        return self.j @ np.asarray(dm, dtype=float)

    def update(self, dm: np.ndarray, dx: np.ndarray, dt: float) -> bool:
        """One pair of increments: motor ``dm`` (rad), image ``dx`` (px) over ``dt`` (s). True if used
        to update J (a pair without motor motion only updates the target velocity)."""
        dm = np.asarray(dm, dtype=float)
        dx = np.asarray(dx, dtype=float)
        if not (np.all(np.isfinite(dm)) and np.all(np.isfinite(dx)) and math.isfinite(dt)) or dt <= 0 or dt > 0.5:
            return False
        if np.max(np.abs(dx)) > 1e5 or np.max(np.abs(dm)) > 10.0:
            self.rejected += 1                   # implausible: no image or handle moves that far between frames
            return False
        self._note_ratio(dm, dx)
        pred = self.j @ dm
        own = dx - self.velocity * dt            # the image motion less the target's own
        r = dx - pred - self.velocity * dt
        rn = float(np.linalg.norm(r))
        self.last_residual = rn
        limit = self.huber * self.scale
        growth = self._says_too_small(pred, own)
        if growth:
            limit = max(limit, rn)
        if rn > 4.0 * limit and self.updates > 5:
            self.rejected += 1                   # a tracker outlier or a jump of the target: not the scope
            self.scale = min(self.scale * 1.1, 200.0)
            return False
        if rn > limit:
            r = r * (limit / rn)
        self.scale = min(max(0.95 * self.scale + 0.05 * min(rn, limit), 1.0), 200.0)
        excited = bool(np.linalg.norm(dm) >= self.min_motion)
        if np.linalg.norm(own) < self.min_image_motion:
            # The image did not follow the motor: the tip sticks (friction, backlash), it does not say
            # J is small. Only the target's velocity learns from this pair (selection biases J up: safe).
            excited = False
            dm = np.zeros(2)
            r = own
        phi = np.array([dm[0], dm[1], dt])
        pm = self.p @ phi
        gain = pm / (self.forgetting + phi @ pm)
        theta = np.column_stack([self.j, self.velocity]) + np.outer(r, gain)
        p = (self.p - np.outer(gain, pm)) / (self.forgetting if excited else 1.0)
        w, v = np.linalg.eigh(0.5 * (p + p.T))
        self.p = (v * np.clip(w, 1e-3, 1e7)) @ v.T       # bounded: no wind-up without excitation
        self.velocity = np.clip(theta[:, 2], -2000.0, 2000.0)
        if excited:
            self.j = self._bounded(theta[:, :2], grow=growth)
            self.updates += 1
        return bool(excited)

    def _note_ratio(self, dm: np.ndarray, dx: np.ndarray) -> None:
        """Add a pair (motor ``dm`` rad, image ``dx`` px) to :attr:`seen_along_prior` and
        :attr:`largest_ratio` if the prior predicts at least ``ratio_min_px`` of image motion for it."""
        p = self.prior @ dm
        size = float(np.linalg.norm(p))
        if size < self.ratio_min_px:
            return
        ratio = float(dx @ p) / (size * size)
        self.seen_along_prior += max(ratio, 0.0) * size
        self.largest_ratio = max(self.largest_ratio, ratio)

    def size_bound(self, seen_px: float, margin: float) -> float | None:
        """An upper bound on the size of J (px/rad, as :attr:`gain_scale`) from the pairs alone, once
        ``seen_px`` of image motion has been seen along the prior's predictions: ``margin`` times the
        largest ratio of seen to predicted motion of any pair, times the prior's size; None before.

        A tip that sticks (friction, slack) moves the image less than J predicts, and one that breaks free
        catches up in a jump, further than J predicts: so the largest ratio over many pairs overestimates
        J rather than underestimates it, unlike a fit, which the sticking pairs pull down (near the
        target, J ends 3x too small). It needs no fit and no velocity: right after engaging, when the
        fit has too few pairs to be trusted and a slow approach's motion is taken up by the target's
        estimated velocity, it already says that a far target's J is about the prior's."""
        if self.seen_along_prior < seen_px or self.largest_ratio <= 0.0:
            return None
        return margin * self.largest_ratio * float(math.sqrt(abs(np.linalg.det(self.prior))))

    def _says_too_small(self, pred: np.ndarray, own: np.ndarray) -> bool:
        """True if the image motion ``own`` (px, the target's velocity removed) went more than
        ``growth_ratio`` times as far along ``pred``, the motion J predicts for the pair's motor motion
        (px, at least 1 px), as ``pred`` itself, with less than half of it sideways.

        Near the target the prior (the assumed depth) is 2-4x too small, and the tip's stick-slip
        shows it in the jumps at break-free, which the Huber clip and the outlier rule above kept out
        of J: J grew by 10 % per pair at most, too slowly for the seconds before the caution had faded
        (a near drift swung +-90 px with J at half its value). A jump sets the whole catch-up against
        one pair's motion, so under stick-slip J ends too large (1.75x in the estimator test), and a
        target's own jump along our motion inflates it too. Erring this way is safe: a larger J means
        smaller steps; J shrinks back at ``max_change`` per pair."""
        pp = float(pred @ pred)
        if pp < 1.0:
            return False
        ratio = float(own @ pred) / pp
        return ratio > self.growth_ratio and float(np.linalg.norm(own - ratio * pred)) < 0.5 * float(np.linalg.norm(own))

    def _bounded(self, j: np.ndarray, grow: bool = False) -> np.ndarray:
        """``j`` within ``max_change`` (relative) of the current J — ``max_growth`` where ``grow``
        and ``j`` is larger — and within :func:`bound_jacobian`'s bounds; the current J if impossible."""
        if not np.all(np.isfinite(j)):
            return self.j
        # J changes slowly in truth (distance, bend): one pair may move it by max_change at most.
        step = j - self.j
        size = float(np.linalg.norm(self.j))
        most = max(self.max_growth, self.max_change) if grow and np.linalg.norm(j) > size else self.max_change
        if np.linalg.norm(step) > most * size:
            j = self.j + step * (most * size / np.linalg.norm(step))
        out = bound_jacobian(j, self.prior, sv_min=self.sv_min, sv_max=self.sv_max, max_coupling=self.max_coupling)
        return self.j if out is None else out

    def rescale(self, columns: np.ndarray) -> None:
        """Carry J over to a motor-side unit that differs per axis: its columns times ``columns`` (2,),
        bounded as every estimate is (e.g. when the modelled tip motion J relates to is replaced)."""
        out = bound_jacobian(self.j * np.asarray(columns, dtype=float)[None, :], self.prior, sv_min=self.sv_min,
                             sv_max=self.sv_max, max_coupling=self.max_coupling)
        if out is not None:
            self.j = out

    @property
    def gain_scale(self) -> float:
        """Geometric mean of the singular values (px/rad): the 'size' of J."""
        return float(math.sqrt(abs(np.linalg.det(self.j))))
