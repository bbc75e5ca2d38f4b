"""Shared pieces of the output-error fits: the play (backlash) operator and the roughness criterion.

The tracker's offset is the image of the tip's motion plus the target's own motion. The target's
motion is smooth (it has mass; a tracker's noise is white), the image of a wrongly modelled tip motion
is not: a wrong delay or a wrong backlash width leaves kinks at every start, stop and reversal of the
motor. So a delay or width is judged by how rough the residual ``x − J·play_w(m(t − d))`` is: the
robust (L1) size of its second differences. White noise and outliers add about the same to every
candidate and do not move the minimum; a smooth target path adds little.
"""
from __future__ import annotations

import numpy as np

__all__ = ["play", "roughness"]


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


def roughness(residual: np.ndarray) -> np.ndarray:
    """L1 size of the second differences of residuals (…, n, 2) over the frame axis: shape (…)."""
    d2 = np.diff(residual, n=2, axis=-2)
    return np.sum(np.sqrt(np.sum(d2 * d2, axis=-1)), axis=-1)
