"""PI control of the pixel offset (report §4.2) and its hysteresis compensations (§4.2.2).

Per axis a, on each new observation with offset x_a (px) captured dt after the previous one:

    integrator_a += I·x_a·dt          (Eq. 4.1-4.2, I in tick/(px·s), converted to rad)
    setpoint_a    = integrator_a + P·x_a + H_a

The integrator starts at the measured motor angle when the lock engages, so the tip does not jump.

Hysteresis compensation H (a backlash inverse). The report's Eq. 4.5 is garbled; its prose is the
specification: compensation is on while the setpoint moves towards the centre, off while it moves
away, its direction may only switch while the target is more than ``hc_threshold_px`` off centre,
and its width is w·|M| (model 1, M the measured motor angle) or slope·(|phi_x| + |phi_y|) + offset
(model 2, from both bending angles, §3.5.2). We write it as

    H_a = width_a · (d_a - sign(M_a)) / 2

with d_a the latched direction of motion (sign of x_a, latched only when |x_a| > threshold). Moving
outwards (d = sign M) gives H = 0; moving towards the centre gives H = -width·sign(M), a step
towards the centre. When the tip crosses the centre while moving the same way, sign(M) flips and
H returns to 0 continuously because width -> 0 at M = 0 for model 1 — this is the report's
"redesign around the centre" (§4.2.2, last paragraph) done.

``pi-smith`` adds latency prediction (a Smith predictor): the offset is corrected by the image
motion the motors have caused since the frame was captured, estimated from the motor history and
the camera's pixels per radian of tip bend. It uses the model-2 compensation.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from ..rig.base import Observation
from .base import Controller, ControllerConfig

__all__ = ["PIController", "MotorHistory"]


class MotorHistory:
    """Recent measured motor angles, to look up where the motors were at a past time (s, rad)."""

    def __init__(self, horizon: float, dt: float) -> None:
        self._buf: deque[tuple[float, np.ndarray]] = deque(maxlen=max(4, int(math.ceil(horizon / dt)) + 4))

    def push(self, t: float, motor: np.ndarray) -> None:
        self._buf.append((t, np.array(motor, dtype=float)))

    def at(self, t: float) -> np.ndarray:
        """Motor angles at time ``t``, interpolated; clamped to the oldest/newest sample."""
        buf = self._buf
        if not buf:
            raise LookupError("no motor history yet")
        if t <= buf[0][0]:
            return buf[0][1].copy()
        if t >= buf[-1][0]:
            return buf[-1][1].copy()
        # Newest samples are the likely ones: search backwards.
        for i in range(len(buf) - 1, 0, -1):
            t0, m0 = buf[i - 1]
            if t0 <= t:
                t1, m1 = buf[i]
                f = (t - t0) / (t1 - t0) if t1 > t0 else 1.0
                return m0 + f * (m1 - m0)
        return buf[0][1].copy()


class PIController(Controller):
    """PI (``pi``), PI + compensation model 1 (``pi-hc``) or model 2 (``pi-hc2``), and ``pi-smith``."""

    def __init__(self, cfg: ControllerConfig, *, px_per_rad: float = 450.0, latency: float = 0.4, **kw) -> None:
        super().__init__(cfg, **kw)
        self.kind = cfg.kind
        self.i_gain = cfg.i_gain * self.rad_per_tick      # rad/(px·s)
        self.p_gain = cfg.p_gain * self.rad_per_tick      # rad/px
        self.px_per_rad = float(px_per_rad)
        self.delay = latency if cfg.motor_delay < 0 else cfg.motor_delay
        self.history = MotorHistory(self.delay + 1.0, self.control_dt)
        self.integrator = np.zeros(2)
        self.direction = np.ones(2)
        self.compensation = np.zeros(2)
        self.x = np.zeros(2)

    def _reset(self, motor: np.ndarray, t: float) -> None:
        self.integrator = motor.copy()
        self.direction = np.where(motor < 0, -1.0, 1.0)   # assume the tip got here moving outwards
        self.compensation = np.zeros(2)
        self.x = np.zeros(2)
        self.history.push(t, motor)

    def _width(self, motor: np.ndarray) -> np.ndarray:
        cfg = self.cfg
        if self.kind == "pi-hc":
            return cfg.hc_width * np.abs(motor)
        bend = cfg.tip_gain * float(np.abs(motor).sum())
        return np.full(2, cfg.hc2_slope * bend + math.radians(cfg.hc2_offset_deg))

    def _update(self, obs: Observation | None, motor: np.ndarray, t: float) -> np.ndarray:
        self.history.push(t, motor)
        if obs is None:
            return self.setpoint  # hold: no integration without a valid observation
        x = np.asarray(obs.offset, dtype=float)
        if self.kind == "pi-smith":
            # Image motion the motors caused since capture has not been seen yet: subtract it.
            moved = motor - self.history.at(obs.capture_time)
            x = x - self.px_per_rad * self.cfg.tip_gain * moved
        dt = self.frame_dt(obs)
        self.x = x
        self.integrator = self._clamp_integrator(self.integrator + self.i_gain * x * dt)
        if self.kind != "pi":
            latch = np.abs(x) > self.cfg.hc_threshold_px
            self.direction = np.where(latch, np.where(x >= 0, 1.0, -1.0), self.direction)
            side = np.where(motor < 0, -1.0, 1.0)
            self.compensation = self._width(motor) * (self.direction - side) / 2.0
        return self.integrator + self.p_gain * x + self.compensation

    def signals(self) -> dict[str, float]:
        return {"comp_x_deg": math.degrees(self.compensation[0]), "comp_y_deg": math.degrees(self.compensation[1])}
