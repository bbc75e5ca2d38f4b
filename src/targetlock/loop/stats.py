"""Running statistics in fixed memory, so a run of any length (up to the allowed 24 h) keeps the same state.

:class:`RunningStats` takes one value at a time and gives count, mean, rms, min and max of the
finite ones (NaN and inf are counted apart, never mixed in); with a histogram range it also gives
quantiles to a stated resolution.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["RunningStats"]


class RunningStats:
    """Count, mean, rms, min, max (and optionally quantiles) of a stream of values.

    ``hist_hi`` (same unit as the values): keep a histogram of [0, hist_hi) in bins of
    ``resolution`` for :meth:`quantile`; values outside fall into the end bins, and quantiles are
    clamped to the exact [min, max], so they are off by at most ``resolution`` inside the range.
    Memory: ``hist_hi / resolution`` counters (e.g. 80 000 for 800 px at 0.01 px), whatever the
    number of values.
    """

    __slots__ = ("count", "nonfinite", "total", "total_sq", "min", "max", "resolution", "_bins")

    def __init__(self, hist_hi: float | None = None, resolution: float = 0.01) -> None:
        self.count = 0
        self.nonfinite = 0
        self.total = 0.0
        self.total_sq = 0.0
        self.min = math.inf
        self.max = -math.inf
        self.resolution = float(resolution)
        self._bins = None if hist_hi is None else np.zeros(max(1, int(math.ceil(hist_hi / resolution))), np.int64)

    def add(self, x: float) -> None:
        """One value; NaN and inf only increase :attr:`nonfinite`."""
        if not math.isfinite(x):
            self.nonfinite += 1
            return
        self.count += 1
        self.total += x
        self.total_sq += x * x
        if x < self.min:
            self.min = x
        if x > self.max:
            self.max = x
        bins = self._bins
        if bins is not None:
            i = int(x / self.resolution)
            bins[0 if i < 0 else (i if i < bins.size else bins.size - 1)] += 1

    @property
    def mean(self) -> float:
        return self.total / self.count if self.count else math.nan

    @property
    def rms(self) -> float:
        return math.sqrt(self.total_sq / self.count) if self.count else math.nan

    def range(self) -> list[float]:
        """[min, max] of the finite values; [] when there were none."""
        return [self.min, self.max] if self.count else []

    def count_above(self, x: float) -> int:
        """How many values were above ``x`` (to the histogram's resolution)."""
        if self._bins is None:
            raise ValueError("count_above() needs a histogram range (hist_hi)")
        return int(self._bins[int(x / self.resolution) + 1:].sum()) if self.count else 0

    def quantile(self, q: float) -> float:
        """The ``q`` quantile (0..1) with linear interpolation between order statistics (as
        ``numpy.percentile``), each order statistic taken at its bin's centre; NaN when empty."""
        if self._bins is None:
            raise ValueError("quantile() needs a histogram range (hist_hi)")
        if not self.count:
            return math.nan
        rank = q * (self.count - 1)
        lo_rank = int(math.floor(rank))
        cum = np.cumsum(self._bins)

        def order_stat(r: int) -> float:
            i = int(np.searchsorted(cum, r + 1))           # the bin holding the (r+1)-th smallest value
            return min(max((i + 0.5) * self.resolution, self.min), self.max)

        a = order_stat(lo_rank)
        if rank == lo_rank:
            return a
        return a + (rank - lo_rank) * (order_stat(lo_rank + 1) - a)
