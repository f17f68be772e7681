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


def test_series_comparison_cuts_a_bounded_measures_interval() -> None:
    """Sumby-Pollack's visual enhancement is at most 1; its summary interval reached 1.19."""
    import pandas as pd

    from facelab.analysis.stats import series_comparison

    table = pd.DataFrame({
        "participant": [f"p{i}" for i in range(4)] * 2,
        "condition": ["a"] * 4 + ["b"] * 4,
        "visual_enhancement": [0.99, 0.98, 0.97, 0.6, 0.5, 0.4, 0.6, 0.5],
    })  # fmt: skip
    plain, _ = series_comparison(table, measures=("visual_enhancement",))
    cut, _ = series_comparison(table, measures=("visual_enhancement",),
                               bounds={"visual_enhancement": (-1.0, 1.0)})  # fmt: skip
    assert plain["visual_enhancement_ci_high"].iloc[0] > 1.0
    assert cut["visual_enhancement_ci_high"].iloc[0] == 1.0
    assert cut["visual_enhancement_ci_high"].iloc[1] == plain["visual_enhancement_ci_high"].iloc[1]
