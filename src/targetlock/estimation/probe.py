"""A short, bounded probing motion when the lock engages (issue 9 §2), and the backlash the controller
can assume before it has measured one.

Tracking alone excites the estimators poorly: in a closed loop the motor follows the target, so the
image motion of the motor and the target's own image motion are nearly proportional (J and the
target's velocity are hard to tell apart), and a slow loop often stays inside the backlash. The probe
adds one sine cycle per handle axis to the controller's output, one axis after the other:
``offset(t) = A·sin(2π·t/T_axis)`` on axis 0 for ``t ∈ [0, T_axis)``, then on axis 1 — zero mean, two
reversals per axis, continuous, ending at zero offset (the controller's own command is then
unchanged). Its peak rate ``2π·A/T_axis`` is checked against the drive's rate limit.

Amplitude and cost. The play's state when the lock engages is unknown: if it sits at an edge, the tip
follows at once in one direction and the image moves by up to ``A·J``; if it sits in the middle, the
tip moves only once the handle has crossed half the width, by ``(A − w/2)·J``. So a probe that must
show a reversal on a scope with backlash width ``w`` needs ``A > w/2`` and may move the image by
``A·J``. :meth:`ProbeSignal.for_scope` takes ``A = w/2 + margin_px/J_near``, capped at
``max_px/J_near`` (the worst case at the nearest distance). Measured on the twin (calibrated scope,
static target, A = 0.176 rad, from the nominal width 0.237 rad and J_near = 1743 px/rad at 1 cm):
peak image excursion 358 px at 1 cm (the target left the image), 256 px at 1.5 cm, 105 px at 5 cm,
70 px at 12 cm; hysteresis leaves the tip displaced by about that much when the probe ends, which
the lock then removes (at 1.5 cm 90 px remain at 5 s). What it buys (tracking after engaging, time
until the delay estimate stays within one frame, with / without): 1.4 / 4.6 s at 5 cm, 0 / 9.9 s at
1.5 cm, 1.2 / 8.0 s at 12 cm; the backlash per axis from the probe's reversals (without it, the
12 cm x axis had no estimate after 30 s). The Jacobian is not measurably faster with it.
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
        self.crosses = True
        """False when :meth:`for_scope` had to cap the amplitude below half the assumed width."""

    @classmethod
    def for_scope(cls, width: float, j_near: float, *, margin_px: float = 100.0, max_px: float = 400.0,
                  duration: float = 2.0, max_rate: float = 1.6) -> "ProbeSignal":
        """A probe that crosses the assumed backlash ``width`` (handle rad) by ``margin_px`` of image
        motion where the image Jacobian is largest (``j_near``, px per handle rad, e.g. the prior at
        the nearest distance), so ``A = width/2 + margin_px/j_near``; capped so that the worst case
        (the play at an edge) moves the image by at most ``max_px`` there, and to what the rate limit
        allows. :attr:`crosses` says whether the capped probe still crosses the assumed width."""
        if not (width >= 0 and j_near > 0 and margin_px >= 0 and max_px >= 0):
            raise ValueError(f"ProbeSignal.for_scope: width = {width} rad must be ≥ 0, j_near = {j_near} px/rad > 0, "
                             f"margin_px = {margin_px} and max_px = {max_px} px ≥ 0")
        amplitude = min(0.5 * width + margin_px / j_near, max_px / j_near,
                        max_rate * (duration / 2.0) / (2.0 * math.pi), 1.0)
        probe = cls(amplitude, duration=duration, max_rate=max_rate)
        probe.crosses = amplitude > 0.5 * width
        return probe

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
