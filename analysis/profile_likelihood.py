"""Bounded maximum likelihood with profile-likelihood intervals, for the small parametric
fits of the objective tasks (audio-visual timing windows, speech reception thresholds).

A model is its log-likelihood ``loglik(theta) -> float`` over a parameter vector with box
``bounds`` (and, optionally, its ``gradient(theta) -> (k,)``: without it L-BFGS-B differences
the likelihood numerically, several evaluations per step; a model that computes both at once
passes ``both(theta) -> (loglik, gradient)`` as well, and the optimiser calls only that).
:func:`best_fit` maximises it from several starts (L-BFGS-B); with ``fixed`` parameters held
it is the profile. :func:`profile_interval` finds where twice the drop of the profile
log-likelihood from the maximum reaches the chi-square(1) quantile, re-fitting the other
parameters at each value from the profile's nearest point fitted so far (the best fit at
first: the profile is continuous there, and a near point needs fewer steps); an end that
would pass the parameter's bound is returned as ``-inf`` / ``inf``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
from scipy import optimize, stats

from facelab.errors import AnalysisError

__all__ = [
    "Both",
    "Bounds",
    "Gradient",
    "LogLik",
    "best_fit",
    "binomial_deviance",
    "binomial_loglik_and_weight",
    "chi2_cutoff",
    "on_bound",
    "profile_interval",
]

LogLik = Callable[[np.ndarray], float]
Gradient = Callable[[np.ndarray], np.ndarray]
Both = Callable[[np.ndarray], tuple[float, np.ndarray]]
Bounds = Sequence[tuple[float, float]]


def chi2_cutoff(level: float) -> float:
    """Twice the log-likelihood drop of a ``level`` profile interval (one parameter)."""
    return float(stats.chi2.ppf(level, 1))


def best_fit(
    loglik: LogLik,
    *,
    bounds: Bounds,
    starts: Sequence[np.ndarray],
    fixed: dict[int, float] | None = None,
    gradient: Gradient | None = None,
    both: Both | None = None,
) -> tuple[np.ndarray, float]:
    """The parameters (``fixed`` {index: value} held) maximising ``loglik`` within
    ``bounds`` from the best of ``starts``, and the log-likelihood there; ``gradient`` the
    log-likelihood's derivatives (k,), if known; ``both`` the two at once (used instead)."""
    fixed = fixed or {}
    k = len(bounds)
    free = [i for i in range(k) if i not in fixed]
    lo = np.array([bounds[i][0] for i in free])
    hi = np.array([bounds[i][1] for i in free])

    def full(free_values: np.ndarray) -> np.ndarray:
        theta = np.empty(k)
        theta[free] = free_values
        for i, v in fixed.items():
            theta[i] = v
        return theta

    def with_gradient(free_values: np.ndarray) -> tuple[float, np.ndarray]:
        theta = full(free_values)
        if both is not None:
            value, grad = both(theta)
            return -value, -np.asarray(grad, dtype=float)[free]
        return -loglik(theta), -np.asarray(gradient(theta), dtype=float)[free]  # type: ignore[misc]

    def without(free_values: np.ndarray) -> float:
        return -loglik(full(free_values))

    best_theta, best_ll = None, -math.inf
    for start in starts:
        s = np.clip(np.asarray(start, dtype=float)[free], lo, hi)
        known = gradient is not None or both is not None
        res = optimize.minimize(with_gradient if known else without, s,
                                jac=known, method="L-BFGS-B",
                                bounds=[bounds[i] for i in free])  # fmt: skip
        if -res.fun > best_ll:
            best_theta, best_ll = full(res.x), float(-res.fun)
    if best_theta is None:
        raise AnalysisError("the model could not be fitted from any start (its likelihood is "
                            "not finite there)")  # fmt: skip
    return best_theta, best_ll


def profile_interval(
    loglik: LogLik,
    *,
    bounds: Bounds,
    theta: np.ndarray,
    ll: float,
    index: int,
    cutoff: float,
    gradient: Gradient | None = None,
    both: Both | None = None,
) -> tuple[float, float]:
    """The profile-likelihood interval of parameter ``index`` around the maximum ``theta``
    (log-likelihood ``ll``); ``-inf`` / ``inf`` for an end beyond the search bound."""
    fitted = [np.asarray(theta, dtype=float)]  # the profile's points so far
    drops: dict[float, float] = {float(theta[index]): -cutoff}  # each value fitted once

    def drop(value: float) -> float:
        if value not in drops:
            near = min(fitted, key=lambda t: abs(t[index] - value))
            at_v, ll_v = best_fit(loglik, bounds=bounds, starts=[near], fixed={index: value},
                                  gradient=gradient, both=both)  # fmt: skip
            fitted.append(at_v)
            drops[value] = 2.0 * (ll - ll_v) - cutoff
        return drops[value]

    lo_b, hi_b = bounds[index]
    at = float(theta[index])
    ends = []
    for bound in (lo_b, hi_b):
        if abs(bound - at) < 1e-9 or drop(bound) < 0:
            ends.append(-math.inf if bound == lo_b else math.inf)
            continue
        ends.append(optimize.brentq(drop, min(at, bound), max(at, bound), xtol=1e-3))
    return ends[0], ends[1]


def on_bound(value: float, bound: tuple[float, float], *, tol: float = 1e-6) -> bool:
    """True when an estimate sits on either end of its search bound."""
    return value <= bound[0] + tol or value >= bound[1] - tol


def binomial_loglik_and_weight(
    p: np.ndarray, *, n: np.ndarray, k: np.ndarray, eps: float
) -> tuple[float, np.ndarray]:
    """The log likelihood of ``k`` of ``n`` "yes" answers at probabilities ``p`` held inside
    [eps, 1 - eps], and its derivative in each ``p`` (0 where ``p`` is held, as the held
    likelihood is flat there): a model's gradient is its rows of dp/dtheta times these. In
    few numpy calls - an optimiser evaluates it hundreds of thousands of times a study."""
    pc = np.minimum(np.maximum(p, eps), 1 - eps)
    qc = 1.0 - pc
    m = n - k
    weight = (k / pc - m / qc) * ((p > eps) & (p < 1 - eps))
    return float(k @ np.log(pc) + m @ np.log(qc)), weight


def binomial_deviance(k: np.ndarray, n: np.ndarray, p: np.ndarray) -> float:
    """Deviance of fitted proportions ``p`` against the saturated model (one proportion per
    level) for ``k`` of ``n`` "yes" answers; ``p`` kept inside (0, 1)."""
    p = np.clip(p, 1e-9, 1 - 1e-9)
    with np.errstate(divide="ignore", invalid="ignore"):
        sat = np.where(k > 0, k * np.log(k / n), 0.0) + np.where(
            n > k, (n - k) * np.log1p(-k / n), 0.0
        )
    return float(2.0 * np.sum(sat - (k * np.log(p) + (n - k) * np.log1p(-p))))

