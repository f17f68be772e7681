"""Psychometric functions: maximum-likelihood fits with a fixed guess rate and a free lapse rate.

The model of the probability of a "yes" (a correct answer in 2AFC, the comparison chosen in a
preference task) at stimulus level ``x``::

    P(x) = gamma + (1 - gamma - lambda) * F(x)

* ``gamma`` - the guess rate, fixed by the task: 0.5 for 2AFC with a correct answer, 1/k for
  identification among k labels, 0 for a preference (which looked more ...?) task;
* ``lambda`` - the lapse rate, free in ``[0, 0.1]`` (bounds configurable);
* ``F`` - a sigmoid from :data:`SIGMOIDS` (:mod:`facelab.psychometric_function`):

  - ``logistic``: ``F = 1 / (1 + exp(-beta * (x - alpha)))``; midpoint ``alpha``;
  - ``weibull``: ``F = 1 - exp(-(x / alpha) ** beta)`` (``x > 0``); midpoint
    ``alpha * ln(2) ** (1 / beta)``.

Every fit reports the midpoint of F (the level where F = 0.5), the slope parameter ``beta``,
the slope of F at its midpoint (per level unit), lambda, the deviance against the saturated
model with its degrees of freedom, and percentile confidence intervals from a parametric
bootstrap (data drawn from the fitted function at the observed levels and counts, refitted).

The search is bounded (logistic: the midpoint within two level ranges of the levels tested,
beta in [1e-3, 1e3] per level range; Weibull: alpha within [min level / 10, 10 x max level],
beta in [0.1, 50]). Estimates that end on a bound are reported, not hidden, in ``note``:

* perfect separation - the fitted F is on its floor or its ceiling at every level, the
  answers jumping from chance to ceiling between two adjacent levels: the slope is unbounded
  and the midpoint anywhere between those levels, so the midpoint and beta CIs are NaN;
* beta at its lower bound - no trend over the levels: the midpoint is not determined;
* the midpoint on its bound - it lies outside the levels tested;
* a CI limit that more than its tail share of the bootstrap refits put on a bound is
  censored: the lower midpoint limit becomes ``-inf`` (logistic) or 0 (Weibull), the upper
  ``inf`` - the data say only that it lies beyond the range searched.

Tables in and out are tidy: counts with columns ``level, n, k`` (trials, "yes" answers) -
:func:`count_responses` makes them from trial rows - and one row per fit out. The reference
values in ``tests/reference/psychometric_R.json`` come from R - ``glm`` with psyphy's
``mafc``/``logit.2asym`` links, lambda profiled with ``optimize`` - written by
``tests/reference/psychometric.R``; the log-likelihood includes the binomial coefficients,
as R's ``logLik`` does.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd
from scipy import optimize, special

from facelab.errors import AnalysisError
from facelab.psychometric_function import SIGMOIDS, midpoint, predict, slope_at_midpoint

__all__ = [
    "FIT_COLUMNS",
    "SIGMOIDS",
    "PsychometricFit",
    "count_responses",
    "fit_psychometric",
    "level_counts",
    "predict",
]

_EPS = 1e-12


@dataclass(frozen=True)
class PsychometricFit:
    """One maximum-likelihood fit. CIs are NaN when no bootstrap was asked for."""

    sigmoid: str
    gamma: float
    alpha: float
    beta: float
    lapse: float
    midpoint: float
    slope_at_midpoint: float
    deviance: float
    deviance_df: int
    log_likelihood: float
    n_trials: int
    n_levels: int
    converged: bool
    midpoint_ci_low: float = float("nan")
    midpoint_ci_high: float = float("nan")
    beta_ci_low: float = float("nan")
    beta_ci_high: float = float("nan")
    lapse_ci_low: float = float("nan")
    lapse_ci_high: float = float("nan")
    n_boot: int = 0
    note: str = ""  # estimates or CI limits on a search bound (see the module docstring)


FIT_COLUMNS: tuple[str, ...] = tuple(PsychometricFit.__dataclass_fields__)


def count_responses(
    trials: pd.DataFrame, *, x: str = "level", y: str = "correct", by: Sequence[str] = ()
) -> pd.DataFrame:
    """Trial rows (``y`` 0/1 or bool) -> counts ``[*by, level, n, k]`` sorted by level."""
    missing = [c for c in (x, y, *by) if c not in trials.columns]
    if missing:
        raise AnalysisError(f"psychometric data lack column(s) {missing}")
    # the two columns only, not the whole frame (simulations count thousands of sessions)
    keep = (trials[x].notna() & trials[y].notna()).to_numpy()
    values = pd.to_numeric(trials[y][keep].astype(float), errors="coerce")
    if values.isna().any() or not values.isin([0.0, 1.0]).all():
        raise AnalysisError(f"column {y!r} must hold 0/1 answers")
    numeric = pd.to_numeric(trials[x][keep], errors="coerce")
    if not by:  # counted directly (a groupby costs ~10 ms)
        return level_counts(level=numeric.to_numpy(dtype=float), y=values.to_numpy())
    data = trials.loc[keep, list(by)].assign(_y=values.to_numpy(), _x=numeric.array)
    keys = [*by, "_x"]
    out = data.groupby(keys, sort=True).agg(n=("_y", "size"), k=("_y", "sum")).reset_index()
    out = out.rename(columns={"_x": "level"})
    out["k"] = out["k"].astype(int)
    return out


def level_counts(*, level: np.ndarray, y: np.ndarray) -> pd.DataFrame:
    """Counts ``[level, n, k]`` sorted by level of trials at ``level`` (T,) with answers ``y``
    (T,) 0/1; trials with a NaN level or answer are left out. No other checks:
    :func:`count_responses` makes them (the calibration's simulated sessions need none and
    are counted thousands of times)."""
    level, y = np.asarray(level, float), np.asarray(y, float)
    kept = ~(np.isnan(level) | np.isnan(y))
    levels, at = np.unique(level[kept], return_inverse=True)
    return pd.DataFrame({
        "level": levels,
        "n": np.bincount(at, minlength=len(levels)),
        "k": np.bincount(at, weights=y[kept], minlength=len(levels))
        .round().astype(int),
    })  # fmt: skip


def _neg_loglik(
    params: np.ndarray, x: np.ndarray, n: np.ndarray, k: np.ndarray, sigmoid: str, gamma: float
) -> float:
    alpha, log_beta, lapse = params
    p = predict(x, sigmoid=sigmoid, alpha=alpha, beta=np.exp(log_beta), gamma=gamma, lapse=lapse)
    p = np.clip(p, _EPS, 1 - _EPS)
    return -float(np.sum(k * np.log(p) + (n - k) * np.log1p(-p)))


def _log_binom(n: np.ndarray, k: np.ndarray) -> float:
    return float(
        np.sum(special.gammaln(n + 1) - special.gammaln(k + 1) - special.gammaln(n - k + 1))
    )


def _saturated_loglik(n: np.ndarray, k: np.ndarray) -> float:
    q = k / n
    with np.errstate(divide="ignore", invalid="ignore"):
        terms = np.where(k > 0, k * np.log(q), 0.0) + np.where(
            n - k > 0, (n - k) * np.log1p(-q), 0.0
        )
    return float(np.sum(terms))


def _starts(x: np.ndarray, sigmoid: str, lapse_bounds: tuple[float, float]) -> list[np.ndarray]:
    span = float(np.ptp(x)) or 1.0
    lapse0 = min(max(0.02, lapse_bounds[0]), lapse_bounds[1])
    starts = []
    for q in (0.25, 0.5, 0.75):
        mid = float(np.quantile(x, q))
        if sigmoid == "logistic":
            for beta in (2.0 / span, 8.0 / span, 30.0 / span):
                starts.append(np.array([mid, np.log(beta), lapse0]))
        else:
            for beta in (1.0, 3.0, 8.0):
                starts.append(np.array([max(mid, 1e-6), np.log(beta), lapse0]))
    return starts


def fit_psychometric(
    counts: pd.DataFrame,
    *,
    sigmoid: str = "logistic",
    gamma: float,
    lapse_bounds: tuple[float, float] = (0.0, 0.1),
    n_boot: int = 0,
    rng: np.random.Generator | None = None,
    ci: float = 0.95,
) -> PsychometricFit:
    """Maximum-likelihood fit of ``counts`` (columns ``level, n, k``).

    Parameters
    ----------
    counts : one row per level: ``level`` (stimulus units), ``n`` trials, ``k`` "yes" answers.
    sigmoid : ``logistic`` or ``weibull`` (Weibull needs levels >= 0).
    gamma : the guess rate, fixed (0.5 for 2AFC, 1/k for k-label identification, 0 for
        preference).
    lapse_bounds : bounds of the free lapse rate; ``(0, 0)`` fixes it at 0.
    n_boot : parametric-bootstrap resamples for the CIs (0: none); needs ``rng``.
    """
    if sigmoid not in SIGMOIDS:
        raise AnalysisError(f"unknown sigmoid {sigmoid!r}; expected one of {', '.join(SIGMOIDS)}")
    if not 0.0 <= gamma < 1.0:
        raise AnalysisError(f"guess rate gamma must be in [0, 1), got {gamma}")
    lo, hi = lapse_bounds
    if not 0.0 <= lo <= hi < 1.0 - gamma:
        raise AnalysisError(
            f"lapse bounds {lapse_bounds} must satisfy 0 <= low <= high < 1 - gamma"
        )
    x = counts["level"].to_numpy(dtype=float)
    n = counts["n"].to_numpy(dtype=float)
    k = counts["k"].to_numpy(dtype=float)
    if len(x) < 2 or len(np.unique(x)) < 2:
        raise AnalysisError("a psychometric fit needs answers at two or more levels")
    if np.any(n <= 0) or np.any(k < 0) or np.any(k > n):
        raise AnalysisError("counts need n > 0 and 0 <= k <= n at every level")
    if sigmoid == "weibull" and np.any(x < 0):
        raise AnalysisError("the Weibull function needs levels >= 0; use the logistic")
    best = _fit(x, n, k, sigmoid=sigmoid, gamma=gamma, lapse_bounds=lapse_bounds)
    alpha, log_beta, lapse = best.x
    beta = float(np.exp(log_beta))
    loglik = -float(best.fun)  # without the binomial coefficients (they cancel in the deviance)
    fit = PsychometricFit(
        sigmoid=sigmoid,
        gamma=gamma,
        alpha=float(alpha),
        beta=beta,
        lapse=float(lapse),
        midpoint=float(midpoint(sigmoid, alpha, beta)),
        slope_at_midpoint=float(slope_at_midpoint(sigmoid, alpha, beta)),
        deviance=max(0.0, 2.0 * (_saturated_loglik(n, k) - loglik)),
        deviance_df=int(len(x) - (3 if hi > lo else 2)),
        log_likelihood=loglik + _log_binom(n, k),
        n_trials=int(n.sum()),
        n_levels=len(x),
        converged=bool(best.success),
    )
    bounds = _bounds(x, sigmoid, lapse_bounds)
    notes, separated = _bound_notes(x, best.x, sigmoid=sigmoid, bounds=bounds)
    fit = PsychometricFit(**{**asdict(fit), "note": "; ".join(notes)})
    if n_boot <= 0:
        return fit
    if rng is None:
        raise AnalysisError("a bootstrap needs a seeded numpy Generator (rng=)")
    p_hat = predict(x, sigmoid=sigmoid, alpha=alpha, beta=beta, gamma=gamma, lapse=lapse)
    draws = np.empty((n_boot, 3))
    alphas = np.empty(n_boot)
    for b in range(n_boot):
        kb = rng.binomial(n.astype(int), p_hat).astype(float)
        res = _fit(x, n, kb, sigmoid=sigmoid, gamma=gamma, lapse_bounds=lapse_bounds, start=best.x)
        a_b, lb_b, l_b = res.x
        alphas[b] = a_b
        draws[b] = (midpoint(sigmoid, a_b, np.exp(lb_b)), np.exp(lb_b), l_b)
    tail = (1.0 - ci) / 2.0
    low, high = np.percentile(draws, [100.0 * tail, 100.0 * (1.0 - tail)], axis=0)
    mid_low, mid_high = float(low[0]), float(high[0])
    tol = 1e-6 * max(1.0, bounds[0][1] - bounds[0][0])
    if not separated and np.mean(alphas <= bounds[0][0] + tol) > tail:
        mid_low = -np.inf if sigmoid == "logistic" else 0.0
        notes.append(
            f"midpoint CI: its lower limit lies below the range searched ({bounds[0][0]:g})"
        )
    if not separated and np.mean(alphas >= bounds[0][1] - tol) > tail:
        mid_high = np.inf
        notes.append(
            f"midpoint CI: its upper limit lies above the range searched ({bounds[0][1]:g})"
        )
    beta_low, beta_high = float(low[1]), float(high[1])
    steep = np.exp(bounds[1][1])
    if not separated and np.mean(draws[:, 1] >= steep * (1 - 1e-6)) > tail:
        beta_high = np.inf  # resamples pile on the bound: steeper than the levels can show
        notes.append(f"slope CI: its upper limit lies above the range searched ({steep:.3g}; "
                     "the levels tested cannot show how steep)")  # fmt: skip
    if separated:
        mid_low = mid_high = beta_low = beta_high = float("nan")
    return PsychometricFit(
        **{
            **asdict(fit),
            "midpoint_ci_low": mid_low,
            "midpoint_ci_high": mid_high,
            "beta_ci_low": beta_low,
            "beta_ci_high": beta_high,
            "lapse_ci_low": float(low[2]),
            "lapse_ci_high": float(high[2]),
            "n_boot": n_boot,
            "note": "; ".join(notes),
        }
    )


def _bounds(
    x: np.ndarray, sigmoid: str, lapse_bounds: tuple[float, float]
) -> list[tuple[float, float]]:
    """Search bounds of (alpha, log beta, lapse)."""
    span = float(np.ptp(x)) or 1.0
    if sigmoid == "logistic":
        alpha_bounds = (float(x.min()) - 2 * span, float(x.max()) + 2 * span)
        beta_bounds = (float(np.log(1e-3 / span)), float(np.log(1e3 / span)))
    else:
        positive = x[x > 0]
        alpha_bounds = (float(positive.min()) / 10 if len(positive) else 1e-6, float(x.max()) * 10)
        beta_bounds = (float(np.log(0.1)), float(np.log(50.0)))
    return [alpha_bounds, beta_bounds, lapse_bounds]


def _at_bound(value: np.ndarray | float, bound: tuple[float, float]) -> tuple[bool, bool]:
    """Whether ``value`` (or any of an array) sits on the low / high end of ``bound``."""
    tol = 1e-6 * max(1.0, abs(bound[1] - bound[0]))
    v = np.asarray(value, dtype=float)
    return bool(np.any(v <= bound[0] + tol)), bool(np.any(v >= bound[1] - tol))


def _bound_notes(
    x: np.ndarray, params: np.ndarray, *, sigmoid: str, bounds: list[tuple[float, float]]
) -> tuple[list[str], bool]:
    """Notes on a point estimate that is not determined; True when the answers separate
    perfectly (F at every level tested is on its floor or its ceiling, with levels on both:
    the likelihood keeps rising with the slope, so the optimiser stops wherever the gradient
    has flattened, at its bound or before)."""
    alpha, log_beta, _ = params
    notes = []
    f = SIGMOIDS[sigmoid](x, alpha, np.exp(log_beta))
    floor, ceiling = f < 0.01, f > 0.99
    separated = bool(np.all(floor | ceiling) and floor.any() and ceiling.any())
    if separated:
        notes.append(
            f"perfect separation: the answers jump from chance to ceiling between levels "
            f"{x[floor].max():g} and {x[ceiling].min():g}, so the midpoint is anywhere there "
            "and the slope unbounded; midpoint and slope CIs not given"
        )
    elif _at_bound(log_beta, bounds[1])[0]:
        notes.append("slope at its lower bound: no trend over the levels, midpoint undetermined")
    elif _at_bound(log_beta, bounds[1])[1]:
        notes.append("slope at its upper bound: steeper than the levels tested can show")
    alpha_low, alpha_high = _at_bound(alpha, bounds[0])
    if (alpha_low or alpha_high) and not separated:
        side = "below" if alpha_low else "above"
        notes.append(f"midpoint on the search bound, {side} the levels tested")
    return notes, separated


def _fit(
    x: np.ndarray,
    n: np.ndarray,
    k: np.ndarray,
    *,
    sigmoid: str,
    gamma: float,
    lapse_bounds: tuple[float, float],
    start: np.ndarray | None = None,
) -> optimize.OptimizeResult:
    bounds = _bounds(x, sigmoid, lapse_bounds)
    starts = [start] if start is not None else _starts(x, sigmoid, lapse_bounds)
    best = None
    for s0 in starts:
        s0 = np.array([np.clip(v, b[0], b[1]) for v, b in zip(s0, bounds, strict=True)])
        res = optimize.minimize(
            _neg_loglik,
            s0,
            args=(x, n, k, sigmoid, gamma),
            method="L-BFGS-B",
            bounds=bounds,
        )
        if best is None or res.fun < best.fun:
            best = res
    assert best is not None
    return best
