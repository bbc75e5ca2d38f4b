"""Delay between the motor motion and the image motion it causes, relative to the frames' stamps.

Each frame carries a capture time; if the stamp is right, the image moves with the motor at that
time (plus the drive's and the tip's lag, tens of ms). If the video latency was not known exactly
(a rig stamps frames with the latency it was told), the image motion appears ``delay`` after the
stamped motor motion (negative when the true latency is shorter than the assumed one).

The estimate is the lag that makes the residual ``x − J·m(t − delay)`` smoothest over a sliding
window of frames (see :mod:`.play`): the target's own motion is smooth, a misaligned image of our
own motion is not. Unlike a cross-correlation of increments, this is not biased by the target's
motion that a closed loop follows (the motor moves *because* the image moved, one loop delay later,
which pulls a correlation towards the wrong lag). The estimate is kept within [lo, hi], and moved only
when the criterion has a clear minimum (``correlation``, the relative depth of the minimum, at least
``min_correlation``) — a motor at rest says nothing about the delay.
"""
from __future__ import annotations

from collections import deque
from typing import Callable

import numpy as np

from .play import roughness

__all__ = ["DelayEstimator"]


class DelayEstimator:
    """Bounded estimate of the delay (s) of the image motion behind the stamped motor motion."""

    def __init__(self, *, initial: float = 0.0, lo: float = -0.3, hi: float = 0.8, step: float = 0.01,
                 window: int = 160, every: int = 10, min_correlation: float = 0.05, min_frames: int = 30) -> None:
        if not lo <= hi:
            raise ValueError(f"DelayEstimator: lo = {lo} must not exceed hi = {hi} (s)")
        self.delay = float(np.clip(initial, lo, hi))
        self.lo, self.hi = lo, hi
        self.candidates = np.arange(lo, hi + 1e-9, step)
        self.frames: deque[tuple[float, np.ndarray]] = deque(maxlen=window)
        self.every = every
        self.min_correlation = min_correlation
        self.min_frames = min_frames
        self.correlation = 0.0
        """Depth of the criterion's minimum relative to its median over the candidates, in [0, 1]:
        0 without information (no motor motion), larger the clearer the delay shows."""
        self.estimates = 0
        """How many window estimates moved the delay."""
        self._count = 0

    def add(self, capture_time: float, offset: np.ndarray, motor_at: Callable[[np.ndarray], np.ndarray],
            jacobian: np.ndarray) -> None:
        """A new frame (capture time s, offset px); ``motor_at(times)`` gives the motor angles (rad,
        shape (n, 2)) the image follows — measured, or after the backlash operator; ``jacobian`` px/rad."""
        offset = np.asarray(offset, dtype=float)
        if not np.all(np.isfinite(offset)) or not np.isfinite(capture_time) or np.max(np.abs(offset)) > 1e5:
            return
        if self.frames and capture_time <= self.frames[-1][0]:
            return                                   # out of order or repeated: not a new frame
        self.frames.append((float(capture_time), offset))
        self._count += 1
        jacobian = np.asarray(jacobian, dtype=float)
        if self._count % self.every == 0 and len(self.frames) >= self.min_frames and np.all(np.isfinite(jacobian)):
            self._estimate(motor_at, jacobian)

    def _estimate(self, motor_at, jacobian) -> None:
        t = np.array([f[0] for f in self.frames])
        x = np.array([f[1] for f in self.frames])
        n, k = t.size, self.candidates.size
        m = np.asarray(motor_at((t[None, :] - self.candidates[:, None]).ravel()), dtype=float).reshape(k, n, 2)
        if not np.all(np.isfinite(m)):
            return
        cost = roughness(x[None] - m @ jacobian.T)
        best = int(np.argmin(cost))
        med = float(np.median(cost))
        self.correlation = float(np.clip((med - cost[best]) / med, 0.0, 1.0)) if med > 0 else 0.0
        if self.correlation >= self.min_correlation:
            # Half-way towards the window's answer: one window's accident cannot throw the estimate.
            self.delay = float(np.clip(0.5 * self.delay + 0.5 * self.candidates[best], self.lo, self.hi))
            self.estimates += 1
