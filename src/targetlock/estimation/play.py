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

import numpy as np

__all__ = ["play", "high_pass", "fit_rough", "rough_residuals"]


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


def high_pass(z: np.ndarray, span: int, axis: int) -> np.ndarray:
    """``z`` minus its centred moving average over ``span`` samples along ``axis`` (edges: shorter average)."""
    z = np.moveaxis(z, axis, -1)
    c = np.cumsum(np.concatenate([np.zeros(z.shape[:-1] + (1,)), z], axis=-1), axis=-1)
    n = z.shape[-1]
    lo = np.clip(np.arange(n) - span // 2, 0, n)
    hi = np.clip(np.arange(n) + span // 2 + 1, 0, n)
    return np.moveaxis(z - (c[..., hi] - c[..., lo]) / (hi - lo), -1, axis)


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
    dx = high_pass(np.diff(x, axis=0), span, 0)       # (n-1, 2)
    dp = high_pass(np.diff(p, axis=1), span, 1)       # (k, n-1, 2)
    w = np.ones(dp.shape[:2])
    for _ in range(2):
        wdp = np.transpose(dp * w[..., None], (0, 2, 1))          # (k, 2, n-1)
        g = wdp @ dp
        lam = ridge * 0.5 * np.trace(g, axis1=1, axis2=2)[:, None, None] + 1e-12
        g = g + lam * np.eye(2)
        b = wdp @ dx + lam * np.asarray(prior, dtype=float).T   # (k, 2 [p], 2 [x])
        jt = np.linalg.solve(g, b)                    # J transposed per candidate
        r = dx[None] - dp @ jt                        # (k, n-1, 2)
        rn = np.sqrt(np.sum(r * r, axis=-1))
        w = (rn <= 3.0 * np.median(rn, axis=1, keepdims=True) + 1e-12).astype(float)
        if common_outliers:
            w = np.broadcast_to(np.any(w > 0, axis=0), w.shape).astype(float)
    return np.transpose(jt, (0, 2, 1)), rn, w
