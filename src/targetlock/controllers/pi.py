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
"redesign around the centre" (§4.2.2, last paragraph) done. Model 2 keeps a width at zero bend, so
there sign(M) is replaced by M/band clipped to ±1 (band = that width): continuous through the centre.

``pi-smith`` adds latency prediction (a Smith predictor): the offset is corrected by the image
motion the tip has made since the frame was captured — the target, placed at the assumed depth
along its pixel ray at the capture-time pose, is re-projected from the current pose through the
chained kinematics. The tip motion comes from an **online
endoscope model** (the twin's own kernel with nominal parameters) driven by the measured motor
angles, so motor motion that only crosses the hysteresis or the deadband — including the
compensation's own steps — is not mistaken for tip motion. It uses the model-2 compensation.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from ..estimation.tip_model import TipModel
from ..model.camera import project, unproject, world_to_camera
from ..model.kinematics import tip_pose
from ..rig.base import Observation
from .base import Controller, ControllerConfig
from .knowledge import Knowledge

__all__ = ["PIController"]


class PIController(Controller):
    """PI (``pi``), PI + compensation model 1 (``pi-hc``) or model 2 (``pi-hc2``), and ``pi-smith``."""

    def __init__(self, cfg: ControllerConfig, *, knowledge: Knowledge, model_dt: float = 0.001, **kw) -> None:
        super().__init__(cfg, knowledge=knowledge, **kw)
        self.camera = knowledge.camera
        self.depth = knowledge.depth
        latency = knowledge.latency
        e = knowledge.endoscope
        self.geometry = (e.tip_length, e.n_elements)
        # Online model for the predictor (pi-smith): the assumed endoscope fed the measured motor.
        self.kind = cfg.kind
        self.i_gain = cfg.integral_gain * self.rad_per_tick      # rad/(px·s)
        self.p_gain = cfg.p_gain * self.rad_per_tick      # rad/px
        delay = latency if cfg.motor_delay < 0 else cfg.motor_delay
        self.tip_model = TipModel(e, model_dt=model_dt, horizon=delay + 1.0)
        self.target_track: deque = deque(maxlen=5)                  # (capture time, world position) of the target
        self.integrator = np.zeros(2)
        self.direction = np.ones(2)
        self.compensation = np.zeros(2)

    def _reset(self, motor: np.ndarray, t: float) -> None:
        self.integrator = motor.copy()
        self.direction = np.where(motor < 0, -1.0, 1.0)   # assume the tip got here moving outwards
        self.compensation = np.zeros(2)
        self.target_track.clear()
        if self.kind == "pi-smith":
            self.tip_model.reset(t, motor)     # the tip got here bending outwards from straight

    def _predict(self, x: np.ndarray, phi_then: np.ndarray, phi_now: np.ndarray,
                 t_capture: float = 0.0, t_now: float = 0.0) -> np.ndarray:
        """Where the target seen at ``x`` (px) with the tip at ``phi_then`` appears now with the tip
        at ``phi_now`` (rad): the target, at the assumed depth, is moved on by its recent world
        velocity over the latency and re-projected from the current pose."""
        cam, g = self.camera, self.geometry
        then = tip_pose(phi_then[0], phi_then[1], g[0], g[1])
        now = tip_pose(phi_now[0], phi_now[1], g[0], g[1])
        p_world = then[:3, :3] @ unproject(x + (cam.cx, cam.cy), self.depth, cam) + then[:3, 3]
        self.target_track.append((t_capture, p_world))
        horizon = self.cfg.target_prediction * (t_now - t_capture)
        if horizon > 0 and len(self.target_track) >= 3:
            ts = np.array([a for a, _ in self.target_track])
            ps = np.array([b for _, b in self.target_track])
            if ts[-1] - ts[0] > 1e-6:
                velocity = np.polyfit(ts - ts[-1], ps, 1)[0]   # least-squares slope, m/s
                p_world = p_world + velocity * horizon
        px = project(world_to_camera(now, p_world), cam)
        return px - (cam.cx, cam.cy) if np.all(np.isfinite(px)) else x

    def _width(self, motor: np.ndarray) -> np.ndarray:
        cfg = self.cfg
        if self.kind == "pi-hc":
            return cfg.hc_width * np.abs(motor)
        bend = cfg.tip_gain * float(np.abs(motor).sum())
        return np.full(2, cfg.hc2_slope * bend + math.radians(cfg.hc2_offset_deg))

    def _side(self, motor: np.ndarray) -> np.ndarray:
        """Which side of the centre the handle is on, -1 … 1. Model 1's width vanishes at the centre,
        so a sign is continuous enough; model 2's width does not (hc2_offset_deg at zero bend), so the
        side tapers linearly over ±that width: crossing the centre moving one way fades the
        compensation out instead of flipping it by the whole width in one tick."""
        if self.kind == "pi-hc":
            return np.where(motor < 0, -1.0, 1.0)
        band = max(math.radians(self.cfg.hc2_offset_deg), 1e-6)
        return np.clip(motor / band, -1.0, 1.0)

    def _update(self, obs: Observation | None, motor: np.ndarray, t: float) -> np.ndarray:
        if self.kind == "pi-smith":
            self.tip_model.update(t, motor)
        if obs is None:
            return None  # hold: no integration without a valid observation
        x = np.asarray(obs.offset, dtype=float)
        if self.kind == "pi-smith":
            x = self._predict(x, self.tip_model.tip_at(obs.capture_time), self.tip_model.tip, obs.capture_time, t)
        dt = self.frame_dt(obs)
        self.integrator = self._clamp_integrator(self.integrator + self.i_gain * x * dt)
        if self.kind != "pi":
            latch = np.abs(x) > self.cfg.hc_threshold_px
            self.direction = np.where(latch, np.where(x >= 0, 1.0, -1.0), self.direction)
            self.compensation = self._width(motor) * (self.direction - self._side(motor)) / 2.0
        return self.integrator + self.p_gain * x + self.compensation

    def signals(self) -> dict[str, float]:
        return {"comp_x_deg": math.degrees(self.compensation[0]), "comp_y_deg": math.degrees(self.compensation[1])}
