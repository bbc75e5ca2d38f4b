"""Controller interface and the limits every controller applies.

A controller is a small steppable object: ``reset(motor, t)`` when the lock engages, then
``step(observation, motor, t) -> setpoint`` once per control tick. ``observation`` is the newest
observation that arrived since the previous tick (None when none did); ``motor`` is the measured
handle angle per axis (rad); the setpoint is a handle angle per axis (rad). Controllers never touch
hardware or clocks; the loop converts to ticks at the drive boundary.
"""
from __future__ import annotations

import abc
import math
from dataclasses import dataclass

import numpy as np

from ..config import ConfigError, param
from ..rig.base import Observation

__all__ = ["ControllerConfig", "Controller", "CONTROLLERS"]

CONTROLLERS = ("pi", "pi-hc", "pi-hc2", "ik", "pi-smith")


@dataclass(frozen=True)
class ControllerConfig:
    """Settings of all controllers (each reads the ones it needs)."""
    kind: str = param("pi-hc", choices=CONTROLLERS, doc="controller: PI, PI + hysteresis compensation (model 1 / 2), "
                                                        "inverse kinematics, PI with latency prediction")
    i_gain: float = param(300.0, unit="tick/(px·s)", lo=0.0, hi=1e5, doc="integral gain I of Eq. 4.2 (report: 300)")
    p_gain: float = param(0.0, unit="tick/px", lo=0.0, hi=1e5, doc="proportional gain P of Eq. 4.2 (report: 0)")
    hc_width: float = param(0.2, lo=0.0, hi=2.0, doc="w: compensation width per measured motor angle (model 1, report: 0.2)")
    hc2_slope: float = param(0.10, lo=0.0, hi=2.0,
                             doc="model 2: compensation width (handle rad) per rad of |phi_x| + |phi_y|")
    hc2_offset_deg: float = param(9.0, unit="deg", lo=0.0, hi=90.0, doc="model 2: compensation width at zero bend")
    hc_threshold_px: float = param(10.0, unit="px", lo=0.0, hi=1000.0,
                                   doc="compensation may switch only while the target is further off centre")
    tip_gain: float = param(90.0 / 110.0, lo=0.05, hi=5.0, doc="tip angle per handle angle assumed by model-based controllers")
    ik_depth: float = param(0.12, unit="m", lo=0.005, hi=2.0, doc="assumed target distance for inverse kinematics (report: 12 cm)")
    ik_damping: float = param(0.7, lo=0.0, hi=0.99, doc="d of Eq. 4.6 (report: 0.7)")
    motor_delay: float = param(-1.0, unit="s", lo=-1.0, hi=5.0,
                               doc="delay of the motor position to match the video (-1: the camera latency)")
    target_prediction: float = param(1.0, lo=0.0, hi=2.0,
                                     doc="pi-smith: fraction of the latency the target's own motion is extrapolated over")
    max_rate: float = param(1.6, unit="rad/s", lo=0.01, hi=100.0, doc="setpoint rate limit")
    max_frame_gap: float = param(0.1, unit="s", lo=0.001, hi=10.0,
                                 doc="longest frame interval integrated at once (after a loss, resume smoothly)")

    def check(self, prefix: str = "") -> None:
        if self.kind in ("pi", "pi-hc", "pi-hc2", "pi-smith") and self.i_gain == 0.0 and self.p_gain == 0.0:
            raise ConfigError(f"{prefix}i_gain and {prefix}p_gain are both 0: the {self.kind} controller would never move")


class Controller(abc.ABC):
    """Common limits: setpoint range, setpoint rate, hold on invalid observations."""

    def __init__(self, cfg: ControllerConfig, *, rad_per_tick: float, lower: np.ndarray, upper: np.ndarray,
                 control_dt: float) -> None:
        self.cfg = cfg
        self.rad_per_tick = float(rad_per_tick)
        self.lower = np.asarray(lower, dtype=float)
        self.upper = np.asarray(upper, dtype=float)
        self.control_dt = float(control_dt)
        self.setpoint = np.zeros(2)
        self.last_obs: Observation | None = None
        self.engaged = False

    def reset(self, motor: np.ndarray, t: float) -> None:
        """Engage at time ``t`` (s) with the measured motor angles ``motor`` (rad): no jump."""
        self.setpoint = np.clip(np.asarray(motor, dtype=float), self.lower, self.upper)
        self.last_obs = None
        self.engaged = True
        self._reset(self.setpoint.copy(), t)

    def step(self, obs: Observation | None, motor: np.ndarray, t: float) -> np.ndarray:
        """Setpoint (rad) for this tick. Invalid or missing observations hold the integrators."""
        if not self.engaged:
            raise RuntimeError("controller stepped before reset(): engage it at the current motor position")
        motor = np.asarray(motor, dtype=float)
        usable = obs is not None and obs.valid and math.isfinite(obs.offset[0]) and math.isfinite(obs.offset[1])
        raw = self._update(obs if usable else None, motor, t)
        if not np.all(np.isfinite(raw)):
            raw = self.setpoint  # a non-finite result holds the last setpoint
        step = self.cfg.max_rate * self.control_dt
        new = np.minimum(np.maximum(raw, self.setpoint - step), self.setpoint + step)
        new = np.minimum(np.maximum(new, self.lower), self.upper)
        self.setpoint = new
        if usable:
            self.last_obs = obs
        return new.copy()

    def frame_dt(self, obs: Observation) -> float:
        """Time (s) this observation's offset is integrated over: the capture interval, capped."""
        if self.last_obs is None:
            return min(self.control_dt, self.cfg.max_frame_gap)
        return float(min(max(obs.capture_time - self.last_obs.capture_time, 0.0), self.cfg.max_frame_gap))

    def signals(self) -> dict[str, float]:
        """Internal signals worth recording (e.g. the compensation), per axis."""
        return {}

    @abc.abstractmethod
    def _reset(self, motor: np.ndarray, t: float) -> None: ...

    @abc.abstractmethod
    def _update(self, obs: Observation | None, motor: np.ndarray, t: float) -> np.ndarray: ...

    def _clamp_integrator(self, value: np.ndarray) -> np.ndarray:
        """Anti-windup: the integrator never leaves the setpoint range."""
        return np.clip(value, self.lower, self.upper)

