"""Inverse-kinematics controller (report §4.3).

On each new observation:

1. the target pixel and the assumed depth give the target in the camera frame (Eq. 3.38 inverted);
2. the camera pose at capture time comes from the forward kinematics at the motor position
   *at the frame's capture time* (the motor history is delayed to match the video, as the report
   delays it by 8 frames; we use the capture timestamp, which needs no frame counting);
3. the bending angles that put the target on the optical axis are solved directly by
   Gauss-Newton on the chained kinematics (the report ran an online simulation of the model with a
   PI loop until it settled; a direct solve reaches the same fixed point in a few iterations);
4. the handle setpoint is those angles over the tip gain, damped towards the measured motor
   position with d (Eq. 4.6): S = S* - d·(S* - M).
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np
from numba import njit

from ..model.camera import unproject
from ..model.kinematics import tip_pose
from ..rig.base import Observation
from .base import Controller, ControllerConfig
from .knowledge import Knowledge

__all__ = ["IKController", "aim_angles"]


@njit(cache=True)
def _aim_residual(target, phi0, phi1, length, n):
    h = tip_pose(phi0, phi1, length, n)
    d = target - h[:3, 3]
    r = h[:3, :3]
    x = r[0, 0] * d[0] + r[1, 0] * d[1] + r[2, 0] * d[2]
    y = r[0, 1] * d[0] + r[1, 1] * d[1] + r[2, 1] * d[2]
    z = r[0, 2] * d[0] + r[1, 2] * d[1] + r[2, 2] * d[2]
    # Angles, not x/z and y/z: zero only with the target in front of the camera (z > 0).
    return np.array([np.arctan2(x, z), np.arctan2(y, z)])


@njit(cache=True)
def aim_angles(target: np.ndarray, phi_start: np.ndarray, length: float, n: int, lower: float, upper: float) -> np.ndarray:
    """Bending angles (rad) whose optical axis passes through ``target`` (base frame, m)."""
    phi = phi_start.copy()
    eps = 1e-6
    for _ in range(30):
        r = _aim_residual(target, phi[0], phi[1], length, n)
        if abs(r[0]) + abs(r[1]) < 1e-10:
            break
        j = np.empty((2, 2))
        for k in range(2):
            p = phi.copy()
            p[k] += eps
            j[:, k] = (_aim_residual(target, p[0], p[1], length, n) - r) / eps
        det = j[0, 0] * j[1, 1] - j[0, 1] * j[1, 0]
        if abs(det) < 1e-12:
            break
        dphi0 = (j[1, 1] * r[0] - j[0, 1] * r[1]) / det
        dphi1 = (-j[1, 0] * r[0] + j[0, 0] * r[1]) / det
        # Cap the step: far from the solution (target beside the camera) a full Newton step overshoots.
        scale = min(1.0, 0.4 / max(abs(dphi0), abs(dphi1)))
        dphi0 *= scale
        dphi1 *= scale
        phi[0] = min(max(phi[0] - dphi0, lower), upper)
        phi[1] = min(max(phi[1] - dphi1, lower), upper)
    return phi


class History:
    """Recent timed samples of an angle pair (motor or tip, rad), to look up a past time (s)."""

    def __init__(self, horizon: float, dt: float) -> None:
        self._buf: deque[tuple[float, np.ndarray]] = deque(maxlen=max(4, int(math.ceil(horizon / dt)) + 4))

    def push(self, t: float, value: np.ndarray) -> None:
        self._buf.append((t, np.array(value, dtype=float)))

    def clear(self) -> None:
        self._buf.clear()

    def at(self, t: float) -> np.ndarray:
        """The value at time ``t``, interpolated; clamped to the oldest/newest sample."""
        buf = self._buf
        if not buf:
            raise LookupError("no history yet")
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

    def at_many(self, times: np.ndarray) -> np.ndarray:
        """Values (n, 2) at many times (s), interpolated and clamped like :meth:`at`."""
        if not self._buf:
            raise LookupError("no history yet")
        ts = np.fromiter((b[0] for b in self._buf), float, len(self._buf))
        vs = np.array([b[1] for b in self._buf])
        times = np.atleast_1d(np.asarray(times, dtype=float))
        return np.column_stack([np.interp(times, ts, vs[:, k]) for k in range(vs.shape[1])])


class IKController(Controller):
    """Target pixel + depth -> 3D target -> bending angles that centre it -> damped handle setpoint."""

    def __init__(self, cfg: ControllerConfig, *, knowledge: Knowledge, **kw) -> None:
        super().__init__(cfg, knowledge=knowledge, **kw)
        self.camera = knowledge.camera
        self.depth = knowledge.depth
        self.tip_length = float(knowledge.endoscope.tip_length)
        self.n_elements = int(knowledge.endoscope.n_elements)
        latency = knowledge.latency
        self.delay = latency if cfg.motor_delay < 0 else cfg.motor_delay
        self.history = History(self.delay + 1.0, self.control_dt)
        self.goal = np.zeros(2)

    def _reset(self, motor: np.ndarray, t: float) -> None:
        self.history.push(t, motor)
        self.goal = motor.copy()

    def _update(self, obs: Observation | None, motor: np.ndarray, t: float) -> np.ndarray:
        self.history.push(t, motor)
        if obs is None:
            return None
        cfg, cam = self.cfg, self.camera
        motor_then = self.history.at(t - self.delay) if cfg.motor_delay >= 0 else self.history.at(obs.capture_time)
        phi_then = cfg.tip_gain * motor_then
        p_cam = unproject(np.asarray(obs.offset) + [cam.cx, cam.cy], self.depth, cam)
        pose = tip_pose(phi_then[0], phi_then[1], self.tip_length, self.n_elements)
        p_base = pose[:3, :3] @ p_cam + pose[:3, 3]
        lim = float(np.max(np.abs(np.concatenate([self.lower, self.upper])))) * cfg.tip_gain
        phi_goal = aim_angles(p_base, phi_then, self.tip_length, self.n_elements, -lim, lim)
        self.goal = phi_goal / cfg.tip_gain
        return self.goal - cfg.ik_damping * (self.goal - motor)

    def signals(self) -> dict[str, float]:
        return {"goal_x_deg": float(np.degrees(self.goal[0])), "goal_y_deg": float(np.degrees(self.goal[1]))}
