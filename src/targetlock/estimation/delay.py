"""Delay between the motor motion and the image motion it causes, relative to the frames' stamps.

Each frame carries a capture time; if the stamp is right, the image moves with the motor at that
time (plus the drive's and the tip's lag, tens of ms). If the video latency was not known or not
subtracted (a rig), the image motion appears ``delay`` after the stamped motor motion. The estimate
is the lag that best lines up the image increments with the motor increments mapped through the
current Jacobian (normalised cross-correlation over a sliding window), kept within [lo, hi] and only
moved when the correlation is clear.

:class:`DelayFitEstimator` (same interface) instead takes the lag that makes the residual
``x − J·m(t − delay)`` smoothest over a sliding window of frames, J fitted for each lag and pulled
towards the J handed in where the window says little (see :mod:`.play`): the target's own motion is
smooth, a misaligned image of our own motion is not. Unlike a cross-correlation of increments, this
is not pulled by the target's motion that a closed loop follows (the motor moves *because* the image
moved, one loop delay later). It reads the motor for each frame when the frame arrives, so its
window (7 s) may be longer than the caller's motor history. Moved only when the criterion has a
clear minimum (``correlation``, the relative depth of the minimum, at least ``min_correlation``), to
the median of the last ``answers`` windows' delays.
"""
from __future__ import annotations

from collections import deque
from typing import Callable

import numpy as np

from .play import fit_rough

__all__ = ["DelayEstimator", "DelayFitEstimator"]


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
        # The motor at every frame's time minus every candidate delay, read in one call.
        m = np.asarray(motor_at((t[None, :] - self.candidates[:, None]).ravel()), dtype=float)
        dp = (np.diff(m.reshape(self.candidates.size, t.size, 2), axis=1) @ jacobian.T).reshape(self.candidates.size, -1)
        dp = dp - dp.mean(axis=1, keepdims=True)
        den = np.linalg.norm(dx) * np.linalg.norm(dp, axis=1)
        ok = den > 1e-9
        best, best_c = self.delay, -1.0
        if ok.any():
            c = np.where(ok, dp @ dx / np.where(ok, den, 1.0), -np.inf)
            i = int(np.argmax(c))
            best, best_c = float(self.candidates[i]), float(c[i])
        self.correlation = best_c
        if best_c >= self.min_correlation:
            self.delay = float(np.clip(0.5 * self.delay + 0.5 * best, self.lo, self.hi))


class DelayFitEstimator:
    """Bounded estimate of the delay (s) of the image motion behind the stamped motor motion, by the
    roughness of the residual (module docstring, second part); same interface as :class:`DelayEstimator`."""

    def __init__(self, *, initial: float = 0.0, lo: float = -0.3, hi: float = 0.8, step: float = 0.01,
                 window: int = 160, every: int = 10, min_correlation: float = 0.05, min_frames: int = 30,
                 answers: int = 15) -> None:
        if not lo <= hi:
            raise ValueError(f"DelayFitEstimator: lo = {lo} must not exceed hi = {hi} (s)")
        self.delay = float(np.clip(initial, lo, hi))
        self.lo, self.hi = lo, hi
        self.candidates = np.arange(lo, hi + 1e-9, step)
        # Per frame: capture time, offset, and the motor at capture time minus each candidate delay, read
        # when the frame arrives (a controller keeps only a few seconds of motor history).
        self.frames: deque[tuple[float, np.ndarray, np.ndarray]] = deque(maxlen=window)
        self.every = every
        self.min_correlation = min_correlation
        self.min_frames = min_frames
        self.correlation = 0.0
        """Depth of the criterion's minimum relative to its median over the candidates, in [0, 1]:
        0 without information (no motor motion), larger the clearer the delay shows."""
        self.jacobian = np.full((2, 2), np.nan)
        """px/rad: the J fitted with the best delay of the last window (NaN before any)."""
        self.estimates = 0
        """How many window estimates moved the delay."""
        self._answers: deque[float] = deque(maxlen=answers)
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
        m = np.asarray(motor_at(capture_time - self.candidates), dtype=float).reshape(self.candidates.size, 2)
        if not np.all(np.isfinite(m)):
            return
        self.frames.append((float(capture_time), offset, m))
        self._count += 1
        jacobian = np.asarray(jacobian, dtype=float)
        if self._count % self.every == 0 and len(self.frames) >= self.min_frames and np.all(np.isfinite(jacobian)):
            self._estimate(jacobian)

    def _estimate(self, jacobian) -> None:
        x = np.array([f[1] for f in self.frames])
        m = np.transpose(np.array([f[2] for f in self.frames]), (1, 0, 2))         # (k candidates, n frames, 2)
        fitted, cost = fit_rough(x, m, jacobian)
        best = int(np.argmin(cost))
        self.jacobian = fitted[best]
        med = float(np.median(cost))
        self.correlation = float(np.clip((med - cost[best]) / med, 0.0, 1.0)) if med > 0 else 0.0
        if self.correlation >= self.min_correlation:
            # The median of the recent windows' answers: single windows scatter (in closed loop the
            # target's own kinks can look like ours), the median does not follow one accident.
            self._answers.append(float(self.candidates[best]))
            self.delay = float(np.clip(np.median(self._answers), self.lo, self.hi))
            self.estimates += 1
