"""Shared pieces of the output-error fits: the play (backlash) operator and the roughness criterion.

The tracker's offset is the image of the tip's motion plus the target's own motion. The target's
motion is smooth (it has mass; a tracker's noise is white), the image of a wrongly modelled tip motion
is not: a wrong delay or a wrong backlash width leaves kinks at every start, stop and reversal of the
motor. So a delay or width is judged by how rough the residual ``x − J·play_w(m(t − d))`` is: the
robust (L1) size of its frame increments less their running mean over ~0.7 s (the slowly varying
target velocity drops out). White noise and outliers add about the same to every candidate and do
not move the minimum; a smooth target path adds little.

J is fitted per candidate (least squares of those high-passed increments, one robust reweighting,
pulled towards the J handed in where a window says little), so the criterion is scale-free: a wrong
J handed in cannot be "explained" by a wider play or a shift that hides the motion.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["play", "fit_rough", "rough_residuals"]


def play(m: np.ndarray, widths: np.ndarray, start: float | None = None) -> np.ndarray:
    """Play operator: output follows the input ``m`` (shape (n,)) only beyond half the width either
    side. ``widths`` (shape (k,), same unit as m): one output column per width, shape (n, k). The
    output starts at ``start`` (default: ``m[0]``, the middle of the band)."""
    m = np.asarray(m, dtype=float)
    half = 0.5 * np.asarray(widths, dtype=float)
    out = np.empty((m.size, half.size))
    y = np.full(half.size, m[0] if start is None else float(start))
    for k, u in enumerate(m):
        y = np.minimum(np.maximum(y, u - half), u + half)
        out[k] = y
    return out


def fit_rough(x: np.ndarray, p: np.ndarray, prior: np.ndarray, ridge: float = 0.3,
              span: int = 15, common_outliers: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """For each candidate motion ``p`` (k, n, 2) (rad) and the offsets ``x`` (n, 2) (px): the J (k, 2, 2)
    that best maps the high-passed increments of p onto those of x, pulled towards ``prior`` (2, 2) (ridge
    of ``ridge`` × the mean excitation, so a window with little or one-sided motion keeps the prior
    where it says nothing), and the L1 roughness (k,) of the residual ``Hx − J·Hp``, H: the frame
    increments less their running mean over ``span`` frames. Rows whose residual exceeds 3× the median
    (tracker outliers, target jumps) are dropped and the fit repeated once; with ``common_outliers`` the
    same rows for every candidate: those that no candidate explains. A candidate is then neither let off
    the rows only it cannot explain nor denied the rows only it can (a stick-slip jump that only the
    right model predicts). (Dropping the rows most candidates fail on, as before, threw exactly those
    away: robustness seeds 0/23/1/204/7/101/201, `adaptive` median rms 24.7/27.9/29.3/26.3/33.5/28.0/30.9
    -> 23.4/27.2/29.3/24.5/31.7/27.8/30.6 px.)"""
    j, rn, w = rough_residuals(x, p, prior, ridge, span, common_outliers)
    return j, np.sum(rn * w, axis=1) / np.maximum(np.sum(w, axis=1), 1.0) * rn.shape[1]


def rough_residuals(x: np.ndarray, p: np.ndarray, prior: np.ndarray, ridge: float = 0.3, span: int = 15,
                    common_outliers: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The fit of :func:`fit_rough`, returning per candidate the J (k, 2, 2), each row's residual norm
    (k, n-1) (px) and the rows kept (k, n-1) (1 kept, 0 dropped as an outlier)."""
    # Frame increments less their running mean over ``span`` frames: the target's own velocity, slowly
    # varying, drops out; our motion's starts, stops and reversals stay.
    dx = _high_passed_increments(np.ascontiguousarray(x, dtype=float)[None], span)[0]    # (n-1, 2)
    dp = _high_passed_increments(np.ascontiguousarray(p, dtype=float), span)               # (k, n-1, 2)
    jt, rn, w = _fit_increments(dx, dp, np.ascontiguousarray(prior, dtype=float), float(ridge), bool(common_outliers))
    return np.transpose(jt, (0, 2, 1)), rn, w


@njit(cache=True)
def _high_passed_increments(p: np.ndarray, span: int) -> np.ndarray:
    """The frame increments of every candidate's motion ``p`` (k, n, 2) less their centred moving average
    over ``span`` increments (shorter at the ends): (k, n-1, 2). Compiled (in numpy it took a dozen
    (k, n) temporaries)."""
    k, n = p.shape[0], p.shape[1] - 1
    out = np.empty((k, n, 2))
    c = np.empty(n + 1)
    for m in range(k):
        for a in range(2):
            c[0] = 0.0
            for i in range(n):
                c[i + 1] = c[i] + (p[m, i + 1, a] - p[m, i, a])
            for i in range(n):
                lo = max(i - span // 2, 0)
                hi = min(i + span // 2 + 1, n)
                out[m, i, a] = (p[m, i + 1, a] - p[m, i, a]) - (c[hi] - c[lo]) / (hi - lo)
    return out


@njit(cache=True)
def _fit_increments(dx: np.ndarray, dp: np.ndarray, prior: np.ndarray, ridge: float,
                    common: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per candidate c: the ridge-pulled 2x2 least squares ``dx ≈ dp[c]·Jᵀ`` over the kept rows, its residual
    norms, and the rows kept (within 3x the candidate's median residual; with ``common``, the rows any
    candidate keeps); fitted twice, the second time on the kept rows. Compiled: the selector fits
    (delays × candidates) of them every few frames, and numpy's batched 2x2 solves and medians cost ~10 ms."""
    k, n = dp.shape[0], dp.shape[1]
    jt = np.empty((k, 2, 2))
    rn = np.empty((k, n))
    w = np.ones((k, n))
    for _ in range(2):
        for c in range(k):
            g00 = g01 = g11 = 0.0
            b00 = b01 = b10 = b11 = 0.0
            for i in range(n):
                wi = w[c, i]
                p0, p1 = dp[c, i, 0], dp[c, i, 1]
                g00 += wi * p0 * p0
                g01 += wi * p0 * p1
                g11 += wi * p1 * p1
                b00 += wi * p0 * dx[i, 0]
                b01 += wi * p0 * dx[i, 1]
                b10 += wi * p1 * dx[i, 0]
                b11 += wi * p1 * dx[i, 1]
            lam = ridge * 0.5 * (g00 + g11) + 1e-12
            g00 += lam
            g11 += lam
            b00 += lam * prior[0, 0]       # b = Σ w·dp dxᵀ + λ·Jpriorᵀ, rows: motion axis, columns: image axis
            b01 += lam * prior[1, 0]
            b10 += lam * prior[0, 1]
            b11 += lam * prior[1, 1]
            det = g00 * g11 - g01 * g01
            j00 = (g11 * b00 - g01 * b10) / det
            j01 = (g11 * b01 - g01 * b11) / det
            j10 = (g00 * b10 - g01 * b00) / det
            j11 = (g00 * b11 - g01 * b01) / det
            jt[c, 0, 0], jt[c, 0, 1], jt[c, 1, 0], jt[c, 1, 1] = j00, j01, j10, j11
            for i in range(n):
                r0 = dx[i, 0] - dp[c, i, 0] * j00 - dp[c, i, 1] * j10
                r1 = dx[i, 1] - dp[c, i, 0] * j01 - dp[c, i, 1] * j11
                rn[c, i] = math.sqrt(r0 * r0 + r1 * r1)
            limit = 3.0 * np.median(rn[c]) + 1e-12
            for i in range(n):
                w[c, i] = 1.0 if rn[c, i] <= limit else 0.0
        if common:
            for i in range(n):
                keep = 0.0
                for c in range(k):
                    if w[c, i] > 0.0:
                        keep = 1.0
                        break
                for c in range(k):
                    w[c, i] = keep
    return jt, rn, w
