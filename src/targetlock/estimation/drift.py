"""The target's own image velocity, when it is a steady drift.

The offset the camera shows is the target's own position less what our own motion moved the image:
``x = w + J·e`` (``e``: the modelled tip at the frame's capture time, equivalent handle rad), so
``w = x − J·e`` is where the target is in the image of the unbent scope. A servo that only removes
the offset it sees lags a target moving at ``v`` px/s by ``v·(latency + 1/(gain·fps))``; knowing
``v`` removes that lag. But a velocity read from noisy frames, stick-slip jumps the model does not
predict, and steps costs more than it gains, so a velocity is reported only when the last
``window`` seconds of ``w`` are a clear straight line: the motion over the window is at least
``significance`` times the scatter about the line, and the two halves' slopes agree within
``consistency`` of the whole's.
"""
from __future__ import annotations

from collections import deque

import numpy as np

__all__ = ["DriftEstimator"]


class DriftEstimator:
    """The target's own image velocity (px/s) over a sliding window of frames, zero unless it is a
    clear, steady drift (module docstring)."""

    def __init__(self, *, window: float = 3.0, significance: float = 6.0, consistency: float = 0.3,
                 min_scatter: float = 1.0, max_speed: float = 200.0) -> None:
        self.window = window                      # s
        self.significance = significance
        self.consistency = consistency
        self.min_scatter = min_scatter            # px: tracker noise floor of the scatter
        self.max_speed = max_speed                # px/s: beyond this it is not a drift
        self.frames: deque[tuple[float, np.ndarray, np.ndarray]] = deque()
        self.velocity = np.zeros(2)               # px/s, zero unless a drift is clear
        self.offset_scatter = 0.0                 # px: rms of the offsets about their mean over the window

    def add(self, capture_time: float, offset: np.ndarray, effective: np.ndarray, jacobian: np.ndarray) -> np.ndarray:
        """A frame: capture time (s), offset (px), modelled tip at that time (equivalent handle rad);
        returns the drift velocity (px/s, zeros when there is no clear drift)."""
        c = float(capture_time)
        self.frames.append((c, np.asarray(offset, dtype=float), np.asarray(effective, dtype=float)))
        while self.frames and self.frames[0][0] < c - self.window:
            self.frames.popleft()
        self.velocity = self._estimate(np.asarray(jacobian, dtype=float))
        return self.velocity

    def reset(self) -> None:
        """Forget the frames (e.g. when the modelled own motion they were read with is replaced)."""
        self.frames.clear()
        self.velocity = np.zeros(2)
        self.offset_scatter = 0.0

    def _estimate(self, j: np.ndarray) -> np.ndarray:
        n = len(self.frames)
        if n < 8:
            return np.zeros(2)
        t = np.array([f[0] for f in self.frames])
        x = np.array([f[1] for f in self.frames])
        self.offset_scatter = float(np.sqrt(np.mean(np.sum((x - x.mean(axis=0)) ** 2, axis=1))))
        if t[-1] - t[0] < 0.8 * self.window:
            return np.zeros(2)
        w = x - np.array([f[2] for f in self.frames]) @ j.T
        slope, fit_rms = _line(t, w)
        scatter = max(fit_rms, self.min_scatter)
        speed = float(np.linalg.norm(slope))
        span = float(t[-1] - t[0])
        if speed * span < self.significance * scatter or speed > self.max_speed:
            return np.zeros(2)
        half = n // 2
        for part in (slice(0, half), slice(half, n)):
            if np.ptp(t[part]) <= 0:
                return np.zeros(2)
            if np.linalg.norm(_line(t[part], w[part])[0] - slope) > self.consistency * speed:
                return np.zeros(2)
        return slope


def _line(t: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares slope (per column of ``w``, units of w per s) of ``w`` over ``t`` and the rms
    distance of the points from the fitted line."""
    tc = t - t.mean()
    wc = w - w.mean(axis=0)
    slope = tc @ wc / float(tc @ tc)
    res = wc - np.outer(tc, slope)
    return slope, float(np.sqrt(np.mean(np.sum(res * res, axis=1))))
