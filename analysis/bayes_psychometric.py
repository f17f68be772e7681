"""Bayesian psychometric fits for one participant's few trials: the posterior on a grid,
with psignifit's default priors, and credible intervals from its marginals.

A participant's 40-60 trials of a staircase or a constant-stimuli block often nearly
separate: the maximum-likelihood slope then runs off to its search bound and a parametric
bootstrap, drawing from that fit, returns tight intervals around the runaway value. The
posterior does not run away: the priors (Schütt, Harmeling, Macke & Wichmann 2016, psignifit
4's defaults) say what is plausible before the data -

* midpoint ``m``: flat over the levels tested, falling with a raised cosine to zero half a
  level range beyond them;
* width ``w`` (the level span over which F rises from 5 % to 95 %; logistic slope
  ``beta = 2 ln 19 / w``): flat from twice the smallest step between levels to the level
  range, falling with a raised cosine to zero at the smallest step and at three ranges;
* lapse ``lambda``: Beta(1, 10) on [0, 0.5];

and the data move them. The posterior is evaluated on a grid of 101 midpoints x 101
log-spaced widths x 51 lapse rates (vectorised; tens of ms per participant); point estimates
are the marginal medians, intervals the marginal 2.5 / 97.5 % quantiles (equal-tailed 95 %
credible intervals). Logistic F only; the model otherwise is that of
:mod:`facelab.analysis.psychometric`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import special

from facelab.errors import AnalysisError

__all__ = ["PosteriorFit", "posterior_fit"]

LN19 = float(np.log(19.0))
N_MID, N_WIDTH, N_LAPSE = 101, 101, 51
LAPSE_MAX = 0.5


@dataclass(frozen=True)
class PosteriorFit:
    """Marginal posterior medians and equal-tailed credible intervals (``ci`` mass)."""

    midpoint: float
    midpoint_ci_low: float
    midpoint_ci_high: float
    slope: float  # logistic beta
    slope_ci_low: float
    slope_ci_high: float
    lapse: float
    lapse_ci_low: float
    lapse_ci_high: float
    n_trials: int
    n_levels: int


def _cosine_window(x: np.ndarray, *, zero_lo: float, flat_lo: float, flat_hi: float,
                   zero_hi: float) -> np.ndarray:  # fmt: skip
    """1 on [flat_lo, flat_hi], raised-cosine flanks to 0 at zero_lo and zero_hi."""
    out = np.zeros_like(x, dtype=float)
    flat = (x >= flat_lo) & (x <= flat_hi)
    out[flat] = 1.0
    left = (x > zero_lo) & (x < flat_lo)
    out[left] = 0.5 - 0.5 * np.cos(np.pi * (x[left] - zero_lo) / (flat_lo - zero_lo))
    right = (x > flat_hi) & (x < zero_hi)
    out[right] = 0.5 + 0.5 * np.cos(np.pi * (x[right] - flat_hi) / (zero_hi - flat_hi))
    return out


def _quantiles(values: np.ndarray, weights: np.ndarray, qs: tuple[float, ...]) -> list[float]:
    """Quantiles of a discrete distribution on sorted ``values`` (linear between cells)."""
    cdf = np.cumsum(weights) / weights.sum()
    return [float(np.interp(q, cdf, values)) for q in qs]


def posterior_fit(counts: pd.DataFrame, *, gamma: float, ci: float = 0.95) -> PosteriorFit:
    """The posterior fit of ``counts`` (columns ``level, n, k``: trials and "yes" answers at
    each level) with guess rate ``gamma``."""
    x = counts["level"].to_numpy(dtype=float)
    n = counts["n"].to_numpy(dtype=float)
    k = counts["k"].to_numpy(dtype=float)
    levels = np.unique(x)
    if len(levels) < 2:
        raise AnalysisError("a psychometric fit needs answers at two or more levels")
    lo, hi = float(levels.min()), float(levels.max())
    span = hi - lo
    step = float(np.diff(levels).min())
    mids = np.linspace(lo - 0.5 * span, hi + 0.5 * span, N_MID)
    widths = np.exp(np.linspace(np.log(step), np.log(3.0 * span), N_WIDTH))
    lapses = np.linspace(0.0, LAPSE_MAX, N_LAPSE)

    log_prior_m = np.log(
        _cosine_window(mids, zero_lo=lo - 0.5 * span, flat_lo=lo, flat_hi=hi,
                       zero_hi=hi + 0.5 * span) + 1e-300
    )  # fmt: skip
    # the width prior is a density in w; the grid is uniform in log w, so each cell weighs w
    log_prior_w = np.log(
        _cosine_window(widths, zero_lo=step, flat_lo=2 * step, flat_hi=span,
                       zero_hi=3 * span) * widths + 1e-300
    )  # fmt: skip
    log_prior_l = np.log(10.0 * (1.0 - lapses / 1.0) ** 9 + 1e-300)  # Beta(1, 10) density

    beta = 2.0 * LN19 / widths  # (W,)
    f = special.expit(beta[None, :, None] * (x[None, None, :] - mids[:, None, None]))  # M W X
    loglik = np.zeros((N_MID, N_WIDTH, N_LAPSE))
    for j, lam in enumerate(lapses):
        p = np.clip(gamma + (1.0 - gamma - lam) * f, 1e-12, 1 - 1e-12)
        loglik[:, :, j] = (k * np.log(p) + (n - k) * np.log1p(-p)).sum(axis=2)
    log_post = (
        loglik
        + log_prior_m[:, None, None]
        + log_prior_w[None, :, None]
        + log_prior_l[None, None, :]
    )
    post = np.exp(log_post - log_post.max())
    tail = (1.0 - ci) / 2.0
    qs = (tail, 0.5, 1.0 - tail)
    m_lo, m_med, m_hi = _quantiles(mids, post.sum(axis=(1, 2)), qs)
    w_lo, w_med, w_hi = _quantiles(widths, post.sum(axis=(0, 2)), qs)
    l_lo, l_med, l_hi = _quantiles(lapses, post.sum(axis=(0, 1)), qs)
    return PosteriorFit(
        midpoint=m_med,
        midpoint_ci_low=m_lo,
        midpoint_ci_high=m_hi,
        slope=2.0 * LN19 / w_med,
        slope_ci_low=2.0 * LN19 / w_hi,  # a wide F is a shallow slope
        slope_ci_high=2.0 * LN19 / w_lo,
        lapse=l_med,
        lapse_ci_low=l_lo,
        lapse_ci_high=l_hi,
        n_trials=int(n.sum()),
        n_levels=len(levels),
    )
