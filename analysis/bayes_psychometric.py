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
log-spaced widths x 51 lapse rates (vectorised; tens of ms per participant). Logistic F only;
the model otherwise is that of :mod:`facelab.analysis.psychometric`. Two summaries of it:

* ``interval="profile"`` (the default): the priors act as a penalty on the likelihood. The
  estimate is the posterior's mode (the penalised maximum likelihood, width on a log scale)
  and each interval holds the values whose *profile* - the log posterior maximised over the
  other two parameters - lies within ``chi2_1(ci) / 2`` of the mode (a penalised
  likelihood-ratio interval, as ``logistf`` gives for separated logistic regressions; ends
  interpolated between grid cells). Over simulated observers these 95 % intervals hold the
  true midpoint and slope 0.91-0.995 of the time across truths and designs - a little
  conservative where 50 staircase trials cannot bound the slope (0.974 / 0.981 at
  ``gain_staircase``'s observer over 1000); ``scripts/psychometric_coverage.py``.
* calibrated profile intervals (``drops=``, what ``facelab analyze`` gives each participant):
  the same mode and profile, but each interval ends where the profile has dropped by an
  amount found for the study's design - participants are simulated through the design as
  an observer at the posterior mode of everyone's answers pooled, and
  :func:`calibrated_drops` takes the 95th percentile of their profiles' deficit at that
  (known) truth: a parametric-bootstrap calibration of the penalised likelihood ratio in
  place of the chi-square's 1.92.
* ``interval="credible"``: marginal posterior medians and equal-tailed credible intervals
  (psignifit's summary; checked against psignifit 4). With 50 trials the priors' breadth
  makes these conservative (coverage 0.995 / 1.000 at ``gain_staircase``'s observer) and a
  slope steeper than the levels' spacing shows is pulled down (0.75 at slope 40).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import pandas as pd
from scipy import special, stats

from facelab.errors import AnalysisError

__all__ = ["PosteriorFit", "calibrated_drops", "posterior_fit"]

LN19 = float(np.log(19.0))
N_MID, N_WIDTH, N_LAPSE = 101, 101, 51
LAPSE_MAX = 0.5


@dataclass(frozen=True)
class PosteriorFit:
    """Point estimates and ``ci`` intervals of one fit; ``interval`` says which summary
    (``profile``: posterior mode and profile intervals; ``credible``: marginal medians and
    equal-tailed credible intervals). ``*_at_limit`` (profile only) marks a parameter the data
    alone do not bound: the likelihood without priors does not exclude the grid's extremes
    (for the slope: a step function, as near-separated data allow), so the priors close its
    interval."""

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
    interval: str = "profile"
    slope_at_limit: bool = False
    midpoint_at_limit: bool = False


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


def _profile_interval(values: np.ndarray, profile: np.ndarray, drop: float,
                      likelihood: np.ndarray) -> tuple[float, float, float, bool]:  # fmt: skip
    """(low, mode, high, unbounded) of the values whose ``profile`` (log posterior, one per
    value, values sorted) lies within ``drop`` of its maximum; each end is interpolated
    linearly between the last cell inside and the first outside. ``unbounded``: the profile
    ``likelihood`` (no priors) at the first or last grid value is still within ``drop`` of its
    maximum - the data alone do not exclude the grid's extremes (for the width: a step or a
    flat function), so the priors set that end of the interval."""
    deficit = profile.max() - profile  # >= 0, 0 at the mode
    best = int(np.argmax(profile))
    inside = deficit <= drop
    lo_i, hi_i = best, best
    while lo_i > 0 and inside[lo_i - 1]:
        lo_i -= 1
    while hi_i < len(values) - 1 and inside[hi_i + 1]:
        hi_i += 1

    def crossing(a: int, b: int) -> float:  # a inside, b outside
        t = (drop - deficit[a]) / (deficit[b] - deficit[a])
        return float(values[a] + t * (values[b] - values[a]))

    low = crossing(lo_i, lo_i - 1) if lo_i > 0 else float(values[0])
    high = crossing(hi_i, hi_i + 1) if hi_i < len(values) - 1 else float(values[-1])
    data_deficit = likelihood.max() - likelihood
    unbounded = data_deficit[0] <= drop or data_deficit[-1] <= drop
    return low, float(values[best]), high, bool(unbounded)


@dataclass(frozen=True)
class _Grid:
    """The posterior on a grid: midpoints (M,), widths (W,), lapse rates (L,), the log
    likelihood and the log posterior (M, W, L)."""

    mids: np.ndarray
    widths: np.ndarray
    lapses: np.ndarray
    loglik: np.ndarray
    log_post: np.ndarray


def _binomial_loglik(z: np.ndarray, *, yes: np.ndarray, no: np.ndarray, gamma: float,
                     lapses: np.ndarray) -> np.ndarray:  # fmt: skip
    """The log likelihood (M, W, L) of ``yes`` and ``no`` answers (X,) at each level, where
    the function without guesses and lapses is ``f = expit(z)`` (``z``: M, W, X): p = gamma +
    (1 - gamma - lapse) f, and 1 - p as (1 - gamma)(1 - f) + lapse f with 1 - f = expit(-z),
    so that neither loses digits to a difference near 1; each is held at 1e-12 or more.
    Levels without yes (or without no) answers add nothing to that term and are left out of
    it. The logarithms, which are nearly all the work (the calibration fits this thousands of
    times), run in single precision, one lapse at a time and in place: 2.7 times faster than
    double here; each cell within a few millionths of the sum of its terms' magnitudes of the
    double-precision value (tests/test_bayes_psychometric.py), interval ends within about
    1e-4 of it."""
    lo = np.float32(1e-12)
    has_yes, has_no = yes > 0, no > 0
    cells = z.shape[0] * z.shape[1]  # one row of levels per (midpoint, width): one gemv
    z_yes = z[..., has_yes].reshape(cells, -1)
    z_no = z[..., has_no].reshape(cells, -1)
    f_yes = special.expit(z_yes).astype(np.float32)
    f_no, g_no = special.expit(z_no).astype(np.float32), special.expit(-z_no).astype(np.float32)
    yes32, no32 = yes[has_yes].astype(np.float32), no[has_no].astype(np.float32)
    p_yes, q_no, tmp = np.empty_like(f_yes), np.empty_like(f_no), np.empty_like(f_no)
    out = np.empty((cells, len(lapses)))
    for j, lam in enumerate(lapses):
        np.multiply(f_yes, np.float32(1.0 - gamma - lam), out=p_yes)
        p_yes += np.float32(gamma)
        np.maximum(p_yes, lo, out=p_yes)
        np.log(p_yes, out=p_yes)
        np.multiply(g_no, np.float32(1.0 - gamma), out=q_no)
        np.multiply(f_no, np.float32(lam), out=tmp)
        q_no += tmp
        np.maximum(q_no, lo, out=q_no)
        np.log(q_no, out=q_no)
        out[:, j] = p_yes @ yes32 + q_no @ no32
    return out.reshape(*z.shape[:2], len(lapses))


def _grid(counts: pd.DataFrame, *, gamma: float,
          shape: tuple[int, int, int] = (N_MID, N_WIDTH, N_LAPSE)) -> _Grid:  # fmt: skip
    """The log likelihood and log posterior of ``counts`` (``level, n, k``) on a grid of
    ``shape`` (midpoints, widths, lapse rates) spanning the priors' support."""
    x = counts["level"].to_numpy(dtype=float)
    n = counts["n"].to_numpy(dtype=float)
    k = counts["k"].to_numpy(dtype=float)
    levels = np.unique(x)
    if len(levels) < 2:
        raise AnalysisError("a psychometric fit needs answers at two or more levels")
    lo, hi = float(levels.min()), float(levels.max())
    span = hi - lo
    step = float(np.diff(levels).min())
    n_mid, n_width, n_lapse = shape
    mids = np.linspace(lo - 0.5 * span, hi + 0.5 * span, n_mid)
    widths = np.exp(np.linspace(np.log(step), np.log(3.0 * span), n_width))
    lapses = np.linspace(0.0, LAPSE_MAX, n_lapse)

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
    z = beta[None, :, None] * (x[None, None, :] - mids[:, None, None])  # M W X
    loglik = _binomial_loglik(z, yes=k, no=n - k, gamma=gamma, lapses=lapses)
    log_post = (
        loglik
        + log_prior_m[:, None, None]
        + log_prior_w[None, :, None]
        + log_prior_l[None, None, :]
    )
    return _Grid(mids, widths, lapses, loglik, log_post)


def posterior_fit(
    counts: pd.DataFrame,
    *,
    gamma: float,
    ci: float = 0.95,
    interval: Literal["profile", "credible"] = "profile",
    drops: tuple[float, float] | None = None,
) -> PosteriorFit:
    """The posterior fit of ``counts`` (columns ``level, n, k``: trials and "yes" answers at
    each level) with guess rate ``gamma``, summarised as ``interval`` says (module doc).
    ``drops`` (profile only): the log-posterior drops that end the midpoint's and the width's
    intervals, as :func:`calibrated_drops` finds them for a design (default ``chi2_1(ci) / 2``
    for both); the lapse's interval keeps ``chi2_1(ci) / 2``."""
    if interval not in ("profile", "credible"):
        raise AnalysisError(f"interval must be 'profile' or 'credible', not {interval!r}")
    g = _grid(counts, gamma=gamma)
    mids, widths, lapses, loglik, log_post = g.mids, g.widths, g.lapses, g.loglik, g.log_post
    n = counts["n"].to_numpy(dtype=float)
    levels = np.unique(counts["level"].to_numpy(dtype=float))
    if interval == "profile":
        drop = float(stats.chi2.ppf(ci, df=1)) / 2.0
        drop_m, drop_w = drops if drops is not None else (drop, drop)
        # log-posterior cells have -690 where a prior is zero; the profile never ends there
        m_lo, m_est, m_hi, m_lim = _profile_interval(
            mids, log_post.max(axis=(1, 2)), drop_m, loglik.max(axis=(1, 2))
        )
        w_lo, w_est, w_hi, w_lim = _profile_interval(
            widths, log_post.max(axis=(0, 2)), drop_w, loglik.max(axis=(0, 2))
        )
        l_lo, l_est, l_hi, _ = _profile_interval(
            lapses, log_post.max(axis=(0, 1)), drop, loglik.max(axis=(0, 1))
        )
    else:
        post = np.exp(log_post - log_post.max())
        tail = (1.0 - ci) / 2.0
        qs = (tail, 0.5, 1.0 - tail)
        m_lo, m_est, m_hi = _quantiles(mids, post.sum(axis=(1, 2)), qs)
        w_lo, w_est, w_hi = _quantiles(widths, post.sum(axis=(0, 2)), qs)
        l_lo, l_est, l_hi = _quantiles(lapses, post.sum(axis=(0, 1)), qs)
        m_lim = w_lim = False
    return PosteriorFit(
        midpoint=m_est,
        midpoint_ci_low=m_lo,
        midpoint_ci_high=m_hi,
        slope=2.0 * LN19 / w_est,
        slope_ci_low=2.0 * LN19 / w_hi,  # a wide F is a shallow slope
        slope_ci_high=2.0 * LN19 / w_lo,
        lapse=l_est,
        lapse_ci_low=l_lo,
        lapse_ci_high=l_hi,
        n_trials=int(n.sum()),
        n_levels=len(levels),
        interval=interval,
        slope_at_limit=w_lim,
        midpoint_at_limit=m_lim,
    )


#: the coarser grid of the calibration's many fits (an eighth of the cells)
CALIBRATION_GRID = (51, 51, 26)


def _deficit_at(values: np.ndarray, profile: np.ndarray, value: float) -> float:
    """How far below its maximum the ``profile`` lies at ``value`` (linear between cells;
    infinite outside the grid, where the prior is zero)."""
    if not values[0] <= value <= values[-1]:
        return float("inf")
    return float(np.interp(value, values, profile.max() - profile))


def calibrated_drops(
    samples: Sequence[pd.DataFrame],
    *,
    gamma: float,
    midpoint: float,
    slope: float,
    ci: float = 0.95,
) -> tuple[float, float]:
    """The log-posterior drops (midpoint, width) at which profile intervals hold the truth
    ``ci`` of the time in ``samples``: counts (``level, n, k``) of participants simulated
    through the study's design as an observer with this ``midpoint`` and logistic ``slope``.
    For each sample, the profile's deficit at the true value; the drops are their ``ci``
    quantiles (a parametric-bootstrap calibration of the penalised
    likelihood ratio; with 50 staircase trials the chi-square's 1.92 over-covers where the
    data do not bound the slope). Fitted on :data:`CALIBRATION_GRID`. Samples with answers at
    one level only are skipped; fewer than 20 usable raise AnalysisError. A drop is infinite
    when more than ``1 - ci`` of the samples' priors exclude the truth (e.g. a pooled slope
    shallower than an adaptive design's narrow span of levels allows): the interval is then
    the grid's whole range."""
    log_width = float(np.log(2.0 * LN19 / slope))
    mid_deficits, width_deficits = [], []
    for counts in samples:
        try:
            g = _grid(counts, gamma=gamma, shape=CALIBRATION_GRID)
        except AnalysisError:
            continue
        mid_deficits.append(_deficit_at(g.mids, g.log_post.max(axis=(1, 2)), midpoint))
        width_deficits.append(_deficit_at(np.log(g.widths), g.log_post.max(axis=(0, 2)), log_width))
    if len(mid_deficits) < 20:
        raise AnalysisError(
            f"calibrating the intervals needs 20 or more simulated participants with answers "
            f"at two levels; {len(mid_deficits)} had them"
        )
    return (_upper_quantile(mid_deficits, ci), _upper_quantile(width_deficits, ci))


def _upper_quantile(deficits: Sequence[float], ci: float) -> float:
    """The ``ci`` quantile of ``deficits`` at rank ``ci * (n + 1)`` (linear between order
    statistics; Hyndman & Fan's type 6): the k-th of n sorted draws lies above a share
    k / (n + 1) of their distribution on average, so an interval ending there holds the truth
    ``ci`` of the time on average over calibrations (numpy's default rank ``ci * (n - 1) + 1``
    gives 0.945 with n = 200). Infinite when the order statistic above that rank is: a truth
    outside the prior's support for that many simulated participants is held only by an
    interval spanning the whole grid (numpy would interpolate NaN between two infinities,
    and a NaN drop gives an empty interval)."""
    ordered = np.sort(np.asarray(deficits, dtype=float))
    upper = min(int(np.ceil(ci * (len(ordered) + 1))), len(ordered)) - 1
    if np.isinf(ordered[upper]):
        return float("inf")
    return float(np.quantile(ordered, ci, method="weibull"))
