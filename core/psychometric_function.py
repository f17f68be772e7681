"""The psychometric function shared by the fits (:mod:`facelab.analysis.psychometric`) and the
adaptive rules that choose levels with it (:mod:`facelab.staircase`). Pure numpy.

The probability of a "yes" (a correct answer in 2AFC, the comparison chosen in a preference
task) at stimulus level ``x``::

    P(x) = gamma + (1 - gamma - lambda) * F(x)

with ``gamma`` the guess rate fixed by the task, ``lambda`` the lapse rate and ``F`` one of
:data:`SIGMOIDS`:

* ``logistic``: ``F = 1 / (1 + exp(-beta * (x - alpha)))``; midpoint ``alpha``, slope at the
  midpoint ``beta / 4`` per level unit;
* ``weibull``: ``F = 1 - exp(-(x / alpha) ** beta)`` (``x >= 0``); midpoint
  ``alpha * ln(2) ** (1 / beta)``.

Every function broadcasts: ``alpha`` and ``beta`` may be arrays (a parameter grid) as long as
their shapes broadcast against ``x``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike
from scipy import special

__all__ = ["SIGMOIDS", "midpoint", "predict", "slope_at_midpoint"]


def _logistic(x: np.ndarray, alpha: ArrayLike, beta: ArrayLike) -> np.ndarray:
    return special.expit(np.asarray(beta) * (x - np.asarray(alpha)))


def _weibull(x: np.ndarray, alpha: ArrayLike, beta: ArrayLike) -> np.ndarray:
    z = np.clip(np.asarray(x, dtype=float), 0.0, None) / np.asarray(alpha)
    return -np.expm1(-(z ** np.asarray(beta)))


#: name -> F(x, alpha, beta)
SIGMOIDS: dict[str, Callable[[np.ndarray, ArrayLike, ArrayLike], np.ndarray]] = {
    "logistic": _logistic,
    "weibull": _weibull,
}


def midpoint(sigmoid: str, alpha: ArrayLike, beta: ArrayLike) -> np.ndarray:
    """The level where F = 1/2 (level units)."""
    alpha, beta = np.asarray(alpha, dtype=float), np.asarray(beta, dtype=float)
    if sigmoid == "logistic":
        return alpha + 0.0 * beta
    return alpha * np.log(2.0) ** (1.0 / beta)


def slope_at_midpoint(sigmoid: str, alpha: ArrayLike, beta: ArrayLike) -> np.ndarray:
    """dF/dx at the midpoint (per level unit)."""
    beta = np.asarray(beta, dtype=float)
    if sigmoid == "logistic":
        return beta / 4.0 + 0.0 * np.asarray(alpha)
    return beta * np.log(2.0) / (2.0 * midpoint(sigmoid, alpha, beta))


def predict(
    x: ArrayLike,
    *,
    sigmoid: str,
    alpha: ArrayLike,
    beta: ArrayLike,
    gamma: float,
    lapse: ArrayLike,
) -> np.ndarray:
    """P(x) of the model above; the parameters broadcast against ``x``."""
    f = SIGMOIDS[sigmoid](np.asarray(x, dtype=float), alpha, beta)
    return gamma + (1.0 - gamma - np.asarray(lapse)) * f
