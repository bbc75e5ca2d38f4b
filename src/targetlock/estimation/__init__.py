"""Online estimation of what the controller needs to know, from what a real rig has: the measured
motor (handle) angles and the tracker's observations (offset, capture time).

Sits between :mod:`targetlock.model` and :mod:`targetlock.controllers`: it may use the model (for
priors), controllers use it, never the reverse. Every estimator is bounded and sanity-checked: its
output stays within stated physical limits whatever the input (noise, dropped frames, outliers).

* :class:`JacobianEstimator` — image Jacobian, px of target motion per handle rad, 2×2 (cross
  coupling included; it carries the working distance, the camera and the handle gain);
  :class:`TipJacobianEstimator` the same relative to a :class:`TipModel`'s tip, position-dependent
  through the camera model (translation and rotation parts, one target depth), by windowed least squares;
* :class:`DelayEstimator` — the delay between the motor motion and the image motion it causes,
  relative to the frames' capture time stamps (a wrongly stamped or unknown video latency);
  :class:`DelayFitEstimator` the same by an output-error fit that a closed loop does not bias;
* :class:`BacklashEstimator` — the motor travel lost at each reversal before the image follows
  (deadband / backlash width) and its growth with bending; :class:`BacklashFitEstimator` the same per
  axis by fitting a play operator (robust to the target's own motion); :func:`nominal_width` its prior;
* :class:`DepthEstimator` — the target depth, from the Jacobian's size and (where observable) the
  tracker's scale;
* :class:`DriftEstimator` — the target's own image velocity (px/s), reported only when it is a clear,
  steady drift;
* :class:`ProbeSignal` — a short bounded handle excitation for the first ≤ 2 s after engaging;
* :class:`TipModel` — the assumed (nominal) endoscope run online on the measured handle angles:
  modelled tip angles with hysteresis and stick-slip, and their recent history; several candidate
  scopes side by side (:func:`scope_candidates`), of which :class:`ScopeSelector` picks the one whose
  motion best explains the image.
"""
from __future__ import annotations

from .backlash import BacklashEstimator, BacklashFitEstimator
from .delay import DelayEstimator, DelayFitEstimator
from .depth import DepthEstimator
from .drift import DriftEstimator
from .jacobian import JacobianEstimator, prior_jacobian
from .probe import ProbeSignal, nominal_width
from .scope_bank import ScopeSelector, scope_candidates
from .tip_jacobian import TipJacobianEstimator, image_jacobian_parts
from .tip_model import TipModel

__all__ = ["JacobianEstimator", "prior_jacobian", "DelayEstimator", "DelayFitEstimator", "BacklashEstimator",
           "BacklashFitEstimator", "DepthEstimator", "DriftEstimator",
           "ProbeSignal", "nominal_width", "TipModel", "TipJacobianEstimator",
           "image_jacobian_parts", "ScopeSelector", "scope_candidates"]
