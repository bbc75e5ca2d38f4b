"""Backlash / deadband width at motor reversals, and its growth with bending.

After a reversal of the motor on an axis, the tip (and the image) stays put until the cables are
taken up again: the motor travel between the reversal and the first image motion the Jacobian
attributes to that axis is the width at that reversal. Widths are collected with the bend (|motor|
summed over both axes) at which they occurred, and fitted as width = a + b·bend (least squares,
clipped to [0, max_width]); with fewer than three reversals the estimate is the median.

:class:`BacklashFitEstimator` (same interface) instead fits the width of a play operator per axis
(the handle travel lost at a reversal) between the motor and the tip. The width is found as the one whose play operator makes the image of the motor motion fit the
camera best: over a sliding window of frames, the residual ``x − J·play_w(m)`` is the target's own
motion (smooth) plus noise, and a wrong width leaves a kink at every reversal (see :mod:`.play`; J is
fitted per candidate width, so an error of the J handed in does not bias the width).
A grid of widths per axis (the other axis at its current estimate) is scored by that roughness; an
axis is updated only when it reversed inside the window by more than the candidate width (else its
width is not observable) and the minimum is clear. Each accepted window gives a (bend, width) sample
per axis — bend = |motor_x| + |motor_y| (handle rad) averaged over the window. Single windows scatter
(in closed loop the target's own kinks resemble a reversal's), so the width is the median of the
samples, and its growth with bend a Theil-Sen line (slope ≥ 0) once 8 samples span 0.3 rad of bend;
always within [0, max_width].
"""
from __future__ import annotations

from collections import deque

import numpy as np

from .play import fit_rough, play

__all__ = ["BacklashEstimator", "BacklashFitEstimator"]


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


class BacklashFitEstimator:
    """Bounded estimate of the backlash width (handle rad) per axis by the play-operator fit (module
    docstring, second part); same interface as :class:`BacklashEstimator`, plus :meth:`axis_width`.

    Feed it a Jacobian that is not grown on break-free jumps (``JacobianEstimator(...,
    growth_ratio=math.inf)``): the growth, safe for steering, leaves J too large around reversals, and
    the fitted width grows with it (tests' twin lock, calibrated scope at 5 cm: the y width +69-83 % on 3
    of 5 noise seeds; without the growth +78 % on 1 of 5)."""

    def __init__(self, *, max_width: float = 0.6, step: float = 0.01, window: int = 200, lead: int = 100,
                 every: int = 20, min_travel: float = 0.01, min_depth: float = 0.05, history: int = 30) -> None:
        if not max_width > 0:
            raise ValueError(f"BacklashFitEstimator: max_width = {max_width} must be > 0 (handle rad)")
        self.max_width = max_width            # rad (handle)
        self.candidates = np.arange(0.0, max_width + 1e-9, step)
        self.window, self.every = window, every
        self.min_travel = min_travel          # motor travel that counts as a reversal (rad)
        self.min_depth = min_depth            # relative depth of the criterion's minimum to accept a window
        self.frames: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=window + lead)
        # (bend rad, width rad, depth of the criterion's minimum) per axis
        self.samples: tuple[deque, deque] = (deque(maxlen=history), deque(maxlen=history))
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
        if self._count % self.every == 0 and len(self.frames) >= self.window // 2:
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
            p = np.empty((cand.shape[1], n, 2))
            p[:, :, a] = cand.T
            p[:, :, b] = other[None, :]
            _, cost = fit_rough(x[scored], p[:, scored], jacobian)
            best = int(np.argmin(cost))
            med = float(np.median(cost))
            depth = (med - cost[best]) / med if med > 0 else 0.0
            # Observable only if the axis came back by more than the width inside the window.
            seg = m[scored, a]
            travel = max(np.max(seg) - seg[-1], seg[-1] - np.min(seg), np.ptp(seg) - abs(seg[-1] - seg[0]))
            if depth >= self.min_depth and travel > self.candidates[best] + self.min_travel:
                widths[a] = self.candidates[best]
                self.current[a] = widths[a]
                self.samples[a].append((bend, float(widths[a]), float(depth)))

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
        if len(w) < 8 or np.ptp(b) < 0.3:
            return _weighted_median(w, np.array([v[2] for v in s]))
        # Growth with bending: Theil-Sen line (median of pairwise slopes), robust to the scattered windows.
        i, k = np.triu_indices(len(b), 1)
        ok = np.abs(b[k] - b[i]) > 0.05
        slope = max(float(np.median((w[k] - w[i])[ok] / (b[k] - b[i])[ok])), 0.0) if np.any(ok) else 0.0
        intercept = float(np.median(w - slope * b))
        return float(np.clip(intercept + slope * bend, 0.0, self.max_width))

    def width(self, bend: float = 0.0) -> float:
        """Estimated width (handle rad) at the given bend (rad, |motor_x| + |motor_y|), the mean of the
        axes that have an estimate; 0 if none has."""
        w = [self.axis_width(a, bend) for a in range(2) if self.samples[a]]
        return float(np.mean(w)) if w else 0.0


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The value below and above which half the weight lies."""
    order = np.argsort(values)
    cum = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cum, 0.5 * cum[-1])])
