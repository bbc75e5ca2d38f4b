"""Delay between the motor motion and the image motion it causes, relative to the frames' stamps.

Each frame carries a capture time; if the stamp is right, the image moves with the motor at that
time (plus the drive's and the tip's lag, tens of ms). If the video latency was not known or not
subtracted (a rig), the image motion appears ``delay`` after the stamped motor motion. The estimate
is the lag that best lines up the image increments with the motor increments mapped through the
current Jacobian (normalised cross-correlation over a sliding window), kept within [lo, hi] and only
moved when the correlation is clear.
"""
from __future__ import annotations

from collections import deque
from typing import Callable

import numpy as np

__all__ = ["DelayEstimator"]


class DelayEstimator:
    def __init__(self, *, initial: float = 0.0, lo: float = -0.2, hi: float = 0.8, step: float = 0.01,
                 window: int = 80, every: int = 10, min_correlation: float = 0.8) -> None:
        self.delay = float(np.clip(initial, lo, hi))
        self.lo, self.hi = lo, hi
        self.candidates = np.arange(lo, hi + 1e-9, step)
        self.frames: deque[tuple[float, np.ndarray]] = deque(maxlen=window)
        self.every = every
        self.min_correlation = min_correlation
        self.correlation = 0.0
        self._count = 0

    def add(self, capture_time: float, offset: np.ndarray, motor_at: Callable[[np.ndarray], np.ndarray],
            jacobian: np.ndarray) -> None:
        """A new frame; ``motor_at(times)`` gives the measured motor angles (rad, shape (n, 2))."""
        if not np.all(np.isfinite(offset)) or not np.isfinite(capture_time):
            return
        self.frames.append((float(capture_time), np.asarray(offset, dtype=float)))
        self._count += 1
        if self._count % self.every == 0 and len(self.frames) >= 20:
            self._estimate(motor_at, jacobian)

    def _estimate(self, motor_at, jacobian) -> None:
        t = np.array([f[0] for f in self.frames])
        x = np.array([f[1] for f in self.frames])
        dx = np.diff(x, axis=0).ravel()
        dx = dx - dx.mean()
        best, best_c = self.delay, -1.0
        for d in self.candidates:
            m = motor_at(t - d)
            dp = (np.diff(m, axis=0) @ jacobian.T).ravel()
            dp = dp - dp.mean()
            den = np.linalg.norm(dx) * np.linalg.norm(dp)
            if den <= 1e-9:
                continue
            c = float(dx @ dp / den)
            if c > best_c:
                best, best_c = float(d), c
        self.correlation = best_c
        if best_c >= self.min_correlation:
            self.delay = float(np.clip(0.5 * self.delay + 0.5 * best, self.lo, self.hi))
