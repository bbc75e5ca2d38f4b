"""Controller interface and the limits every controller applies.

A controller is a small steppable object: ``reset(motor, t)`` when the lock engages, then
``step(observation, motor, t) -> setpoint`` once per control tick. ``observation`` is the newest
observation that arrived since the previous tick (None when none did); ``motor`` is the measured
handle angle per axis (rad); the setpoint is a handle angle per axis (rad). Controllers never touch
hardware or clocks; the loop converts to ticks at the drive boundary.

The setpoint rate limit is a property of time: a controller's ``_update`` returns a new *command*
only when it has something new (a frame), ``None`` otherwise, and the setpoint keeps slewing towards
the last command at ``max_rate`` on every tick. So the same scenario gives the same result at any
loop rate (before, the held setpoint made the limit ``max_rate·fps/rate``).

A lost target (invalid observations) is held: the integrators stop, the setpoint finishes its slew to
the last command and stays there, and :meth:`Controller.lost_for` reports for how long (the run
summary counts the losses). We chose hold-and-report over a return along the last known motion: with
a 0.4 s video latency the last motion seen is 0.4 s old and, with hysteresis, an open-loop return
easily overshoots; a held tip is what a clinician expects and can recover by hand.
"""
from __future__ import annotations

import abc
import math
from dataclasses import dataclass

import numpy as np

from ..config import ConfigError, param
from ..model.endoscope import EndoscopeParams
from ..rig.base import Observation
from .knowledge import Knowledge

__all__ = ["ControllerConfig", "Controller", "CONTROLLERS"]

CONTROLLERS = ("pi", "pi-hc", "pi-hc2", "ik", "pi-smith", "adaptive")

# The integral gain each controller uses when ``i_gain`` is left at its default (tick/(px·s)): the
# report's I = 300, and I = 800 for the predictive controller, whose prediction removes the latency
# that limits PI (tuned on the report's scenarios, see docs/results.md).
DEFAULT_I_GAIN = {"pi-smith": 800.0}
REPORT_I_GAIN = 300.0


@dataclass(frozen=True)
class ControllerConfig:
    """Settings of all controllers (each reads the ones it needs)."""
    kind: str = param("adaptive", choices=CONTROLLERS, doc="controller: PI, PI + hysteresis compensation (model 1 / 2), "
                                                        "inverse kinematics, PI with latency prediction, self-calibrating (online estimation)")
    i_gain: float = param(-1.0, unit="tick/(px·s)", lo=-1.0, hi=1e5,
                          doc="integral gain I of Eq. 4.2; -1: the controller's default (300 as in the report, pi-smith 800; ik and adaptive have none)")
    p_gain: float = param(0.0, unit="tick/px", lo=0.0, hi=1e5, doc="proportional gain P of Eq. 4.2 (report: 0)")
    hc_width: float = param(0.2, lo=0.0, hi=2.0, doc="w: compensation width per measured motor angle (model 1, report: 0.2)")
    hc2_slope: float = param(0.10, lo=0.0, hi=2.0,
                             doc="model 2: compensation width (handle rad) per rad of |phi_x| + |phi_y|")
    hc2_offset_deg: float = param(9.0, unit="deg", lo=0.0, hi=90.0, doc="model 2: compensation width at zero bend")
    hc_threshold_px: float = param(10.0, unit="px", lo=0.0, hi=1000.0,
                                   doc="compensation may switch only while the target is further off centre")
    tip_gain: float = param(90.0 / 110.0, lo=0.05, hi=5.0, doc="tip angle per handle angle assumed by model-based controllers")
    ik_damping: float = param(0.7, lo=0.0, hi=0.99, doc="d of Eq. 4.6 (report: 0.7)")
    motor_delay: float = param(-1.0, unit="s", lo=-1.0, hi=5.0,
                               doc="delay of the motor position to match the video (-1: the camera latency)")
    target_prediction: float = param(1.0, lo=0.0, hi=2.0,
                                     doc="pi-smith: fraction of the latency the target's own motion is extrapolated over")
    adaptive_caution_time: float = param(2.0, unit="s", lo=0.01, hi=100.0,
                                         doc="adaptive: time constant with which that caution fades after engaging")
    adaptive_servo_gain: float = param(0.3, lo=0.01, hi=1.0, doc="adaptive: fraction of the predicted error removed per frame")
    adaptive_drift_lead: float = param(1.0, lo=0.0, hi=2.0,
                                       doc="adaptive: fraction of a clear, steady drift of the target's lag that is led (0: none)")
    adaptive_dead_travel: float = param(0.8, lo=0.0, hi=1.0,
                                        doc="adaptive: fraction of the modelled dead travel (slack, friction band) crossed at once, at most the step the offset asks for (0: none)")
    adaptive_candidates: int = param(64, lo=1, hi=256,
                                     doc="adaptive: candidate endoscopes run around the assumed one, the one that best explains the image steering (1: the assumed only)")
    adaptive_hunt_hold: float = param(15.0, unit="px", lo=0.0, hi=100.0,
                                      doc="adaptive: largest offset left alone on an image axis where the lock hunts about a resting target (0: never)")
    max_rate: float = param(1.6, unit="rad/s", lo=0.01, hi=100.0, doc="setpoint rate limit")
    max_frame_gap: float = param(0.1, unit="s", lo=0.001, hi=10.0,
                                 doc="longest frame interval integrated at once (after a loss, resume smoothly)")

    @property
    def integral_gain(self) -> float:
        """The integral gain in use (tick/(px·s)): ``i_gain``, or the controller's default for -1."""
        return DEFAULT_I_GAIN.get(self.kind, REPORT_I_GAIN) if self.i_gain == -1.0 else self.i_gain

    def check(self, prefix: str = "") -> None:
        if self.i_gain < 0.0 and self.i_gain != -1.0:
            raise ConfigError(f"{prefix}i_gain = {self.i_gain}: allowed: -1 (the controller's default) or [0, 1e5]")
        if self.kind in ("pi", "pi-hc", "pi-hc2", "pi-smith") and self.integral_gain == 0.0 and self.p_gain == 0.0:
            raise ConfigError(f"{prefix}i_gain and {prefix}p_gain are both 0: the {self.kind} controller would never move")


class Controller(abc.ABC):
    """Common limits: setpoint range, setpoint rate, hold on invalid observations."""

    def __init__(self, cfg: ControllerConfig, *, rad_per_tick: float, lower: np.ndarray, upper: np.ndarray,
                 control_dt: float, knowledge: Knowledge) -> None:
        self.cfg = cfg
        self.knowledge = knowledge          # what this controller assumes about the plant
        self.rad_per_tick = float(rad_per_tick)
        self.lower = np.asarray(lower, dtype=float)
        self.upper = np.asarray(upper, dtype=float)
        self.control_dt = float(control_dt)
        self.setpoint = np.zeros(2)
        self.command = np.zeros(2)          # last unlimited command (rad) the setpoint slews towards
        self.last_obs: Observation | None = None
        self.engaged = False
        self.last_valid_time = 0.0          # s, when the target was last seen (or the lock engaged)
        self.losses = 0                     # times the target was lost since engaging
        self._lost = False

    def reset(self, motor: np.ndarray, t: float) -> None:
        """Engage at time ``t`` (s) with the measured motor angles ``motor`` (rad): no jump."""
        self.setpoint = np.clip(np.asarray(motor, dtype=float), self.lower, self.upper)
        self.command = self.setpoint.copy()
        self.last_obs = None
        self.engaged = True
        self.last_valid_time = float(t)
        self.losses = 0
        self._lost = False
        self._reset(self.setpoint.copy(), t)

    def step(self, obs: Observation | None, motor: np.ndarray, t: float) -> np.ndarray:
        """Setpoint (rad) for this tick. Invalid or missing observations hold the integrators."""
        if not self.engaged:
            raise RuntimeError("controller stepped before reset(): engage it at the current motor position")
        motor = np.asarray(motor, dtype=float)
        usable = obs is not None and obs.valid and math.isfinite(obs.offset[0]) and math.isfinite(obs.offset[1])
        if usable:
            self.last_valid_time = float(t)
            self._lost = False
        elif obs is not None and not self._lost:
            self._lost = True
            self.losses += 1
        raw = self._update(obs if usable else None, motor, t)
        if raw is not None:
            raw = np.minimum(np.maximum(np.asarray(raw, dtype=float), self.lower), self.upper)
            if np.all(np.isfinite(raw)):
                self.command = raw   # a non-finite result keeps the previous command
        step = self.cfg.max_rate * self.control_dt
        new = np.minimum(np.maximum(self.command, self.setpoint - step), self.setpoint + step)
        new = np.minimum(np.maximum(new, self.lower), self.upper)
        self.setpoint = new
        if usable:
            self.last_obs = obs
        return new.copy()

    def lost_for(self, t: float) -> float:
        """How long (s) the target has not been seen at time ``t`` (0 while it is tracked)."""
        return float(t - self.last_valid_time) if self._lost else 0.0

    def frame_dt(self, obs: Observation) -> float:
        """Time (s) this observation's offset is integrated over: the capture interval, capped."""
        if self.last_obs is None:
            return min(self.control_dt, self.cfg.max_frame_gap)
        return float(min(max(obs.capture_time - self.last_obs.capture_time, 0.0), self.cfg.max_frame_gap))

    def signals(self) -> dict[str, float]:
        """Internal signals worth recording (e.g. the compensation), per axis."""
        return {}

    def learned_endoscope(self) -> EndoscopeParams | None:
        """The endoscope parameters this controller found steering best while it ran (e.g. ``adaptive``'s
        candidate scope), for the next run's ``knowledge.endoscope_file``; None if it identifies none."""
        return None

    @abc.abstractmethod
    def _reset(self, motor: np.ndarray, t: float) -> None: ...

    @abc.abstractmethod
    def _update(self, obs: Observation | None, motor: np.ndarray, t: float) -> np.ndarray | None:
        """New command (rad) from a usable observation, or None to keep slewing to the last one."""

    def _clamp_integrator(self, value: np.ndarray) -> np.ndarray:
        """Anti-windup: the integrator never leaves the setpoint range."""
        return np.clip(value, self.lower, self.upper)

