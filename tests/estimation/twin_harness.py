"""A lock on the full twin that feeds the online estimators exactly what ``adaptive`` feeds them, and
the twin's truth (oracle) they are compared with. Shared by the twin tests of this package."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from targetlock.controllers.ik import History
from targetlock.estimation import BacklashFitEstimator, DelayFitEstimator, JacobianEstimator, prior_jacobian
from targetlock.estimation.probe import nominal_width
from targetlock.estimation.tip_jacobian import TipJacobianEstimator
from targetlock.estimation.tip_model import TipModel, hysteresis_loop, triangle
from targetlock.model.endoscope import EndoscopeParams
from targetlock.model.camera import CameraParams, project, world_to_camera
from targetlock.model.kinematics import tip_pose
from targetlock.model.twin import TwinConfig, twin_config
from targetlock.rig.simulated import ObservationNoise, SimulatedRig

NOMINAL_TIP_GAIN = 90.0 / 110.0       # the controller's assumed handle -> tip gain (ControllerConfig)
STAMP_LATENCY = 0.4                   # s, the latency the rig is told (nominal knowledge)
CONTROL_DT = 0.02                     # s, the loop's 50 Hz
NOMINAL_WIDTH = nominal_width(EndoscopeParams())   # rad, the backlash the nominal scope has (knowledge)
_E = EndoscopeParams()
NOMINAL_TIP_LAG = _E.mu_f / (_E.cable_arm ** 2 * _E.cable_stiffness + _E.tip_stiffness)   # s, the nominal tip's lag


def make_twin(preset: str, distance: float, *, latency: float, jitter: float = 0.0, path: str = "ellipse",
              size: float = 0.4, frequency: float = 0.1, start_tip_deg=(-10.0, 0.0)) -> TwinConfig:
    """A twin with the target at ``distance`` (m) on a path scaled to it (``size`` × distance)."""
    return twin_config(preset, {
        "camera": {"latency": latency, "latency_jitter": jitter},
        "scene": {"path": path, "distance": distance, "ellipse_size": [size * distance, size * distance],
                  "ellipse_frequency": frequency, "start_delay": 0.5, "start_tip_deg": list(start_tip_deg)}})


def nominal_prior(motor: np.ndarray, depth: float = 0.12) -> np.ndarray:
    """The controller's prior: nominal camera and tip geometry, assumed depth (12 cm nominal)."""
    return prior_jacobian(motor, camera=CameraParams(), depth=depth, tip_gain=NOMINAL_TIP_GAIN, tip_length=0.12,
                          n_elements=30)


# ------------------------------------------------------------------------------------------- truth
def image_per_tip(twin: TwinConfig, tip: np.ndarray, target: np.ndarray, eps: float = 1e-4) -> np.ndarray:
    """d(image offset)/d(tip angles) (px/rad) of the world point ``target`` at the tip angles ``tip``."""
    e, cam = twin.endoscope, twin.camera
    base = project(world_to_camera(tip_pose(tip[0], tip[1], e.tip_length, e.n_elements), target), cam)
    out = np.empty((2, 2))
    for a in range(2):
        d = np.array(tip, dtype=float)
        d[a] += eps
        out[:, a] = (project(world_to_camera(tip_pose(d[0], d[1], e.tip_length, e.n_elements), target), cam) - base) / eps
    return out


@dataclass
class SweepTruth:
    """Measured on the twin itself by a slow handle triangle sweep per axis (quasi-static)."""
    slope: np.ndarray          # tip rad per handle rad on the moving branch, per axis
    width: np.ndarray          # handle rad lost at a reversal (horizontal width of the tip-handle loop), per axis
    tip_lag: float             # s, time constant of the tip behind the handle on the moving branch


def sweep_truth(twin: TwinConfig, amplitude: float = 0.6, rate: float = 0.2) -> SweepTruth:
    """Drive each handle axis alone in a slow triangle (``rate`` rad/s, ±``amplitude`` rad about the
    start, two cycles) and read the twin's tip angles (oracle); slope and width of the loop by
    :func:`hysteresis_loop` (the handle travel lost at a reversal, over the middle of the tip range)."""
    slope, width = np.zeros(2), np.zeros(2)
    t, tri = triangle(amplitude, rate)
    for a in range(2):
        rig = SimulatedRig(twin)
        rig.drives.home()
        start = rig.handle_angles()
        h, tip = np.empty(t.size), np.empty(t.size)
        for k, tk in enumerate(t):
            sp = start.copy()
            sp[a] += tri[k]
            rig.drives.send_setpoints(np.rint(sp / rig.drives.rad_per_tick))
            rig.advance(tk)
            h[k], tip[k] = rig.handle_angles()[a], rig.tip_angles()[a]
        slope[a], width[a] = hysteresis_loop(t, h, tip)
    k = twin.endoscope.cable_arm ** 2 * twin.endoscope.cable_stiffness
    return SweepTruth(slope=slope, width=width, tip_lag=twin.endoscope.mu_f / (k + twin.endoscope.tip_stiffness))


# ------------------------------------------------------------------------------------------- the lock
@dataclass
class Trace:
    t: list = field(default_factory=list)             # capture times (s)
    j: list = field(default_factory=list)             # estimated J
    j_true: list = field(default_factory=list)        # d offset / d tip at the pose × sweep slope (oracle)
    delay: list = field(default_factory=list)
    width: list = field(default_factory=list)
    reversals: list = field(default_factory=list)


class Lock:
    """Integral lock scheduled by the estimated J (loop gain ``loop_gain`` 1/s), feeding the estimators
    as ``controllers/adaptive.py`` does: motor at capture time minus the estimated delay from a history,
    a play operator of the estimated width, increments between frames (spanning frames when slow).

    ``jacobian="tip"``: the traced J is instead the :class:`TipJacobianEstimator`'s, fed with a
    :class:`TipModel` of the nominal scope run on the measured handle angles (its delay: the delay
    estimate less the nominal tip lag, which the model has); the RLS still runs for the other estimators."""

    def __init__(self, twin: TwinConfig, *, noise: ObservationNoise | None = None, loop_gain: float = 1.2,
                 probe=None, truth: SweepTruth | None = None, fixed_width: float | None = None,
                 fixed_delay: float | None = None, scheduled: bool = True, jac_kw: dict | None = None,
                 min_span: float = 0.0, jacobian: str = "rls", tip_endoscope: EndoscopeParams | None = None) -> None:
        self.fixed_width, self.fixed_delay, self.scheduled = fixed_width, fixed_delay, scheduled
        self.probe_start = 0.0
        self.min_span = min_span
        self.rig = SimulatedRig(twin, noise, stamp_latency=STAMP_LATENCY)
        self.rig.drives.home()
        self.twin, self.truth, self.probe = twin, truth, probe
        m = self.rig.handle_angles()
        prior = self.prior = nominal_prior(m)
        far, near = nominal_prior(m, 0.15), nominal_prior(m, 0.01)
        self.jac = JacobianEstimator(prior, sv_min=0.75 * np.linalg.svd(far, compute_uv=False).min(),
                                     sv_max=1.5 * np.linalg.svd(near, compute_uv=False).max(), **(jac_kw or {}))
        self.delay = DelayFitEstimator(initial=0.0)
        self.tip_model = self.tip_jac = None
        if jacobian == "tip":
            self.tip_model = TipModel(tip_endoscope or EndoscopeParams())      # nominal knowledge by default
            self.tip_model.reset(0.0, m)
            self.tip_jac = TipJacobianEstimator(camera=CameraParams(), tip_length=0.12, n_elements=30,
                                                slope=self.tip_model.sweep(m)[0], depth=0.12,
                                                sv_min=self.jac.sv_min, sv_max=self.jac.sv_max)
        elif jacobian != "rls":
            raise ValueError(f"Lock: jacobian = {jacobian!r}; allowed: 'rls', 'tip'")
        self.backlash = BacklashFitEstimator()
        self.history = History(3.0, CONTROL_DT)
        self.tip_history = History(3.0, CONTROL_DT)     # oracle: the twin's tip angles, for tests only
        self.frame_hooks: list = []                      # called with each valid observation after the estimators
        self.eff_history = History(3.0, CONTROL_DT)
        self.effective = m.copy()
        self.command = m.copy()
        self.loop_gain = loop_gain
        self.prev = None
        self.last_c = None
        self.trace = Trace()

    def width(self, motor):
        """Per-axis play width (handle rad): the estimate where an axis has one, else the nominal prior."""
        if self.fixed_width is not None:
            return self.fixed_width
        bend = float(np.abs(motor).sum())
        w = np.array([self.backlash.axis_width(a, bend) for a in range(2)])
        return np.where(np.isfinite(w), w, NOMINAL_WIDTH)

    def run(self, seconds: float) -> Trace:
        rig = self.rig
        n = int(round(seconds / CONTROL_DT))
        for k in range(1, n + 1):
            now = k * CONTROL_DT
            rig.advance(now)
            motor = rig.handle_angles()
            self.history.push(now, motor)
            self.tip_history.push(now, rig.tip_angles())
            if self.tip_model is not None:
                self.tip_model.update(now, motor)
            half = 0.5 * self.width(motor)
            self.effective = np.clip(self.effective, motor - half, motor + half)
            self.eff_history.push(now, self.effective)
            for obs in rig.observations.poll(now):
                if obs.valid:
                    self._observe(obs)
                    for hook in self.frame_hooks:
                        hook(obs)
            offset = self.probe.offset(now - self.probe_start) if self.probe is not None else 0.0
            lo, hi = rig.drives.limits
            sp = np.clip(np.rint((self.command + offset) / rig.drives.rad_per_tick), lo, hi)
            rig.drives.send_setpoints(sp)
        return self.trace

    def _observe(self, obs) -> None:
        x = np.asarray(obs.offset, float)
        c = float(obs.capture_time)
        d = self.delay.delay if self.fixed_delay is None else self.fixed_delay
        e_c = self.eff_history.at(c - d)
        m_c = self.history.at(c - d)
        if self.prev is None:
            self.prev = (c, x)
        tp, xp = self.prev
        dm = e_c - self.eff_history.at(tp - d)
        if c - tp >= self.min_span and (np.linalg.norm(dm) >= self.jac.min_motion or c - tp >= 0.4):
            self.jac.update(dm, x - xp, c - tp)
            self.prev = (c, x)
        self.delay.add(c, x, self.eff_history.at_many, self.jac.j)
        self.backlash.add(m_c, x, self.jac.j)
        if self.tip_jac is not None:
            self.tip_jac.add(c, x, self.tip_model.tips_at, d - NOMINAL_TIP_LAG)
        dt = 0.0 if self.last_c is None else min(max(c - self.last_c, 0.0), 0.2)
        self.last_c = c
        # integral action with the estimated J: u += k · J⁻¹ x, loop gain k (1/s)
        self.command = self.command - self.loop_gain * dt * np.linalg.solve(self.jac.j if self.scheduled else self.prior, x)
        tr = self.trace
        tr.t.append(c)
        tr.j.append((self.jac if self.tip_jac is None else self.tip_jac).j.copy())
        tr.delay.append(self.delay.delay)
        tr.width.append(self.backlash.width(float(np.abs(m_c).sum())))
        tr.reversals.append(self.backlash.reversals)
        if self.truth is not None:
            rig = self.rig
            true_t = obs.arrival_time - rig.twin.camera.latency   # oracle: when the frame was really captured
            target = rig.scene.target_position(true_t)
            tr.j_true.append(image_per_tip(self.twin, rig.tip_angles(), target) * self.truth.slope)
