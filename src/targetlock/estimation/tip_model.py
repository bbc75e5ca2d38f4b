"""Online tip-angle predictor: the nominal endoscope model run on the measured handle angles.

A rig measures the handle (motor) angles, not the tip's. Between the two lie the cables' slack, the
tip's Coulomb friction (hysteresis, stick-slip) and its viscous lag. :class:`TipModel` runs the
twin's own kernel (:func:`targetlock.model.endoscope.advance`) with the endoscope parameters the
controller *assumes* (e.g. the nominal ``calibrated`` preset, never the plant's truth), its handle
driven to follow the measured angles (linearly interpolated between two measurements, so a 50 Hz
measurement does not become 20 ms steps), and keeps a short history of the modelled tip angles so a
caller can ask where the tip was at a frame's capture time (:meth:`TipModel.tip_at`).

With parameters off by tens of percent the modelled tip still has the right *shape*: it stands
still inside the play after a reversal, starts moving where the cables take up, sticks and slips —
which a linear or play-operator map of the handle does not. Its amplitude may be off by a gain per
axis, which an estimator of the image Jacobian relative to the modelled tip absorbs.

At reset the tip is assumed to have reached the current handle angles by bending outwards from
straight (as the clinician bent it before engaging); the true state inside the hysteresis band is
unknown, and the model forgets that assumption after the first reversal beyond the band.

It can run several candidate endoscopes side by side on the same handle angles (the kernel is batched:
32 candidates cost about twice one); one of them, :attr:`TipModel.member`, is the one read by
:attr:`~TipModel.tip` and :meth:`~TipModel.tips_at`, and :meth:`~TipModel.all_tips_at` reads them all.
"""
from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence

import numpy as np

from ..model.drives import DriveParams
from ..model.endoscope import EndoscopeParams, advance, dead_travel, initial_state, pack_params, simulate

__all__ = ["TipModel", "hysteresis_loop", "triangle"]

# The model's handle follows its set-point at once: it *is* the measured handle angle.
_FOLLOW = DriveParams(time_constant=0.0, max_velocity_ticks=1e9, min_angle=-6.3, max_angle=6.3)


class TipModel:
    """Nominal-endoscope model fed with measured handle angles (rad) at times (s); modelled tip angles
    (rad) at any recent time.

    ``endoscope``: the assumed parameters, or a sequence of candidate endoscopes run together (the
    first is the member read until :attr:`member` is changed); ``model_dt`` (s): the kernel's step; ``horizon`` (s): how far
    back :meth:`tip_at` can look (older times are clamped to the oldest sample); ``max_gap`` (s): a
    longer gap between two updates (a stalled loop) is bridged at the newest handle angle held, not
    by interpolation over it."""

    def __init__(self, endoscope: EndoscopeParams | Sequence[EndoscopeParams], *, model_dt: float = 0.001,
                 horizon: float = 3.0, max_gap: float = 0.2) -> None:
        if not 1e-5 <= model_dt <= 0.02:
            raise ValueError(f"TipModel: model_dt = {model_dt} s; allowed: [1e-05, 0.02] s")
        if not horizon > 0:
            raise ValueError(f"TipModel: horizon = {horizon} s; allowed: > 0 s")
        self.endoscopes = [endoscope] if isinstance(endoscope, EndoscopeParams) else list(endoscope)
        if not self.endoscopes:
            raise ValueError("TipModel: no endoscope given")
        self.member = 0
        """Index of the candidate endoscope that :attr:`tip` and :meth:`tips_at` read."""
        self.model_dt = float(model_dt)
        self.max_gap = float(max_gap)
        self.params = pack_params(self.endoscopes, _FOLLOW)
        self.state = initial_state(len(self.endoscopes))
        self.horizon = float(horizon)
        self._times: deque[float] = deque()
        self._tips: deque[np.ndarray] = deque()
        self._stacked: tuple[np.ndarray, np.ndarray] | None = None     # the history as arrays, until it changes
        self._time = math.nan
        self._handle = np.zeros(2)

    def sweep(self, handle: np.ndarray, *, amplitude: float = 0.6, rate: float = 0.2,
              model_dt: float = 0.002) -> tuple[np.ndarray, np.ndarray]:
        """The assumed scope's hysteresis loop about the handle angles ``handle`` (rad): each axis alone
        driven in two slow triangle cycles (±``amplitude`` rad at ``rate`` rad/s) from a fresh start
        there, analysed by :func:`hysteresis_loop` (of the :attr:`member` read). Returns (slope, width) per axis: tip rad per handle
        rad on a moving branch, and the handle rad lost at a reversal. Runs on a separate state (this
        model's history is untouched); about 0.1 s of CPU."""
        handle = np.asarray(handle, dtype=float)
        t, tri = triangle(amplitude, rate)
        slope, width = np.zeros(2), np.zeros(2)
        for a in range(2):
            probe = TipModel(self.endoscope)
            probe.reset(0.0, handle)
            path = np.repeat(handle[None, :], t.size, axis=0)
            path[:, a] += tri
            out = simulate(probe.state, probe.params, path[:, None, :], model_dt, max(1, int(round(0.01 / model_dt))))
            slope[a], width[a] = hysteresis_loop(t, path[:, a], out[:, 0, 2 + a])
        return slope, width

    @property
    def endoscope(self) -> EndoscopeParams:
        """The parameters of the member read."""
        return self.endoscopes[self.member]

    @property
    def tip(self) -> np.ndarray:
        """Modelled tip angles (rad) of the member read, at the last update."""
        return self.state[self.member, 2:4].copy()

    def dead_travel(self, direction: np.ndarray) -> np.ndarray:
        """Handle travel (rad, per axis) the member read needs, from its state now, before its tip moves
        when the handle turns in ``direction`` (sign per axis): see :func:`~targetlock.model.endoscope.dead_travel`."""
        state = self.state[self.member]
        return dead_travel(self.endoscope, state[0:2], state[2:4], direction)

    @property
    def time(self) -> float:
        """Time (s) of the last update; NaN before :meth:`reset`."""
        return self._time

    def reset(self, t: float, handle: np.ndarray) -> None:
        """Start at time ``t`` (s) with the handle at ``handle`` (rad), the tip at rest, reached by
        bending outwards from straight."""
        handle = np.asarray(handle, dtype=float)
        if handle.shape != (2,) or not np.all(np.isfinite(handle)) or not math.isfinite(t):
            raise ValueError(f"TipModel.reset: handle = {handle} rad must be 2 finite angles, t = {t} s finite")
        k = len(self.endoscopes)
        self.state = initial_state(k)
        ramp = np.linspace(0.0, 1.0, 51)[1:, None, None] * np.broadcast_to(handle, (1, k, 2))
        simulate(self.state, self.params, ramp, 0.002, 10)
        advance(self.state, self.params, np.broadcast_to(handle, (k, 2)).copy(), 0.002, 500)
        self.state[:, 4:6] = 0.0
        self._time = float(t)
        self._handle = handle.copy()
        self._times.clear()
        self._tips.clear()
        self._stacked = None
        self._push(t)

    def update(self, t: float, handle: np.ndarray) -> np.ndarray:
        """Advance the model to time ``t`` (s), the handle moving linearly from the last measurement to
        ``handle`` (rad); returns the modelled tip angles (rad). A non-finite handle angle holds the
        last one; a time not after the last update changes nothing."""
        if math.isnan(self._time):
            raise RuntimeError("TipModel.update before reset")
        handle = np.where(np.isfinite(handle), np.asarray(handle, dtype=float), self._handle)
        span = float(t) - self._time
        n = int(round(span / self.model_dt)) if math.isfinite(span) else 0
        if n <= 0:
            return self.tip
        start = self._handle if span <= self.max_gap else handle
        frac = (np.arange(1, n + 1) / n)[:, None, None]
        path = np.repeat(start[None, None, :] + frac * (handle - start)[None, None, :], len(self.endoscopes), axis=1)
        simulate(self.state, self.params, path, self.model_dt, 1)
        self._time = float(t)
        self._handle = handle.copy()
        self._push(t)
        return self.tip

    def _push(self, t: float) -> None:
        self._stacked = None
        self._times.append(float(t))
        self._tips.append(self.state[:, 2:4].copy())
        while len(self._times) > 2 and self._times[1] < t - self.horizon:
            self._times.popleft()
            self._tips.popleft()

    def tip_at(self, t: float) -> np.ndarray:
        """Modelled tip angles (rad) at time ``t`` (s), interpolated between updates; clamped to the
        oldest / newest."""
        return self.tips_at(np.array([t]))[0]

    def tips_at(self, times: np.ndarray) -> np.ndarray:
        """Modelled tip angles (rad, shape (n, 2)) of the member read at the times (s), like :meth:`tip_at`."""
        return self.all_tips_at(times, self.member)

    def all_tips_at(self, times: np.ndarray, member: int | slice = slice(None)) -> np.ndarray:
        """Modelled tip angles (rad) of every member, shape (n, members, 2), at the times (s), interpolated
        between updates and clamped to the oldest / newest; with an integer ``member``, that one's (n, 2)."""
        if not self._times:
            raise LookupError("TipModel: no history before reset")
        if self._stacked is None:
            self._stacked = (np.fromiter(self._times, float, len(self._times)), np.array(self._tips))
        ts, history = self._stacked
        times = np.clip(np.atleast_1d(np.asarray(times, dtype=float)), ts[0], ts[-1])
        vs = history[:, member]
        if ts.size == 1:
            return np.repeat(vs, times.size, axis=0)
        # Update times strictly increase (an update that does not advance is not recorded).
        hi = np.clip(np.searchsorted(ts, times, side="right"), 1, ts.size - 1)
        lo = hi - 1
        w = (times - ts[lo]) / (ts[hi] - ts[lo])
        wshape = (-1,) + (1,) * (vs.ndim - 1)
        return vs[lo] + w.reshape(wshape) * (vs[hi] - vs[lo])


def triangle(amplitude: float, rate: float, dt: float = 0.01, cycles: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Times (s, step ``dt``) and a triangle wave (rad) of ±``amplitude`` at ``rate`` rad/s starting at 0
    rising, ``cycles`` periods long: the slow handle sweep of a hysteresis measurement."""
    if not (amplitude > 0 and rate > 0):
        raise ValueError(f"triangle: amplitude = {amplitude} rad and rate = {rate} rad/s must be > 0")
    period = 4.0 * amplitude / rate
    t = np.arange(0.0, cycles * period, dt)
    return t, amplitude * (2.0 / math.pi) * np.arcsin(np.sin(2.0 * math.pi * t / period))


def hysteresis_loop(t: np.ndarray, handle: np.ndarray, tip: np.ndarray) -> tuple[float, float]:
    """Slope and width of a hysteresis loop from a slow triangle sweep of one axis (:func:`triangle`,
    at least two cycles): times ``t`` (s), handle and tip angles (rad) sampled together. On the last
    cycle, over the middle 60 % of the tip's range (where the tip moves on both branches), a line is
    fitted to each branch: the slope (tip rad per handle rad) is their mean, the width (handle rad)
    the mean handle distance between the rising and the falling branch at equal tip angle."""
    t, handle, tip = (np.asarray(v, dtype=float) for v in (t, handle, tip))
    period = 0.5 * (t[-1] - t[0])
    last = t >= t[0] + period              # the first cycle reaches the loop from the start
    lo, hi = np.quantile(tip[last], [0.2, 0.8])
    rising = np.gradient(handle)
    mid = last & (tip > lo) & (tip < hi)
    s_up, c_up = np.polyfit(handle[mid & (rising > 0)], tip[mid & (rising > 0)], 1)
    s_dn, c_dn = np.polyfit(handle[mid & (rising < 0)], tip[mid & (rising < 0)], 1)
    levels = np.linspace(lo, hi, 20)
    return float(0.5 * (s_up + s_dn)), float(np.mean((levels - c_up) / s_up - (levels - c_dn) / s_dn))
