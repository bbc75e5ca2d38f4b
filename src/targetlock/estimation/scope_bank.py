"""Which endoscope is this? Candidate scopes run side by side, judged by how well they explain the image.

The hysteresis and deadband differ between endoscopes and change with use (report §2.3, §3.4): the
friction, the cables' slack or pretension, the stiffnesses and the handle gain all move them. A
controller that models the tip with the nominal parameters is wrong by tens of percent on another
scope; on the robustness benchmark, handing the true endoscope parameters (and nothing else) to
``adaptive`` halves its worst rest oscillation and brings its median most of the way to the oracle's.
No single parameter does it: slack, friction, stiffness and handle gain together shape the loop.

So :func:`scope_candidates` spreads candidate endoscopes around the assumed one over the spread the
report describes between scopes (friction ×0.7–2.2, tip stiffness ×0.75–1.35, slack −0.9 to +1.4 mm
about the assumed, handle gain ±15 %; a quasi-random Sobol set, the assumed scope first), a
:class:`~targetlock.estimation.TipModel` runs them all on the measured handle angles, and
:class:`ScopeSelector` picks, every few frames, the candidate whose modelled tip motion best explains
the image over the last seconds (the likelihood of the high-passed residuals of
:func:`~targetlock.estimation.play.rough_residuals` under heavy-tailed noise, J fitted per candidate,
so the answer does not depend on the Jacobian being right): a wrong deadband or hysteresis leaves
kinks in the residual at every start, stop and reversal, the target's own motion does not. It switches only to a clearly
better candidate (hysteresis against noise), and only from windows with enough own motion to tell.
"""
from __future__ import annotations

import dataclasses
import math
from collections import deque

import numpy as np
from numba import njit
from scipy.stats import qmc

from ..model.endoscope import EndoscopeParams
from .play import rough_residuals

__all__ = ["scope_candidates", "ScopeSelector", "CANDIDATE_SPREAD"]

# Degrees of freedom of the Student-t the selector scores the residuals with: heavy-tailed, so a frame
# the candidate does not explain costs only logarithmically more the further off it is.
RESIDUAL_DOF = 4.0
MIN_RESIDUAL_SCALE = 0.5     # px, the least residual scale the selector assumes (a noiseless twin's image)

CANDIDATE_SPREAD = {
    "friction": (0.7, 2.2),        # × mu_n and friction_offset together (looped shafts: ~1.5×)
    "tip_stiffness": (0.75, 1.35),  # × tip_stiffness
    "slack": (-0.0009, 0.0014),     # m added to cable_slack (pretensioned to very slack)
    "handle_radius": (0.85, 1.15),  # × handle_radius
}


def scope_candidates(assumed: EndoscopeParams, n: int = 32, seed: int = 0) -> list[EndoscopeParams]:
    """``n`` candidate endoscopes: ``assumed`` first, then a scrambled Sobol set over
    :data:`CANDIDATE_SPREAD` (friction and stiffness scaled log-uniformly); deterministic for a seed."""
    if n < 1:
        raise ValueError(f"scope_candidates: n = {n}; allowed: >= 1")
    out = [assumed]
    if n == 1:
        return out
    u = qmc.Sobol(d=4, scramble=True, seed=seed).random(1 << math.ceil(math.log2(n - 1)))[: n - 1]
    spread = CANDIDATE_SPREAD

    def log_scale(v: float, key: str) -> float:
        lo, hi = spread[key]
        return math.exp(math.log(lo) + v * (math.log(hi) - math.log(lo)))

    for f, k, s, h in u:
        friction = log_scale(f, "friction")
        lo, hi = spread["slack"]
        out.append(dataclasses.replace(
            assumed, mu_n=assumed.mu_n * friction, friction_offset=assumed.friction_offset * friction,
            tip_stiffness=assumed.tip_stiffness * log_scale(k, "tip_stiffness"),
            cable_slack=assumed.cable_slack + lo + s * (hi - lo),
            handle_radius=assumed.handle_radius * (spread["handle_radius"][0]
                                                   + h * (spread["handle_radius"][1] - spread["handle_radius"][0]))))
    return out


class ScopeSelector:
    """Picks the candidate endoscope whose modelled motion best explains the image (module docstring).

    Feed every frame with :meth:`add`: its capture time (s), offset (px) and every candidate's modelled
    motion at the capture time minus each of ``delays`` (s) (shape (delays, members, 2), in the unit of
    the Jacobian's columns, e.g. equivalent handle rad). ``window`` frames are judged every ``every``
    frames once ``min_frames`` are in, and every ``every_while_filling`` frames until the window is full
    (the first seconds after engaging, when a wrong model costs most); each candidate at its best delay
    (the video latency is not known either).

    **The judgement is a likelihood ratio.** Each frame's residual (the image's high-passed increment
    less the candidate's, :func:`~targetlock.estimation.play.rough_residuals`) is scored under a 2-D
    Student-t (:data:`RESIDUAL_DOF`) whose scale is the same for every candidate: the typical residual
    of the window's best candidate. The candidate read (:attr:`best`) changes to one whose
    log-likelihood over the window is at least ``min_evidence`` nats higher (in ``confirm`` windows in a
    row; one is enough). Where scopes differ is in a few frames (the tip's stick-slip jumps after a
    reversal, 5-10 of 120): a frame the right candidate explains within the noise and a wrong one
    misses by 10 px is worth several nats here. The paired t-test of the residuals used before
    estimated its noise from the same frames, so those few frames widened their own error bar; against
    its false switches it needed the same candidate in two windows in a row.
    Robustness benchmark, 22 random sets of 60 cases (seeds 0/23/204/1 screened; 7/101/201-203/205 and
    300-305 compared 24 nats against 12 and 40, and one window against two; 400-405 held out until the
    choice was made): mean of the medians 28.78 -> 26.70 px (held-out sets 28.28 -> 26.46), lower on 18
    sets and higher on 1; over all 1320 cases p95 118 -> 106 px, per case 304 better and 119 worse by
    more than 5 %, worse than 1.1x PI 55 -> 49, resting cases still moving 171 -> 157 of 440. Two
    windows in a row on the likelihood ratio gained less (27.91 px; on the held-out sets 27.55, per
    case 30 better and 30 worse). On the report's straight path at 12 cm, where the t-test switched
    away from the right assumed scope at 4.5 s, it keeps it.

    **Judged early and often.** The first judgement comes after ``min_frames`` (15, 0.6-1 s at 15-25 fps),
    every 3 frames until the window is full, then every 5. Handing the true scope to the controller from
    the start is worth most of the gap to the oracle (robustness seeds 0/23/204/1, median rms: assumed
    scope 25.5 px, true scope first 16.3, oracle 15.4), the same true scope merely in the bank only 23.9:
    it is chosen at 2.6-9 s, and a step at engaging is over by then. On 22 random sets of 60 cases, mean
    of the medians: from 50 frames every 10, 26.70 px; from 25, every 5 while filling, 26.20; every 5
    throughout too, 26.22 (and no case lost where PI keeps it); from 15 frames every 3 while filling,
    25.85; from 10 every 2, 25.86. One judgement costs ~4 ms for 32 candidates at 13 delays over 120
    frames (the compiled fit); ``adaptive`` runs 64 (25.85 -> 25.54 px). See docs/research.md."""

    def __init__(self, members: int, delays: np.ndarray, *, window: int = 120, every: int = 5,
                 every_while_filling: int = 3, min_frames: int = 15, min_evidence: float = 24.0,
                 confirm: int = 1) -> None:
        if members < 1:
            raise ValueError(f"ScopeSelector: members = {members}; allowed: >= 1")
        if every < 1 or every_while_filling < 1:
            raise ValueError(f"ScopeSelector: every = {every}, every_while_filling = {every_while_filling} frames; "
                             "allowed: >= 1")
        if not 2 <= min_frames <= window:
            raise ValueError(f"ScopeSelector: min_frames = {min_frames}; allowed: 2 to window = {window}")
        if not min_evidence > 0.0:
            raise ValueError(f"ScopeSelector: min_evidence = {min_evidence} nats; allowed: > 0")
        self.members = members
        self.delays = np.atleast_1d(np.asarray(delays, dtype=float))
        self.best = 0
        self.window, self.min_frames = window, min_frames
        self.every, self.every_while_filling = every, every_while_filling
        self.min_evidence = min_evidence
        self.confirm = confirm
        self._pending = (-1, 0)          # candidate found significantly better, in how many windows in a row
        self.frames: deque[tuple[float, np.ndarray, np.ndarray]] = deque(maxlen=window)
        self.cost = np.full(members, np.nan)
        """Negative log-likelihood (nats, up to a common constant) of each candidate at its best delay in the
        last window judged (NaN before)."""
        self.evidence = 0.0
        """Log-likelihood ratio (nats) of the last window's best candidate over the one read."""
        self.switches = 0
        self.judged = 0
        """Windows judged so far."""
        self._count = 0

    def add(self, capture_time: float, offset: np.ndarray, motions: np.ndarray,
            jacobian: np.ndarray) -> np.ndarray | None:
        """A new frame. Returns None, or after a switch the column scales (2,) that carry a Jacobian
        relative to the old candidate's motion over to the new one's (from the two candidates' fitted J)."""
        if self.members == 1:
            return None                               # nothing to choose from
        offset = np.asarray(offset, dtype=float)
        motions = np.asarray(motions, dtype=float)
        if (not np.all(np.isfinite(offset)) or not math.isfinite(capture_time)
                or motions.shape != (self.delays.size, self.members, 2) or not np.all(np.isfinite(motions))):
            return None
        if self.frames and capture_time <= self.frames[-1][0]:
            return None
        self.frames.append((float(capture_time), offset, motions.reshape(-1, 2)))
        self._count += 1
        step = self.every_while_filling if len(self.frames) < self.window else self.every
        if self._count % step or len(self.frames) < self.min_frames:
            return None
        self.judged += 1
        x = np.array([f[1] for f in self.frames])
        p = np.transpose(np.array([f[2] for f in self.frames]), (1, 0, 2))      # (delays·members, n, 2)
        fitted, rn, kept = rough_residuals(x, p, np.asarray(jacobian, dtype=float), common_outliers=True)
        d, m = self.delays.size, self.members
        rn, kept, fitted = rn.reshape(d, m, -1), kept.reshape(d, m, -1), fitted.reshape(d, m, 2, 2)
        cost = _neg_log_likelihood(rn, kept)
        at = np.argmin(cost, axis=0)                   # each candidate's best delay
        self.cost = cost[at, np.arange(m)]
        cur, new = self.best, int(np.argmin(self.cost))
        self.evidence = float(self.cost[cur] - self.cost[new])
        if self.evidence < self.min_evidence:
            self._pending = (-1, 0)
            return None
        count = self._pending[1] + 1 if self._pending[0] == new else 1
        self._pending = (new, count)
        if count < self.confirm:
            return None
        self._pending = (-1, 0)
        old_cols = np.linalg.norm(fitted[at[cur], cur], axis=0)
        new_cols = np.linalg.norm(fitted[at[new], new], axis=0)
        self.best = new
        self.switches += 1
        return np.clip(new_cols / np.maximum(old_cols, 1e-9), 0.8, 1.25)


def _neg_log_likelihood(rn: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """Negative log-likelihood (nats, up to a constant) of the residual norms ``rn`` (..., n) (px) over the
    kept frames (``kept``, 1/0, the same frames for every candidate) under a 2-D Student-t with
    :data:`RESIDUAL_DOF` degrees of freedom and one scale for all: the smallest median residual norm
    of any candidate over 1.18 (the median of a Rayleigh distribution of unit scale), at least
    :data:`MIN_RESIDUAL_SCALE`."""
    rows = np.any(kept > 0, axis=tuple(range(kept.ndim - 1)))
    if not rows.any():
        return np.zeros(rn.shape[:-1])
    smallest = _smallest_median(np.ascontiguousarray(rn.reshape(-1, rn.shape[-1]), dtype=float), rows)
    scale = max(smallest / 1.1774, MIN_RESIDUAL_SCALE)
    rho = 0.5 * (RESIDUAL_DOF + 2.0) * np.log1p((rn / scale) ** 2 / RESIDUAL_DOF)
    return np.sum(rho * kept, axis=-1)


@njit(cache=True)
def _smallest_median(rn: np.ndarray, rows: np.ndarray) -> float:
    """The smallest median over the ``rows`` of any candidate's residuals ``rn`` (candidates, n), without a
    median of every candidate: one whose residuals are below the smallest median so far in fewer than half
    of the rows cannot have a smaller one (exactly np.min(np.median(rn[:, rows], axis=1)); a count
    instead of a selection for most of them)."""
    k, n = rn.shape
    m = 0
    for i in range(n):
        if rows[i]:
            m += 1
    buf = np.empty(m)
    best = np.inf
    for c in range(k):
        below = 0
        for i in range(n):
            if rows[i] and rn[c, i] < best:
                below += 1
        if 2 * below < m:          # the middle value(s) are >= best: so is the median
            continue
        j = 0
        for i in range(n):
            if rows[i]:
                buf[j] = rn[c, i]
                j += 1
        best = min(best, np.median(buf))
    return best
