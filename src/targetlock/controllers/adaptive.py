"""``adaptive``: a self-calibrating lock for an unknown scope at any working distance.

It is the report's PI (I = ``i_gain``, default 300) whenever it knows nothing, and departs from PI
only as far as its own measurements justify. PI with I = 300 is right at the nominal distance
(12 cm); the image Jacobian J (px per handle rad) grows roughly as 1/distance, so at 1–2 cm PI's loop
gain is 3–5× too high (it oscillates and loses the target) and at 15 cm slightly low. So:

* the image Jacobian J is estimated while the lock runs by bounded RLS on frame-to-frame increments
  (package :mod:`targetlock.estimation`), starting from the nominal prior (the nominal camera, tip
  geometry and working distance), so the estimate starts where PI's tuning is right;
* the integral gain is scheduled as ``I · |J_nominal| / |J_estimate|`` (|·| the geometric mean of the
  singular values) — the same loop gain PI has at 12 cm, at any distance — clamped to at most
  ``adaptive_max_gain`` × I (far distances are never slower than PI and never much faster);
* a supervisor compares the image motion the model predicted between frames with what the camera
  then showed; the schedule is blended in by that trust, and at low trust (just engaged, the shaft
  moved, the tracker jumped, the estimate still converging) the gain falls back to plain PI's;
* the motion not yet seen in the image (the last video latency of motor motion) is predicted into
  the offset, a Smith predictor in image space (x + w·J·(m_now − m_capture)): just after engaging
  with a cautious Jacobian (``adaptive_cautious_depth``, fading with ``adaptive_caution_time`` and
  with trust), so the blind first move cannot overshoot by a near distance's 3–5×; and with the
  estimate, weighted by how much larger than nominal it is (0 at the nominal distance, where PI's
  tuning already accounts for the latency — a predictor without the target's motion would only add
  tracking lag there; 1 from twice the nominal Jacobian). ``adaptive_prediction`` adds trust-weighted
  prediction everywhere (off by default: it costs tracking lag on drifting targets).

The delay between the stamped capture time and the image motion (a wrongly stamped or unknown
latency) and the backlash width at reversals are estimated as well: the delay lines up the motor
increments the Jacobian is fitted to with the image increments; the backlash shapes them (a play
operator: motor motion inside the backlash does not move the tip). No hysteresis compensation is
applied: PI's direction of motion is kept, so a wrong estimate changes only the gain and the prediction.
"""
from __future__ import annotations

import math

import numpy as np

from ..estimation import BacklashEstimator, DelayEstimator, JacobianEstimator, prior_jacobian
from ..model.camera import CameraParams
from ..model.endoscope import EndoscopeParams
from ..rig.base import Observation
from .base import Controller, ControllerConfig
from .knowledge import Knowledge
from .pi import History

__all__ = ["AdaptiveController"]


TUNED_DEPTH = 0.12
"""m: the target distance at which the report chose I = 300 (§5.2); PI's gain is right there."""


class AdaptiveController(Controller):
    """PI whose integral gain is scheduled by an online image Jacobian, with a fallback to PI."""

    def __init__(self, cfg: ControllerConfig, *, knowledge: Knowledge, **kw) -> None:
        super().__init__(cfg, knowledge=knowledge, **kw)
        self.history = History(knowledge.latency + 2.0, self.control_dt)
        self.i_gain = cfg.integral_gain * self.rad_per_tick      # rad/(px·s), PI's
        self.integrator = np.zeros(2)
        self.trust = 0.0
        self.gain_factor = 1.0
        self.pair_span = 0.4              # s, longest interval between the frames of one increment pair
        self.engaged_at = 0.0

    def _prior(self, motor: np.ndarray, depth: float) -> np.ndarray:
        k = self.knowledge
        return prior_jacobian(motor, camera=k.camera, depth=depth, tip_gain=self.cfg.tip_gain,
                              tip_length=k.endoscope.tip_length, n_elements=k.endoscope.n_elements)

    def _reset(self, motor: np.ndarray, t: float) -> None:
        k, cfg = self.knowledge, self.cfg
        self.history.clear()
        self.history.push(t, motor)
        prior = self._prior(motor, k.depth)
        # px/rad where PI's I is right: the geometry the report tuned I = 300 in (12 cm, f = 300 px, its
        # scope), whatever this controller knows; with the plant's true depth (oracle) the schedule must
        # still lower the gain at 1-2 cm, not treat the true Jacobian as PI's.
        tuned = prior_jacobian(motor, camera=CameraParams(), depth=TUNED_DEPTH, tip_gain=cfg.tip_gain,
                               tip_length=EndoscopeParams().tip_length, n_elements=k.endoscope.n_elements)
        self.nominal_scale = float(math.sqrt(abs(np.linalg.det(tuned))))
        # Bounds of J: from the farthest (15 cm, 25 % margin) to the nearest (1 cm, 50 % margin) distance
        # the lock is made for; the gain clamp below is what keeps far distances PI-like.
        far = self._prior(motor, max(0.15, k.depth))
        near = self._prior(motor, min(0.01, k.depth))
        floor = 0.75 * float(np.min(np.linalg.svd(far, compute_uv=False)))
        ceiling = 1.5 * float(np.max(np.linalg.svd(near, compute_uv=False)))
        self.cautious_scale = float(math.sqrt(abs(np.linalg.det(self._prior(motor, min(cfg.adaptive_cautious_depth, k.depth))))))
        self.jacobian = JacobianEstimator(prior, sv_min=floor, sv_max=ceiling)
        self.delay = DelayEstimator(initial=0.0)
        self.backlash = BacklashEstimator()
        self.integrator = motor.copy()
        self.trust = 0.0
        self.gain_factor = 1.0
        self.engaged_at = t
        self.mismatch = 1.0               # running |residual| / |predicted motion| of the model
        self.prev: tuple[float, np.ndarray] | None = None
        # Play (backlash) operator on the motor: the part of the motor motion that moves the tip.
        e = k.endoscope
        self.nominal_width = max(2.0 * e.cable_slack / e.handle_radius, 0.0) + 0.02
        self.effective = motor.copy()
        self.effective_history = History(k.latency + 2.0, self.control_dt)
        self.effective_history.push(t, self.effective)

    def _width(self, motor: np.ndarray) -> float:
        """Backlash width (handle rad) assumed by the play operator: the estimate once a few reversals
        were seen, never more than ``adaptive_max_backlash``."""
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
        tp, xp = self.prev if self.prev is not None else (c, x)
        dm = e_c - self.effective_history.at(tp - self.delay.delay)
        # Slow motion (tracking a drifting target) moves the motor too little between two frames to
        # say anything about J: the pair then spans several frames, up to ``pair_span`` s.
        if self.prev is None or np.linalg.norm(dm) >= est.min_motion or c - tp >= self.pair_span:
            if self.prev is not None:
                predicted = est.predict(dm)
                rejected = est.rejected
                if est.update(dm, x - xp, c - tp):
                    # Supervisor: how well did the model predict the image motion of our own motion?
                    r = est.last_residual / (np.linalg.norm(predicted) + 3.0)
                    self.mismatch = 0.8 * self.mismatch + 0.2 * min(r, 3.0)
                elif est.rejected > rejected:
                    self.mismatch = 0.8 * self.mismatch + 0.2 * 3.0    # an outlier: distrust a while
            self.prev = (c, x)
        self.delay.add(c, x, self.effective_history.at_many, est.j)
        self.backlash.add(m_c, x, est.j)
        # Trust in the model: 1 while its predictions match (mismatch <= 0.3), 0 beyond 0.8.
        self.trust = float(np.clip((0.8 - self.mismatch) / 0.5, 0.0, 1.0)) if est.updates >= 5 else 0.0
        scheduled = min(self.nominal_scale / est.gain_scale, cfg.adaptive_max_gain)
        self.gain_factor = 1.0 + self.trust * (scheduled - 1.0)
        # Prediction of the motion not yet seen: with the estimate once trusted; before, with a
        # pessimistic (near-distance) Jacobian, so the blind first move cannot overshoot by far.
        caution = (1.0 - self.trust) * math.exp(-(t - self.engaged_at) / cfg.adaptive_caution_time)
        # Prediction with the estimate where it says the target is nearer than nominal (PI's gain too
        # high for its latency there): fully on from twice the nominal Jacobian; off where PI's tuning holds.
        nearer = float(np.clip(est.gain_scale / self.nominal_scale - 1.0, 0.0, 1.0))
        weight = caution * self.cautious_scale / est.gain_scale + max(cfg.adaptive_prediction * self.trust, nearer)
        x_now = x + weight * est.predict(self.effective - e_c)
        step = self.gain_factor * self.i_gain * x_now * self.frame_dt(obs)
        self.integrator = self._clamp_integrator(self.integrator + step)
        return self.integrator

    def signals(self) -> dict[str, float]:
        """Per axis: the estimated image Jacobian's direct terms (px per handle rad), the trust and the
        integral gain in use relative to PI's."""
        if not self.engaged:
            return {"jacobian_x_px_per_rad": math.nan, "jacobian_y_px_per_rad": math.nan, "trust": math.nan,
                    "gain_factor": math.nan}
        j = self.jacobian.j
        return {"jacobian_x_px_per_rad": abs(float(j[0, 0])), "jacobian_y_px_per_rad": abs(float(j[1, 1])),
                "trust": self.trust, "gain_factor": self.gain_factor}
