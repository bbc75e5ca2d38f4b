"""A short, bounded probing motion when the lock engages (issue 9 §2), and the backlash the controller
can assume before it has measured one.

Tracking alone excites the estimators poorly: in a closed loop the motor follows the target, so the
image motion of the motor and the target's own image motion are nearly proportional (J and the
target's velocity are hard to tell apart), and a slow loop often stays inside the backlash. The probe
adds one sine cycle per handle axis to the controller's output, one axis after the other:
``offset(t) = A·sin(2π·t/T_axis)`` on axis 0 for ``t ∈ [0, T_axis)``, then on axis 1 — zero mean, two
reversals per axis, continuous, ending at zero offset (the controller's own command is then
unchanged). Its amplitude ``A = width/2 + max_px/J_near`` crosses the assumed backlash width and then
moves the image by at most ``max_px`` at the nearest working distance (J_near px/rad); its peak rate
``2π·A/T_axis`` is checked against the drive's rate limit.

Cost to the user: for ``duration`` s (≤ 2 s) after engaging the tip moves up to ``max_px`` (less at
farther distances, nothing more if the true backlash is wider than assumed) on top of the lock's own
correction; the lock's correction is not delayed (the probe is added, not substituted).
"""
from __future__ import annotations

import math

import numpy as np

from ..model.endoscope import EndoscopeParams

__all__ = ["ProbeSignal", "nominal_width"]


def nominal_width(e: EndoscopeParams, bend: float = 0.3) -> float:
    """Handle travel (rad) lost at a reversal of the endoscope ``e`` at tip bend ``bend`` (rad,
    |Φx| + |Φy|), quasi-statically: the slack of both cables (2·s0/r_h, none with pretension) plus
    the cable stretch needed to turn the tip's Coulomb friction around (2·N/(c·K_c·r_h), N from the
    model's friction law). A prior from the assumed (nominal) scope, not a measurement; within
    about 20 % of the hysteresis loop of the twin's presets."""
    normal = e.mu_n * (bend + e.friction_offset) if e.friction_model == "both-angles" else e.mu_n * bend
    slack = 2.0 * max(e.cable_slack, 0.0) / e.handle_radius
    return slack + 2.0 * normal / (e.cable_arm * e.cable_stiffness * e.handle_radius)


class ProbeSignal:
    """Bounded engage probe: a handle offset (rad, per axis) to add to the controller's output."""

    def __init__(self, amplitude: float, *, duration: float = 2.0, max_rate: float = 1.6) -> None:
        if not 0.0 < duration <= 2.0:
            raise ValueError(f"ProbeSignal: duration = {duration} s; allowed: (0, 2] s")
        if not 0.0 <= amplitude <= 1.0:
            raise ValueError(f"ProbeSignal: amplitude = {amplitude} rad; allowed: [0, 1] rad (handle)")
        self.duration = float(duration)
        self.axis_time = self.duration / 2.0
        rate = 2.0 * math.pi * amplitude / self.axis_time
        if rate > max_rate:
            raise ValueError(f"ProbeSignal: amplitude = {amplitude} rad over {self.axis_time} s per axis needs "
                             f"{rate:.2f} rad/s; allowed: at most max_rate = {max_rate} rad/s")
        self.amplitude = float(amplitude)

    @classmethod
    def for_scope(cls, width: float, j_near: float, *, max_px: float = 60.0, duration: float = 2.0,
                  max_rate: float = 1.6) -> "ProbeSignal":
        """A probe that crosses the assumed backlash ``width`` (handle rad) and then moves the image by
        at most ``max_px`` where the image Jacobian is largest (``j_near``, px per handle rad, e.g.
        the prior at the nearest distance); the amplitude is cut to what the rate limit allows."""
        if not (width >= 0 and j_near > 0 and max_px >= 0):
            raise ValueError(f"ProbeSignal.for_scope: width = {width} rad must be ≥ 0, j_near = {j_near} px/rad > 0, "
                             f"max_px = {max_px} px ≥ 0")
        amplitude = 0.5 * width + max_px / j_near
        amplitude = min(amplitude, max_rate * (duration / 2.0) / (2.0 * math.pi), 1.0)
        return cls(amplitude, duration=duration, max_rate=max_rate)

    def offset(self, t: float) -> np.ndarray:
        """Handle offset (rad, shape (2,)) at ``t`` s since engaging; zero before 0 and after ``duration``."""
        out = np.zeros(2)
        if not 0.0 <= t < self.duration:
            return out
        axis = 0 if t < self.axis_time else 1
        out[axis] = self.amplitude * math.sin(2.0 * math.pi * (t - axis * self.axis_time) / self.axis_time)
        return out

    def done(self, t: float) -> bool:
        """True once the probe is over (``t`` s since engaging)."""
        return t >= self.duration
