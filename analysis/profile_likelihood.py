"""Bounded maximum likelihood with profile-likelihood intervals, for the small parametric
fits of the objective tasks (audio-visual timing windows, speech reception thresholds).

A model is its log-likelihood ``loglik(theta) -> float`` over a parameter vector with box
``bounds`` (and, optionally, its ``gradient(theta) -> (k,)``: without it L-BFGS-B differences
the likelihood numerically, several evaluations per step; a model that computes both at once
passes ``both(theta) -> (loglik, gradient)`` as well, and the optimiser calls only that).
:func:`best_fit` maximises it from several starts (L-BFGS-B); with ``fixed`` parameters held
it is the profile. :func:`profile_interval` finds where twice the drop of the profile
log-likelihood from the maximum reaches the chi-square(1) quantile, re-fitting the other
parameters at each value from the profile's nearest point fitted so far on the best fit's
side (the profile followed outwards: it is continuous there, and a near point needs fewer
steps), by Newton steps that take the profile's slope from the model's gradient; an end
that would pass the parameter's bound is returned as ``-inf`` / ``inf``.
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
    (log-likelihood ``ll``); ``-inf`` / ``inf`` for an end beyond the search bound.

    With the model's gradient an end is found by Newton steps on the signed root of the
    drop, sqrt(2 (ll - profile)), which is close to linear in the parameter: its slope at a
    profile point is the likelihood's derivative in the held parameter there (the other
    parameters are at their best, so they add nothing to the profile's slope), so each step
    costs one fit; a step that would leave the bracket the fits so far have narrowed is a
    bisection instead. Without it, Brent's method on the drop (``xtol`` 1e-3)."""
    best = np.asarray(theta, dtype=float)
    fitted = [best]  # the profile's points so far
    drops: dict[float, tuple[float, np.ndarray]] = {float(best[index]): (-cutoff, best)}

    def profile(value: float) -> tuple[float, np.ndarray]:
        """Twice the drop at ``value`` minus the cutoff, and the profile's best point: fitted
        from the nearest point fitted so far on the best fit's side of ``value`` (the
        profile followed outwards), and when that drop reaches the cutoff also from the
        nearest point beyond it, if any (a fit from either side can stop in a worse
        optimum where the answers change steeply between offsets; the better one counts)."""
        if value not in drops:
            side = np.sign(value - best[index])
            inner = [t for t in fitted if (value - t[index]) * side >= 0]
            outer = [t for t in fitted if (value - t[index]) * side < 0]
            starts = [min(inner, key=lambda t: abs(t[index] - value))]
            at_v, ll_v = best_fit(loglik, bounds=bounds, starts=starts, fixed={index: value},
                                  gradient=gradient, both=both)  # fmt: skip
            if outer and 2.0 * (ll - ll_v) >= cutoff:
                other, ll_o = best_fit(loglik, bounds=bounds, fixed={index: value},
                                       starts=[min(outer, key=lambda t: abs(t[index] - value))],
                                       gradient=gradient, both=both)  # fmt: skip
                if ll_o > ll_v:
                    at_v, ll_v = other, ll_o
            fitted.append(at_v)
            drops[value] = (2.0 * (ll - ll_v) - cutoff, at_v)
        return drops[value]

    def grad(t: np.ndarray) -> np.ndarray:
        """The log-likelihood's gradient at ``t``."""
        return np.asarray(both(t)[1] if both is not None else gradient(t),  # type: ignore[misc]
                          dtype=float)  # fmt: skip

    def slope(at_v: np.ndarray) -> float:
        """d loglik / d theta[index] at a profile point."""
        return float(grad(at_v)[index])

    lo_b, hi_b = bounds[index]
    at = float(theta[index])
    if gradient is None and both is None:
        ends = []
        for bound in (lo_b, hi_b):
            if abs(bound - at) < 1e-9 or profile(bound)[0] < 0:
                ends.append(-math.inf if bound == lo_b else math.inf)
            else:
                ends.append(optimize.brentq(lambda v: profile(v)[0], min(at, bound),
                                            max(at, bound), xtol=1e-3))  # fmt: skip
        return ends[0], ends[1]
    curvature = _profile_curvature(grad, theta=best, bounds=bounds, index=index)
    lo, hi = (-math.inf if abs(lo_b - at) < 1e-9 else
              _crossing(profile, slope, at=at, bound=lo_b, cutoff=cutoff, curvature=curvature),
              math.inf if abs(hi_b - at) < 1e-9 else
              _crossing(profile, slope, at=at, bound=hi_b, cutoff=cutoff, curvature=curvature))
    return lo, hi


#: a Newton step shorter than this (in the parameter's units) ends the search for an end:
#: the step is taken without another fit (its error is of the order of its square)
_STEP_TOL = 1e-3


def _profile_curvature(
    grad: Callable[[np.ndarray], np.ndarray], *, theta: np.ndarray, bounds: Bounds, index: int
) -> float:
    """-d2 profile / d theta[index]^2 at the maximum ``theta``: 1 / (the inverse of minus the
    Hessian)[index, index] over the parameters not on a bound (a parameter on its bound stays
    there along the profile), the Hessian from differences of the gradient (steps into the
    box). NaN when it is not a maximum's (no curvature to start from)."""
    free = [i for i, (lo, hi) in enumerate(bounds)
            if i == index or (theta[i] > lo + 1e-6 and theta[i] < hi - 1e-6)]  # fmt: skip
    g0 = grad(theta)
    rows = []
    for i in free:
        h = 1e-5 * max(1.0, abs(theta[i]))
        h = -h if theta[i] + h > bounds[i][1] else h
        shifted = theta.copy()
        shifted[i] += h
        rows.append((grad(shifted) - g0)[free] / h)
    neg_hessian = -0.5 * (np.array(rows) + np.array(rows).T)
    if not np.all(np.isfinite(neg_hessian)) or np.any(np.linalg.eigvalsh(neg_hessian) <= 0):
        return math.nan
    return 1.0 / float(np.linalg.inv(neg_hessian)[free.index(index), free.index(index)])


def _crossing(
    profile: Callable[[float], tuple[float, np.ndarray]], slope: Callable[[np.ndarray], float],
    *, at: float, bound: float, cutoff: float, curvature: float,
) -> float:  # fmt: skip
    """Where the profile's drop from the best fit ``at`` reaches ``cutoff`` towards
    ``bound`` (+-inf when it does not by the bound): Newton on r(u) = sqrt(drop) at distance
    u from ``at``, from the quadratic approximation's end sqrt(cutoff / ``curvature``) (the
    bound when that is unknown), inside a bracket that every fit narrows."""
    direction = 1.0 if bound > at else -1.0
    span = abs(bound - at)
    target = math.sqrt(cutoff)
    lo, hi, hi_known = 0.0, span, False  # r(lo) < target; r(hi) >= target once hi_known
    u = min(target / math.sqrt(curvature), span) if curvature > 0 else span
    for _ in range(100):
        excess, at_v = profile(at + direction * u)
        r = math.sqrt(max(excess + cutoff, 0.0))
        if r < target:
            if u >= span:
                return direction * math.inf  # the drop stays under the cutoff to the bound
            lo = u
        else:
            hi, hi_known = u, True
        dr = -slope(at_v) * direction / r if r > 0 else math.nan  # d r / d u
        step = (target - r) / dr if dr > 0 else math.nan
        if abs(step) < _STEP_TOL and lo <= u + step <= hi:
            return at + direction * (u + step)
        if hi_known and hi - lo < _STEP_TOL:
            return at + direction * 0.5 * (lo + hi)
        nxt = u + step
        if not lo < nxt < hi:  # outside the bracket, or no slope to go by
            nxt = span if not hi_known else 0.5 * (lo + hi)
        u = nxt
    return at + direction * (0.5 * (lo + hi) if hi_known else math.inf)


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

