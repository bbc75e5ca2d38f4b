"""Backlash / deadband width at motor reversals, and its growth with bending.

After a reversal of the motor on an axis, the tip (and the image) stays put until the cables are
taken up again: the motor travel between the reversal and the first image motion the Jacobian
attributes to that axis is the width at that reversal. Widths are collected with the bend (|motor|
summed over both axes) at which they occurred, and fitted as width = a + b·bend (least squares,
clipped to [0, max_width]); with fewer than three reversals the estimate is the median.
"""
from __future__ import annotations

from collections import deque

import numpy as np

__all__ = ["BacklashEstimator"]


class BacklashEstimator:
    def __init__(self, *, threshold_px: float = 4.0, max_width: float = 0.5, min_travel: float = 0.01,
                 history: int = 20) -> None:
        self.threshold_px = threshold_px      # image motion that counts as 'the tip moved' (px)
        self.max_width = max_width            # rad (handle)
        self.min_travel = min_travel          # motor travel that counts as a reversal (rad)
        self.samples: deque[tuple[float, float]] = deque(maxlen=history)   # (bend rad, width rad)
        self._dir = np.zeros(2)
        self._turn_motor = np.full(2, np.nan)     # motor where the axis reversed
        self._turn_image = np.zeros((2, 2))       # image offset at the reversal
        self._extreme = np.full(2, np.nan)

    def add(self, motor: np.ndarray, offset: np.ndarray, jacobian: np.ndarray, target_motion: np.ndarray | None = None) -> None:
        """Motor (rad) at a frame's capture time and the frame's offset (px)."""
        motor = np.asarray(motor, dtype=float)
        offset = np.asarray(offset, dtype=float)
        if not (np.all(np.isfinite(motor)) and np.all(np.isfinite(offset))):
            return
        for a in range(2):
            if np.isnan(self._extreme[a]):
                self._extreme[a] = motor[a]
                continue
            move = motor[a] - self._extreme[a]
            d = np.sign(move)
            if self._dir[a] == 0 and abs(move) > self.min_travel:
                self._dir[a] = d
            if self._dir[a] != 0 and d == self._dir[a]:
                self._extreme[a] = motor[a]          # still going the same way
            elif self._dir[a] != 0 and abs(move) > self.min_travel and np.isnan(self._turn_motor[a]):
                self._turn_motor[a] = self._extreme[a]   # reversed: wait for the image to follow
                self._turn_image[a] = offset
            if not np.isnan(self._turn_motor[a]):
                col = jacobian[:, a]
                seen = float(np.dot(offset - self._turn_image[a], col) / max(np.linalg.norm(col), 1e-9))
                travel = motor[a] - self._turn_motor[a]
                if abs(seen) > self.threshold_px and np.sign(seen) == np.sign(travel):
                    gain = max(float(np.linalg.norm(col)), 1e-9)     # px per rad along this axis
                    width = float(np.clip(abs(travel) - self.threshold_px / gain, 0.0, self.max_width))
                    self.samples.append((float(np.abs(motor).sum()), width))
                    self._dir[a] = np.sign(travel)
                    self._extreme[a] = motor[a]
                    self._turn_motor[a] = np.nan
                elif abs(travel) > self.max_width:
                    self._turn_motor[a] = np.nan     # no image motion within the largest width: not a reversal we can use
                    self._dir[a] = np.sign(travel)
                    self._extreme[a] = motor[a]

    @property
    def reversals(self) -> int:
        return len(self.samples)

    def width(self, bend: float = 0.0) -> float:
        """Estimated width (handle rad) at the given bend (rad, |motor_x| + |motor_y|); 0 if unknown."""
        if not self.samples:
            return 0.0
        b = np.array([s[0] for s in self.samples])
        w = np.array([s[1] for s in self.samples])
        if len(w) < 3 or np.ptp(b) < 0.1:
            return float(np.median(w))
        slope, intercept = np.polyfit(b, w, 1)
        slope = max(float(slope), 0.0)
        return float(np.clip(intercept + slope * bend, 0.0, self.max_width))
