"""Graded designs: VAS ratings of a stimulus dimension shown at fixed levels.

Two analyses of how ratings change with the level, both tidy DataFrames in and out:

* :func:`trend_contrast` - the linear trend contrast of the repeated-measures ANOVA. Each
  participant's cell means (one per level) give a least-squares slope
  ``s_i = sum_j c_j * m_ij / sum_j c_j**2`` with ``c_j`` the centred levels (so unequal
  spacing is respected); the contrast is tested against its own error term,
  ``t = mean(s) / (sd(s) / sqrt(n))`` on ``n - 1`` df, ``F = t**2`` - the multivariate
  (separate-error) contrast, as emmeans does on an afex model.
* :func:`graded_lmm` - a linear mixed model on every rating,
  ``rating ~ level + (1 + level | participant)``, fitted by REML (statsmodels MixedLM):
  the fixed slope with its standard error, Wald z and p, and the random-effect SDs and
  correlation.

Reference values from R (afex + emmeans for the contrast, lme4 for the mixed model) are in
``tests/reference/graded_R.json``, written by ``tests/reference/graded.R``.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np
import pandas as pd
from scipy import stats as sps

from facelab.analysis.stats import require
from facelab.errors import AnalysisError

__all__ = ["LMM_COLUMNS", "TREND_COLUMNS", "graded_lmm", "trend_contrast"]

TREND_COLUMNS = ("n", "levels", "slope", "se", "ci_low", "ci_high", "t", "df", "f", "p")
LMM_COLUMNS = (
    "n_participants",
    "n_obs",
    "intercept",
    "slope",
    "slope_se",
    "t",
    "df",
    "p",
    "sd_intercept",
    "sd_slope",
    "corr",
    "sd_residual",
    "converged",
)


def _subject(subject: str, participant: str | None) -> str:
    """``subject=`` is the name (as everywhere in facelab.analysis); ``participant=`` was the
    old one and still works for one release."""
    if participant is None:
        return subject
    warnings.warn(
        "participant= is deprecated; use subject= (as the other analysis functions do)",
        DeprecationWarning,
        stacklevel=3,
    )
    return participant


def trend_contrast(
    ratings: pd.DataFrame,
    *,
    dv: str = "rating",
    level: str = "level",
    subject: str = "participant",
    by: Sequence[str] = (),
    ci: float = 0.95,
    participant: str | None = None,
) -> pd.DataFrame:
    """The linear trend contrast per group of ``by`` (see the module docstring).

    ``ratings``: one row per rating (or per cell mean). Participants missing a level are left
    out of that group's contrast (a contrast needs every level).
    """
    subject = _subject(subject, participant)
    require(ratings, (dv, level, subject, *by))
    rows = []
    groups = list(ratings.groupby(list(by), sort=True)) if by else [((), ratings)]
    for key, part in groups:
        key = key if isinstance(key, tuple) else (key,)
        cells = part.groupby([subject, level])[dv].mean().unstack(level).dropna()
        x = cells.columns.to_numpy(dtype=float)
        if len(x) < 2:
            raise AnalysisError(f"a trend needs two or more levels; group {key} has {len(x)}")
        c = x - x.mean()
        slopes = cells.to_numpy(dtype=float) @ c / np.sum(c**2)
        n = len(slopes)
        if n < 2:
            raise AnalysisError(f"a trend contrast needs two or more complete participants ({key})")
        mean, se = float(slopes.mean()), float(slopes.std(ddof=1) / np.sqrt(n))
        t = mean / se if se > 0 else float("inf") * np.sign(mean)
        q = sps.t.ppf(0.5 + ci / 2, n - 1)
        rows.append(
            {
                **dict(zip(by, key, strict=True)),
                "n": n,
                "levels": len(x),
                "slope": mean,
                "se": se,
                "ci_low": mean - q * se,
                "ci_high": mean + q * se,
                "t": t,
                "df": n - 1,
                "f": t**2,
                "p": float(2 * sps.t.sf(abs(t), n - 1)),
            }
        )
    return pd.DataFrame(rows, columns=[*by, *TREND_COLUMNS])


def graded_lmm(
    ratings: pd.DataFrame,
    *,
    dv: str = "rating",
    level: str = "level",
    subject: str = "participant",
    by: Sequence[str] = (),
    participant: str | None = None,
) -> pd.DataFrame:
    """``dv ~ level + (1 + level | participant)`` by REML, one row per group of ``by``.

    The slope's ``t`` is referred to Student's t with participants - 1 df (the slope varies
    between participants): the Satterthwaite df R's lmerTest gives for a balanced design
    (9.00002 for 10 participants, tests/reference/graded.R), where the normal reference
    would be anti-conservative with few participants."""
    import statsmodels.formula.api as smf  # heavy; only needed here

    subject = _subject(subject, participant)
    require(ratings, (dv, level, subject, *by))
    rows = []
    groups = list(ratings.groupby(list(by), sort=True)) if by else [((), ratings)]
    for key, part in groups:
        key = key if isinstance(key, tuple) else (key,)
        data = pd.DataFrame(
            {
                "y": part[dv].astype(float).to_numpy(),
                "x": part[level].astype(float).to_numpy(),
                "g": part[subject].astype(str).to_numpy(),
            }
        )
        if data["g"].nunique() < 3:
            raise AnalysisError(f"a random-slope model needs three or more participants ({key})")
        model = smf.mixedlm("y ~ x", data, groups=data["g"], re_formula="~x")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fit = model.fit(reml=True, method=["lbfgs", "powell"])
        cov = np.asarray(fit.cov_re, dtype=float)
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        df = data["g"].nunique() - 1  # the slope varies between participants
        rows.append(
            {
                **dict(zip(by, key, strict=True)),
                "n_participants": int(data["g"].nunique()),
                "n_obs": len(data),
                "intercept": float(fit.fe_params["Intercept"]),
                "slope": float(fit.fe_params["x"]),
                "slope_se": float(fit.bse_fe["x"]),
                "t": float(fit.tvalues["x"]),
                "df": df,
                "p": float(2 * sps.t.sf(abs(float(fit.tvalues["x"])), df)),
                "sd_intercept": float(sd[0]),
                "sd_slope": float(sd[1]),
                "corr": float(cov[0, 1] / (sd[0] * sd[1])) if sd.all() else float("nan"),
                "sd_residual": float(np.sqrt(fit.scale)),
                "converged": bool(fit.converged),
            }
        )
    return pd.DataFrame(rows, columns=[*by, *LMM_COLUMNS])
