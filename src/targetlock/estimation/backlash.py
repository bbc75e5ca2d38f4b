"""Backlash / deadband width at motor reversals, per axis, and its growth with bending.

After a reversal of the motor on an axis the tip (and the image) stays put until the cables are
taken up again: the handle travel lost is the width of a play operator between the motor and the
tip. The width is found as the one whose play operator makes the image of the motor motion fit the
camera best: over a sliding window of frames, the residual ``x − J·play_w(m)`` is the target's own
motion (smooth) plus noise, and a wrong width leaves a kink at every reversal (see :mod:`.play`).
A grid of widths per axis (the other axis at its current estimate) is scored by that roughness; an
axis is updated only when it reversed inside the window by more than the candidate width (else its
width is not observable) and the minimum is clear. Each accepted window gives a (bend, width) sample
per axis — bend = |motor_x| + |motor_y| (handle rad) averaged over the window — and the width at a
bend is the least-squares line through the samples (slope ≥ 0), or their median while the bends seen
span less than 0.1 rad; always within [0, max_width].
"""
from __future__ import annotations

from collections import deque

import numpy as np

from .play import play, roughness

__all__ = ["BacklashEstimator"]


class BacklashEstimator:
    """Bounded estimate of the backlash width (handle rad) per axis, from motor angles and image offsets."""

    def __init__(self, *, max_width: float = 0.6, step: float = 0.01, window: int = 200, lead: int = 100,
                 every: int = 20, min_travel: float = 0.01, min_depth: float = 0.03, history: int = 30) -> None:
        if not max_width > 0:
            raise ValueError(f"BacklashEstimator: max_width = {max_width} must be > 0 (handle rad)")
        self.max_width = max_width            # rad (handle)
        self.candidates = np.arange(0.0, max_width + 1e-9, step)
        self.window, self.every = window, every
        self.min_travel = min_travel          # motor travel that counts as a reversal (rad)
        self.min_depth = min_depth            # relative depth of the criterion's minimum to accept a window
        self.frames: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=window + lead)
        self.samples: tuple[deque, deque] = (deque(maxlen=history), deque(maxlen=history))   # (bend, width) per axis
        self.current = np.full(2, np.nan)     # latest accepted window estimate per axis (rad)
        self._count = 0
        self._reversals = 0
        self._dir = np.zeros(2)
        self._extreme = np.full(2, np.nan)

    def add(self, motor: np.ndarray, offset: np.ndarray, jacobian: np.ndarray) -> None:
        """Motor (handle rad) at a frame's capture time (minus the estimated delay), the frame's offset
        (px) and the current image Jacobian (px/rad)."""
        motor = np.asarray(motor, dtype=float)
        offset = np.asarray(offset, dtype=float)
        jacobian = np.asarray(jacobian, dtype=float)
        if not (np.all(np.isfinite(motor)) and np.all(np.isfinite(offset)) and np.all(np.isfinite(jacobian))):
            return
        if np.max(np.abs(offset)) > 1e5 or np.max(np.abs(motor)) > 10.0:
            return
        self._count_reversals(motor)
        self.frames.append((motor, offset))
        self._count += 1
        if self._count % self.every == 0 and len(self.frames) >= self.frames.maxlen // 2:
            self._estimate(jacobian)

    def _count_reversals(self, motor: np.ndarray) -> None:
        for a in range(2):
            if np.isnan(self._extreme[a]):
                self._extreme[a] = motor[a]
                continue
            move = motor[a] - self._extreme[a]
            if self._dir[a] == 0 or np.sign(move) == self._dir[a]:
                if abs(move) > self.min_travel or self._dir[a] != 0:
                    self._dir[a] = np.sign(move) if move != 0 else self._dir[a]
                    self._extreme[a] = motor[a]
            elif abs(move) > self.min_travel:
                self._reversals += 1
                self._dir[a] = -self._dir[a]
                self._extreme[a] = motor[a]

    def _estimate(self, jacobian: np.ndarray) -> None:
        m = np.array([f[0] for f in self.frames])
        x = np.array([f[1] for f in self.frames])
        n = m.shape[0]
        scored = slice(max(n - self.window, 0), n)
        widths = np.where(np.isfinite(self.current), self.current, 0.0)
        bend = float(np.mean(np.abs(m[scored]).sum(axis=1)))
        for a in range(2):
            b = 1 - a
            other = play(m[:, b], widths[b:b + 1])[:, 0]
            cand = play(m[:, a], self.candidates)                                 # (n, k)
            pred = cand.T[:, :, None] * jacobian[:, a] + (other[:, None] * jacobian[:, b])[None]   # (k, n, 2)
            cost = roughness(x[None, scored] - pred[:, scored])
            best = int(np.argmin(cost))
            med = float(np.median(cost))
            depth = (med - cost[best]) / med if med > 0 else 0.0
            # Observable only if the axis came back by more than the width inside the window.
            seg = m[scored, a]
            travel = max(np.max(seg) - seg[-1], seg[-1] - np.min(seg), np.ptp(seg) - abs(seg[-1] - seg[0]))
            if depth >= self.min_depth and travel > self.candidates[best] + self.min_travel:
                widths[a] = self.candidates[best]
                self.current[a] = widths[a]
                self.samples[a].append((bend, float(widths[a])))

    @property
    def reversals(self) -> int:
        """Motor reversals seen (both axes) once a width was estimated; 0 before."""
        return self._reversals if any(self.samples) else 0

    def axis_width(self, axis: int, bend: float = 0.0) -> float:
        """Estimated width (handle rad) of one axis at the given bend (rad, |motor_x| + |motor_y|);
        NaN while that axis has no estimate."""
        s = self.samples[axis]
        if not s:
            return float("nan")
        b = np.array([v[0] for v in s])
        w = np.array([v[1] for v in s])
        if len(w) < 3 or np.ptp(b) < 0.1:
            return float(np.median(w))
        slope, intercept = np.polyfit(b, w, 1)
        if slope < 0:
            return float(np.clip(np.median(w), 0.0, self.max_width))
        return float(np.clip(intercept + slope * bend, 0.0, self.max_width))

    def width(self, bend: float = 0.0) -> float:
        """Estimated width (handle rad) at the given bend (rad, |motor_x| + |motor_y|), the mean of the
        axes that have an estimate; 0 if none has."""
        w = [self.axis_width(a, bend) for a in range(2) if self.samples[a]]
        return float(np.mean(w)) if w else 0.0
