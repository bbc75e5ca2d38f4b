"""``adaptive``: a self-calibrating lock for an unknown scope at any working distance.

It assumes almost nothing: the nominal camera and tip geometry give only a *prior* image Jacobian,
deliberately taken at a short distance (``adaptive_prior_depth``, default 3 cm: a large Jacobian
means a small, safe gain). While the lock runs it estimates (package :mod:`targetlock.estimation`):

* the image Jacobian J (px per handle rad, 2×2) by bounded RLS on frame-to-frame increments —
  this carries the working distance, the focal length and the handle gain, so the loop gain is
  scheduled by it (an integral gain of ``K·J⁻¹``: the same closed-loop bandwidth at 1 cm and 15 cm);
* the delay between the stamped capture time and the image motion (wrong or unknown latency);
* the backlash width at reversals (bend dependent). It shapes the motor signal the Jacobian is fitted
  to (a play operator: motor motion inside the backlash does not move the tip). A backlash inverse
  (``adaptive_backlash`` × half the width, in the direction of motion) is available but off by
  default: on the robustness benchmark an overestimated width made it cycle at rest, which cost more
  than the compensation gained.

On each frame the offset is predicted to now with the estimated model (a Smith predictor in image
space: x + J·(m_now − m_capture)), and integrated with gain ``K``. A supervisor compares the
image motion the model predicted between frames with what the camera then showed; while they
disagree (just engaged, the shaft moved, the tracker jumped, the scope is unlike the prior) the
prediction is faded out and the gain falls back to a conservative integral gain
``adaptive_safe_gain / (latency + frame interval)`` — PI tuned for the estimated delay.
"""
from __future__ import annotations

import math

import numpy as np

from ..estimation import BacklashEstimator, DelayEstimator, JacobianEstimator, prior_jacobian
from ..rig.base import Observation
from .base import Controller, ControllerConfig
from .knowledge import Knowledge
from .pi import History

__all__ = ["AdaptiveController"]


class AdaptiveController(Controller):
    """Gain-scheduled, latency-predicting, backlash-compensating integral lock with a fallback."""

    def __init__(self, cfg: ControllerConfig, *, knowledge: Knowledge, **kw) -> None:
        super().__init__(cfg, knowledge=knowledge, **kw)
        self.history = History(knowledge.latency + 2.0, self.control_dt)
        self.integrator = np.zeros(2)
        self.compensation = np.zeros(2)
        self.trust = 0.0

    def _reset(self, motor: np.ndarray, t: float) -> None:
        k, cfg = self.knowledge, self.cfg
        self.history.clear()
        self.history.push(t, motor)
        prior = prior_jacobian(motor, camera=k.camera, depth=min(cfg.adaptive_prior_depth, k.depth),
                               tip_gain=cfg.tip_gain, tip_length=k.endoscope.tip_length,
                               n_elements=k.endoscope.n_elements)
        # Floor of J: the Jacobian at the farthest working distance (15 cm) with 25 % margin, so the
        # scheduled gain is never higher than a correct one at any distance the lock is made for.
        far = prior_jacobian(motor, camera=k.camera, depth=max(0.15, k.depth), tip_gain=cfg.tip_gain,
                             tip_length=k.endoscope.tip_length, n_elements=k.endoscope.n_elements)
        near = prior_jacobian(motor, camera=k.camera, depth=min(0.01, k.depth), tip_gain=cfg.tip_gain,
                              tip_length=k.endoscope.tip_length, n_elements=k.endoscope.n_elements)
        floor = 0.75 * float(np.min(np.linalg.svd(far, compute_uv=False)))
        ceiling = 1.5 * float(np.max(np.linalg.svd(near, compute_uv=False)))
        self.jacobian = JacobianEstimator(prior, sv_min=floor, sv_max=ceiling)
        self.delay = DelayEstimator(initial=0.0)
        self.backlash = BacklashEstimator()
        self.integrator = motor.copy()
        self.compensation = np.zeros(2)
        self.direction = np.zeros(2)
        self.trust = 0.0
        self.mismatch = 1.0               # running |residual| / |predicted motion| of the model
        self.prev: tuple[float, np.ndarray] | None = None
        # Play (backlash) operator on the motor: the part of the motor motion that moves the tip.
        e = k.endoscope
        self.nominal_width = max(2.0 * e.cable_slack / e.handle_radius, 0.0) + 0.02
        self.effective = motor.copy()
        self.effective_history = History(k.latency + 2.0, self.control_dt)
        self.effective_history.push(t, self.effective)
        self.frame_interval = 1.0 / max(k.camera.fps, 1.0)

    def _width(self, motor: np.ndarray) -> float:
        """Backlash width (handle rad) assumed now: the estimate once a few reversals were seen,
        never more than ``adaptive_max_backlash`` (an overestimate makes the compensation cycle)."""
        if self.backlash.reversals >= 3:
            return min(self.backlash.width(float(np.abs(motor).sum())), self.cfg.adaptive_max_backlash)
        return min(self.nominal_width, self.cfg.adaptive_max_backlash)

    def _update(self, obs: Observation | None, motor: np.ndarray, t: float) -> np.ndarray | None:
        self.history.push(t, motor)
        half = 0.5 * self._width(motor)
        self.effective = np.clip(self.effective, motor - half, motor + half)
        self.effective_history.push(t, self.effective)
        if obs is None:
            return None
        cfg = self.cfg
        x = np.asarray(obs.offset, dtype=float)
        c = float(obs.capture_time)
        m_c = self.history.at(c - self.delay.delay)
        e_c = self.effective_history.at(c - self.delay.delay)
        est = self.jacobian
        if self.prev is not None:
            tp, xp = self.prev
            dm = e_c - self.effective_history.at(tp - self.delay.delay)
            predicted = est.predict(dm)
            rejected = est.rejected
            if est.update(dm, x - xp, c - tp):
                # Supervisor: how well did the model predict the image motion of our own motion?
                r = est.last_residual / (np.linalg.norm(predicted) + 3.0)
                self.mismatch = 0.8 * self.mismatch + 0.2 * min(r, 3.0)
            elif est.rejected > rejected:
                self.mismatch = 0.8 * self.mismatch + 0.2 * 3.0    # rejected as an outlier: distrust a while
        self.prev = (c, x)
        self.delay.add(c, x, self.effective_history.at_many, est.j)
        self.backlash.add(m_c, x, est.j)
        # Trust in the model: 1 while its predictions match (mismatch <= 0.3), 0 beyond 0.8.
        self.trust = float(np.clip((0.8 - self.mismatch) / 0.5, 0.0, 1.0)) if est.updates >= 5 else 0.0
        x_now = x + self.trust * est.predict(self.effective - e_c)   # Smith prediction to now
        age = max(t - c, 0.0) + max(self.delay.delay, 0.0)         # what the video hides from us (s)
        k_safe = cfg.adaptive_safe_gain / (age + self.frame_interval + 0.05)
        k = k_safe + self.trust * max(cfg.adaptive_gain - k_safe, 0.0)
        dt = self.frame_dt(obs)
        step = -k * np.linalg.solve(est.j, x_now) * dt
        self.integrator = self._clamp_integrator(self.integrator + step)
        # Backlash inverse: half the estimated width in the direction of the integrator's motion.
        moving = np.abs(step) > 1e-6
        self.direction = np.where(moving, np.sign(step), self.direction)
        self.compensation = 0.5 * self._width(motor) * self.direction * cfg.adaptive_backlash
        return self.integrator + self.compensation

    def signals(self) -> dict[str, float]:
        """Per axis: the estimated image Jacobian's direct terms (px per handle rad), then the trust."""
        if not self.engaged:
            return {"jacobian_x_px_per_rad": math.nan, "jacobian_y_px_per_rad": math.nan, "trust": math.nan}
        j = self.jacobian.j
        return {"jacobian_x_px_per_rad": abs(float(j[0, 0])), "jacobian_y_px_per_rad": abs(float(j[1, 1])),
                "trust": self.trust}
