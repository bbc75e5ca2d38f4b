"""Running statistics of a run: the summary's figures without keeping the rows."""
from __future__ import annotations

import numpy as np
import pytest

from targetlock.loop.stats import RunningStats


def test_quantiles_and_counts_match_numpy_on_the_kept_values():
    rng = np.random.default_rng(3)
    x = rng.gamma(2.0, 20.0, 5000)
    s = RunningStats(hist_hi=1000.0, resolution=0.01)
    for v in list(x) + [float("nan"), float("inf")]:
        s.add(v)
    assert s.count == x.size and s.nonfinite == 2
    assert s.rms == pytest.approx(np.sqrt(np.mean(x ** 2)))
    for q in (0.5, 0.95, 0.99):
        assert s.quantile(q) == pytest.approx(np.percentile(x, 100 * q), abs=0.01)
    for limit in (10.0, 40.0, 100.0):
        assert abs(s.count_above(limit) - int(np.sum(x > limit))) <= int(np.sum(np.abs(x - limit) < 0.01))
    assert RunningStats(hist_hi=1.0).count_above(0.5) == 0
