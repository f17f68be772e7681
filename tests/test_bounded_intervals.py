"""Intervals of bounded measures stay inside their range (a t interval of shares right near
1 reached past 1, of ratings near a scale's end past it)."""

from __future__ import annotations

import numpy as np

from facelab.analysis.stats import mean_t_interval


def test_a_t_interval_is_cut_at_the_measures_bounds() -> None:
    shares = np.array([1.0, 1.0, 0.9, 1.0, 0.6])
    mean, low, high = mean_t_interval(shares)
    assert high > 1.0  # the plain t interval leaves the range
    cut = mean_t_interval(shares, bounds=(0.0, 1.0))
    assert cut[0] == mean and cut[1] == low and cut[2] == 1.0
    low_end = mean_t_interval(1 - shares, bounds=(0.0, 1.0))
    assert low_end[1] == 0.0 and 0 < low_end[2] < 1
    # inside the range nothing changes; one value has no interval, bounds or not
    mid = np.array([0.4, 0.5, 0.6])
    assert mean_t_interval(mid, bounds=(0.0, 1.0)) == mean_t_interval(mid)
    assert np.isnan(mean_t_interval(np.array([1.0]), bounds=(0.0, 1.0))[1])
