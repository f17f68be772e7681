"""Statistics for rating studies: the paper's procedure and the sound within-subject one.

Every function takes a long DataFrame (one row per observation) and column names,
keyword-only, and returns a tidy DataFrame with snake_case columns. Nothing is rounded.

Level order: a ``pandas.Categorical`` column keeps its category order; any other column
uses the order of first appearance. Pairs are (level i, level j) with i < j in that order.

Procedures
----------
* ``one_way_anova`` + ``tukey_hsd``: between-subjects; on pooled individual ratings this is
  the paper's procedure (pseudo-replication: it treats repeated ratings as independent).
* ``rm_anova`` + ``pairwise_paired``: one-way repeated measures on participant means
  (ratings in a participant x condition cell are averaged first), with Mauchly's test and
  Greenhouse-Geisser / Huynh-Feldt corrections; paired t-tests with R's p.adjust methods.
* ``friedman``: the rank-based companion on participant means.
* ``lmm_anova``: a linear mixed model on all ratings with random participant and
  participant x condition intercepts; F test with the aggregated design's df.

All values were checked against R (tests/reference/stats_reference.R).
"""

from __future__ import annotations

import functools
import sys
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from typing import Any, Literal

import numpy as np
import pandas as pd
from scipy import stats

from facelab.errors import AnalysisError

__all__ = [
    "cell_means",
    "friedman",
    "levels",
    "lmm_anova",
    "mean_t_interval",
    "one_way_anova",
    "p_adjust",
    "pairwise_paired",
    "psychometric",
    "require",
    "rm_anova",
    "rm_sums_of_squares",
    "series_comparison",
    "tukey_hsd",
]


# --------------------------------------------------------------------------- helpers


def require(data: pd.DataFrame, columns: Sequence[str]) -> None:
    if not isinstance(data, pd.DataFrame):
        raise AnalysisError(f"expected a pandas DataFrame, got {type(data).__name__}")
    missing = [c for c in columns if c not in data.columns]
    if missing:
        raise AnalysisError(
            f"missing column(s) {', '.join(map(repr, missing))}; "
            f"have {', '.join(map(str, data.columns))}"
        )


def _numeric(data: pd.DataFrame, dv: str) -> pd.Series:
    values = pd.to_numeric(data[dv], errors="coerce")
    bad = values.isna() & data[dv].notna()
    if bad.any():
        raise AnalysisError(f"column {dv!r} has non-numeric values, e.g. {data[dv][bad].iloc[0]!r}")
    if values.isna().any():
        raise AnalysisError(f"column {dv!r} has {int(values.isna().sum())} missing value(s)")
    return values.astype(float)


def screen_covariates(
    data: pd.DataFrame, covariates: Sequence[str], *, condition: str
) -> tuple[list[str], list[str]]:
    """(usable, notes): a covariate is dropped when it is constant, or when it is fixed by
    the condition (no variation within any condition: collinear with the condition terms, so
    it adds nothing to a model that has them). A covariate kept that is constant within some
    conditions (e.g. no postures at all in a gesture-only condition) is named too: its slope
    comes from the other conditions, and the condition effect is read at its value there."""
    used, dropped = [], []
    for c in covariates:
        if data[c].nunique() < 2:
            dropped.append(f"{c} constant")
            continue
        within = data[c] - data.groupby(condition, observed=True)[c].transform("mean")
        if float(np.abs(within).max()) < 1e-12:
            dropped.append(f"{c} fixed by condition")
            continue
        used.append(c)
        per = data.groupby(condition, observed=True)[c]
        flat = [f"{k} ({v:g})" for k, v in per.first().items() if per.nunique()[k] == 1]
        if flat:
            dropped.append(f"{c} constant within {', '.join(flat)}")
    return used, dropped


def levels(series: pd.Series) -> list:
    """Levels of a factor column: category order if categorical, else first appearance."""
    if isinstance(series.dtype, pd.CategoricalDtype):
        present = set(series.dropna().unique())
        return [c for c in series.cat.categories if c in present]
    return list(pd.unique(series.dropna()))


def _pairs(names: Sequence) -> list[tuple[int, int]]:
    return [(i, j) for i in range(len(names)) for j in range(i + 1, len(names))]


#: p_adjust's method names (R's p.adjust) -> statsmodels' multipletests names
_ADJUST = {"bonferroni": "bonferroni", "holm": "holm"}


def p_adjust(p: Sequence[float], *, method: str = "holm") -> np.ndarray:
    """Adjusted p-values as R's ``p.adjust``: ``none``, ``bonferroni`` or ``holm``
    (statsmodels' ``multipletests``)."""
    from statsmodels.stats.multitest import multipletests

    p = np.asarray(p, dtype=float)
    if method == "none":
        return p.copy()
    if method not in _ADJUST:
        raise AnalysisError(
            f"unknown p-value adjustment {method!r}; expected none, bonferroni or holm"
        )
    if p.size == 0:
        return p.copy()
    return multipletests(p, method=_ADJUST[method])[1]


# --------------------------------------------------------------------------- between subjects


def _groups(data: pd.DataFrame, dv: str, between: str) -> tuple[list, list[np.ndarray]]:
    require(data, [dv, between])
    values = _numeric(data, dv)
    names = levels(data[between])
    if len(names) < 2:
        raise AnalysisError(f"column {between!r} needs at least 2 levels, has {len(names)}")
    groups = [values[data[between] == name].to_numpy() for name in names]
    small = [str(n) for n, g in zip(names, groups, strict=True) if len(g) < 2]
    if small:
        raise AnalysisError(f"level(s) {', '.join(small)} of {between!r} have fewer than 2 values")
    return names, groups


def one_way_anova(data: pd.DataFrame, *, dv: str, between: str) -> pd.DataFrame:
    """One-way between-subjects ANOVA.

    Returns one row: ``df1, df2, f, p, eta_sq`` (eta squared = SS_between / SS_total).
    """
    _, groups = _groups(data, dv, between)
    all_values = np.concatenate(groups)
    grand = all_values.mean()
    ss_between = sum(len(g) * (g.mean() - grand) ** 2 for g in groups)
    ss_within = sum(((g - g.mean()) ** 2).sum() for g in groups)
    df1, df2 = len(groups) - 1, len(all_values) - len(groups)
    if ss_within <= 0:
        raise AnalysisError(f"column {dv!r} has no variance within levels of {between!r}")
    f = (ss_between / df1) / (ss_within / df2)
    return pd.DataFrame(
        [
            {
                "df1": df1,
                "df2": df2,
                "f": f,
                "p": stats.f.sf(f, df1, df2),
                "eta_sq": ss_between / (ss_between + ss_within),
            }
        ]
    )


def tukey_hsd(data: pd.DataFrame, *, dv: str, between: str, alpha: float = 0.05) -> pd.DataFrame:
    """Tukey HSD (Tukey-Kramer for unequal group sizes), as R's ``TukeyHSD``.

    Returns one row per pair: ``a, b, diff, ci_low, ci_high, p_adj`` with
    ``diff = mean(b) - mean(a)`` and a ``1 - alpha`` simultaneous confidence interval.

    The numbers are scipy's ``tukey_hsd`` (the same operations), with the studentized range
    evaluated once per reported pair rather than on the whole k x k table, and its critical
    value kept per (level, k, df) - scipy integrates both numerically, about 20 ms a p-value
    and 0.25 s a critical value; a study's paper layout asks for the same one several times.
    """
    names, groups = _groups(data, dv, between)
    k = len(groups)
    means = np.asarray([np.mean(g) for g in groups])
    sizes = np.asarray([g.size for g in groups])
    df = np.sum(sizes) - k
    mse = np.sum(np.asarray([np.var(g, ddof=1) for g in groups]) * (sizes - 1)) / df
    if np.unique(sizes).size == 1:
        stand_err = np.full((k, k), np.sqrt(2 / sizes[0] * mse / 2))
    else:
        stand_err = np.sqrt((1 / sizes + 1 / sizes[None].T) * mse / 2)
    radius = _studentized_range_quantile(1 - alpha, k, int(df)) * stand_err
    rows = []
    for i, j in _pairs(names):
        diff = means[j] - means[i]  # R reports level j - level i
        rows.append(
            {
                "a": names[i],
                "b": names[j],
                "diff": diff,
                "ci_low": diff - radius[i, j],
                "ci_high": diff + radius[i, j],
                "p_adj": float(stats.studentized_range.sf(abs(diff) / stand_err[i, j], k, df)),
            }
        )
    return pd.DataFrame(rows)


@functools.lru_cache(maxsize=256)
def _studentized_range_quantile(level: float, k: int, df: int) -> float:
    return float(stats.studentized_range.ppf(level, k, df))


# --------------------------------------------------------------------------- within subjects


def cell_means(data: pd.DataFrame, *, dv: str, within: str, subject: str) -> pd.DataFrame:
    """Participant x level means as a wide table (rows: subjects, columns: levels).

    Raises if any participant lacks a level: a missing cell is an error, never dropped.
    """
    require(data, [dv, within, subject])
    values = _numeric(data, dv)
    names = levels(data[within])
    if len(names) < 2:
        raise AnalysisError(f"column {within!r} needs at least 2 levels, has {len(names)}")
    frame = pd.DataFrame(
        {"s": data[subject].to_numpy(), "w": data[within].to_numpy(), "y": values.to_numpy()}
    )
    wide = frame.groupby(["s", "w"], sort=False, observed=True)["y"].mean().unstack("w")
    wide = wide.reindex(columns=names)
    missing = wide.isna()
    if missing.any().any():
        cells = [
            f"{wide.index[int(s)]} x {wide.columns[int(w)]}"
            for s, w in zip(*np.nonzero(missing.to_numpy()), strict=True)
        ]
        raise AnalysisError(
            f"missing cell(s) ({subject} x {within}): {', '.join(cells[:5])}"
            f"{' …' if len(cells) > 5 else ''}; a repeated-measures analysis needs every "
            "participant in every condition (use lmm_anova for incomplete data)"
        )
    if len(wide) < 2:
        raise AnalysisError(f"need at least 2 participants in {subject!r}, have {len(wide)}")
    return wide


def _sphericity(y: np.ndarray) -> tuple[float, float, float, float]:
    """Mauchly's W and its p, Greenhouse-Geisser and Huynh-Feldt epsilons for (n, k) data."""
    n, k = y.shape
    p = k - 1
    # orthonormal contrasts (Helmert-like) spanning the space orthogonal to the mean
    q, _ = np.linalg.qr(np.column_stack([np.ones(k), np.eye(k)[:, : k - 1]]))
    contrasts = q[:, 1:]
    cov = np.cov(y @ contrasts, rowvar=False).reshape(p, p)
    trace = np.trace(cov)
    eps_gg = trace**2 / (p * np.trace(cov @ cov))
    # Huynh-Feldt with Lecoutre's correction, as R's car/afex (one group)
    if p == 1:
        return 1.0, 1.0, 1.0, 1.0
    den = p * (n - 1 - p * eps_gg)
    # at n - 1 = p eps_gg (two participants: eps_gg = 1/p exactly) the estimate is 0/0; the
    # rounding of eps_gg must not turn it into a number (-1 was reported)
    eps_hf = min(1.0, (n * p * eps_gg - 2) / den) if den > 1e-9 * p * n else float("nan")
    if n - 1 <= p:  # the covariance is singular: Mauchly's test is undefined (as in R)
        return float("nan"), float("nan"), float(eps_gg), eps_hf
    w = np.linalg.det(cov) / (trace / p) ** p
    # chi-square approximation with the second-order term, exactly as R's mauchly.test and
    # car (whose w2 uses the number of levels k, not p = k - 1, in its "3 * p" term)
    dfe = n - 1
    rho = 1 - (2 * p**2 + p + 2) / (6 * p * dfe)
    w2 = (
        (p + 2)
        * (p - 1)
        * (p - 2)
        * (2 * p**3 + 6 * p**2 + 3 * k + 2)
        / (288 * (dfe * p * rho) ** 2)
    )
    z = -dfe * rho * np.log(w)
    dof = p * (p + 1) / 2 - 1
    pr1, pr2 = stats.chi2.sf(z, dof), stats.chi2.sf(z, dof + 4)
    return float(w), float(pr1 + w2 * (pr2 - pr1)), float(eps_gg), float(eps_hf)


def rm_sums_of_squares(y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SS of conditions, subjects and error for cell means ``y`` of shape (..., n, k).

    Works on a stack of data sets at once (leading axes), as the power simulation needs.
    """
    n, k = y.shape[-2:]
    grand = y.mean(axis=(-2, -1), keepdims=True)
    ss_cond = n * ((y.mean(axis=-2, keepdims=True) - grand) ** 2).sum(axis=(-2, -1))
    ss_subj = k * ((y.mean(axis=-1, keepdims=True) - grand) ** 2).sum(axis=(-2, -1))
    ss_err = ((y - grand) ** 2).sum(axis=(-2, -1)) - ss_cond - ss_subj
    return ss_cond, ss_subj, ss_err


def rm_anova(data: pd.DataFrame, *, dv: str, within: str, subject: str) -> pd.DataFrame:
    """One-way repeated-measures ANOVA on participant means.

    Returns one row: ``df1, df2, f, p, w_mauchly, p_mauchly, eps_gg, p_gg, eps_hf, p_hf,
    eta_g_sq, eta_p_sq``. Repeated ratings in a cell are averaged first; a missing cell
    raises :class:`AnalysisError`. With two levels sphericity holds trivially (W = 1, eps = 1).
    """
    y = cell_means(data, dv=dv, within=within, subject=subject).to_numpy()
    n, k = y.shape
    ss_cond, ss_subj, ss_err = rm_sums_of_squares(y)
    df1, df2 = k - 1, (k - 1) * (n - 1)
    if ss_err <= 0:
        raise AnalysisError("no residual variance (participant x condition); F is undefined")
    f = (ss_cond / df1) / (ss_err / df2)
    w, p_w, eps_gg, eps_hf = _sphericity(y)
    return pd.DataFrame(
        [
            {
                "df1": df1,
                "df2": df2,
                "f": f,
                "p": stats.f.sf(f, df1, df2),
                "w_mauchly": w,
                "p_mauchly": p_w,
                "eps_gg": eps_gg,
                "p_gg": stats.f.sf(f, df1 * eps_gg, df2 * eps_gg),
                "eps_hf": eps_hf,
                "p_hf": stats.f.sf(f, df1 * eps_hf, df2 * eps_hf),
                "eta_g_sq": ss_cond / (ss_cond + ss_subj + ss_err),
                "eta_p_sq": ss_cond / (ss_cond + ss_err),
            }
        ]
    )


def pairwise_paired(
    data: pd.DataFrame, *, dv: str, within: str, subject: str, padjust: str = "holm"
) -> pd.DataFrame:
    """Paired t-tests between all levels on participant means (R ``pairwise.t.test(paired=TRUE)``).

    Returns one row per pair: ``a, b, t, df, p_unc, p_adj, d_z``; ``t`` and ``d_z`` are for
    the differences ``a - b`` (as R's ``t.test(a, b, paired=TRUE)``), ``d_z = mean/sd`` of the
    differences; ``padjust`` is none, bonferroni or holm.
    """
    wide = cell_means(data, dv=dv, within=within, subject=subject)
    names = list(wide.columns)
    rows = []
    for i, j in _pairs(names):
        diff = wide.iloc[:, i].to_numpy() - wide.iloc[:, j].to_numpy()
        sd = diff.std(ddof=1)
        if sd == 0:
            raise AnalysisError(f"the differences {names[i]} - {names[j]} have no variance")
        t = diff.mean() / (sd / np.sqrt(len(diff)))
        rows.append(
            {
                "a": names[i],
                "b": names[j],
                "t": t,
                "df": len(diff) - 1,
                "p_unc": 2 * stats.t.sf(abs(t), len(diff) - 1),
                "d_z": diff.mean() / sd,
            }
        )
    out = pd.DataFrame(rows)
    out.insert(5, "p_adj", p_adjust(out["p_unc"], method=padjust))
    return out


def friedman(data: pd.DataFrame, *, dv: str, within: str, subject: str) -> pd.DataFrame:
    """Friedman test on participant means (tie-corrected, as R ``friedman.test``).

    Returns one row: ``chi2, df, p, kendall_w`` with Kendall's W = chi2 / (n (k - 1)).
    """
    y = cell_means(data, dv=dv, within=within, subject=subject).to_numpy()
    n, k = y.shape
    if k < 3:
        raise AnalysisError("the Friedman test needs at least 3 levels (use a Wilcoxon test for 2)")
    if n < 2 or bool(np.all(y == y[:, :1])):
        raise AnalysisError("every participant's means are tied across the conditions: no "
                            "ranks differ" if n >= 2 else "it needs two or more participants")
    chi2, p = stats.friedmanchisquare(*y.T)
    return pd.DataFrame([{"chi2": chi2, "df": k - 1, "p": p, "kendall_w": chi2 / (n * (k - 1))}])


def _balanced_lmm_f(frame: pd.DataFrame, n: int, k: int) -> float | None:
    """The REML Wald F of the balanced model in closed form, or None if not balanced.

    With every subject x condition cell holding the same number r of ratings, the REML
    estimates are the ANOVA (expected-mean-square) estimates truncated at 0, and the Wald F
    of the condition effect is ``MS_cond / MS_error`` on cell means when the subject x
    condition variance is positive (the RM ANOVA F); at its boundary (estimate 0) the error
    pools the interaction and the within-cell sums of squares.
    """
    counts = frame.groupby(["s", "w"], observed=False)["y"].size()
    if len(counts) != n * k or counts.nunique() != 1:
        return None
    r = int(counts.iloc[0])
    means = frame.groupby(["s", "w"], observed=False)["y"].mean().unstack("w").to_numpy()
    grand = means.mean()
    ss_cond = n * np.sum((means.mean(axis=0) - grand) ** 2)
    resid = means - means.mean(axis=1, keepdims=True) - means.mean(axis=0) + grand
    ss_int = np.sum(resid**2)
    df_cond, df_int = k - 1, (k - 1) * (n - 1)
    ms_int = ss_int / df_int
    if r == 1:
        return float((ss_cond / df_cond) / ms_int)
    cell_mean = frame.groupby(["s", "w"], observed=False)["y"].transform("mean")
    ss_within = float(np.sum((frame["y"] - cell_mean) ** 2))
    df_within = n * k * (r - 1)
    if r * ms_int >= ss_within / df_within:  # sigma_v^2 >= 0: the RM ANOVA F
        return float((ss_cond / df_cond) / ms_int)
    pooled = (r * ss_int + ss_within) / (df_int + df_within)  # sigma_v^2 at 0
    return float((r * ss_cond / df_cond) / pooled)


def lmm_anova(
    data: pd.DataFrame, *, dv: str, within: str, subject: str, closed_form: bool = True
) -> pd.DataFrame:
    """Linear mixed model F test for ``within`` on all ratings.

    Model: ``dv ~ within + (1 | subject) + (1 | subject:within)`` fitted by REML. The Wald
    chi-square of the ``within`` effects is divided by its df to give F, tested on
    ``df1 = k - 1`` and ``df2 = (k - 1)(n - 1)``, the df of the aggregated design
    (statsmodels has no Satterthwaite df). Balanced data (every cell the same number of
    ratings) use the closed form of the REML fit (:func:`_balanced_lmm_f`, milliseconds for
    1,000 participants); otherwise - or with ``closed_form=False`` - statsmodels MixedLM is
    fitted. Returns ``df1, df2, f, p``.
    """
    require(data, [dv, within, subject])
    names = levels(data[within])
    frame = pd.DataFrame(
        {
            "y": _numeric(data, dv).to_numpy(),
            "w": pd.Categorical(data[within].to_numpy(), categories=names),
            "s": data[subject].astype(str).to_numpy(),
        }
    )
    n, k = frame["s"].nunique(), len(names)
    if k < 2 or n < 2:
        raise AnalysisError(f"need at least 2 levels of {within!r} and 2 subjects")
    df1, df2 = k - 1, (k - 1) * (n - 1)
    f_closed = _balanced_lmm_f(frame, n, k) if closed_form else None
    if f_closed is not None:
        return pd.DataFrame(
            [{"df1": df1, "df2": df2, "f": f_closed, "p": stats.f.sf(f_closed, df1, df2)}]
        )
    import statsmodels.formula.api as smf
    from statsmodels.tools.sm_exceptions import ConvergenceWarning, SingularMatrixWarning

    model = smf.mixedlm(
        "y ~ C(w)", frame, groups="s", re_formula="1", vc_formula={"sw": "0 + C(w)"}
    )
    fit = None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        # a participant x condition variance at its boundary (0) is a valid REML fit
        warnings.simplefilter("ignore", SingularMatrixWarning)
        # BFGS with a tight gradient tolerance reaches the REML optimum to ~1e-12; the others
        # are fallbacks for awkward data
        for options in (
            {"method": "bfgs", "gtol": 1e-12},
            {"method": "lbfgs"},
            {"method": "powell"},
        ):
            try:
                candidate = model.fit(reml=True, maxiter=5000, **options)
            except (np.linalg.LinAlgError, ValueError):
                continue
            if candidate.converged:
                fit = candidate
                break
    if fit is None:
        raise AnalysisError(
            "the mixed model did not converge; check the data (rm_anova on means "
            "is the alternative)"
        )
    effects = [name for name in fit.fe_params.index if name.startswith("C(w)")]
    beta = fit.fe_params[effects].to_numpy()
    cov = fit.cov_params().loc[effects, effects].to_numpy()
    chi2 = float(beta @ np.linalg.solve(cov, beta))
    f = chi2 / df1
    return pd.DataFrame([{"df1": df1, "df2": df2, "f": f, "p": stats.f.sf(f, df1, df2)}])


# --------------------------------------------------------------------------- psychometric


#: the columns of :func:`psychometric`: DESIGN.md's contract first, then the fuller fit
PSYCHOMETRIC_COLUMNS: tuple[str, ...] = (
    "subject",
    "n",
    "midpoint",
    "slope",
    "lapse",
    "deviance",
    "midpoint_ci_low",
    "midpoint_ci_high",
    "slope_ci_low",
    "slope_ci_high",
    "lapse_ci_low",
    "lapse_ci_high",
    "sigmoid",
    "gamma",
    "alpha",
    "slope_at_midpoint",
    "deviance_df",
    "log_likelihood",
    "n_levels",
    "converged",
    "n_boot",
    "estimate",
    "note",
)
_FIT_RENAMES = {"beta": "slope", "beta_ci_low": "slope_ci_low", "beta_ci_high": "slope_ci_high",
                "n_trials": "n"}  # fmt: skip


def psychometric(
    data: pd.DataFrame,
    *,
    level: str,
    correct: str,
    subject: str | None = None,
    pooled: bool = False,
    gamma: float = 0.5,
    sigmoid: str = "logistic",
    lapse_bounds: tuple[float, float] = (0.0, 0.1),
    n_boot: int = 200,
    rng: np.random.Generator | None = None,
    per_subject: Literal["ml", "posterior"] = "ml",
    drops: tuple[float, float] | None = None,
) -> pd.DataFrame:
    """Psychometric fits, P = gamma + (1 - gamma - lambda) * F(x): the one psychometric API
    of facelab (its engines: :mod:`facelab.analysis.psychometric`, maximum likelihood, and
    :mod:`facelab.analysis.bayes_psychometric`, the posterior).

    Parameters
    ----------
    data : one row per trial (``correct`` 0/1), or one row per level with ``correct`` the
        proportion correct and an ``n`` column (trials at that level).
    level, correct : column names.
    subject : a column to fit each subject separately; None fits all rows pooled.
    pooled : with ``subject``, also the fit of all rows pooled (subject ``"pooled"``).
    gamma : the guess rate (0.5 for 2AFC, 0 for a preference).
    sigmoid : ``logistic`` (F = 1 / (1 + exp(-slope * (x - midpoint)))) or ``weibull``.
    lapse_bounds : bounds of the free lapse rate; ``(0, 0)`` fixes it at 0.
    n_boot, rng : parametric-bootstrap resamples for the CIs and their generator (default
        ``numpy.random.default_rng(0)``, so repeated calls agree).
    per_subject : how each subject's row is estimated: ``ml`` (maximum likelihood with the
        bootstrap intervals, as the pooled row always is) or ``posterior`` (logistic only:
        psignifit's default priors as a penalty - the posterior mode and 95 % profile
        intervals - for one person's few trials, where the ML slope runs away; see
        :mod:`facelab.analysis.bayes_psychometric`). ``estimate`` says which a row is.
    drops : with ``per_subject="posterior"``, the log-posterior drops (midpoint, width) that
        end the profile intervals, calibrated for the design
        (:func:`facelab.analysis.bayes_psychometric.calibrated_drops`); default chi2_1(.95)/2.

    Returns one row per subject (then the pooled row, subject ``"pooled"``), columns
    :data:`PSYCHOMETRIC_COLUMNS`: ``subject, n, midpoint, slope, lapse, deviance,
    midpoint_ci_low, midpoint_ci_high`` (DESIGN.md), then the slope and lapse intervals and
    the fit's details. A subject whose fit is impossible (answers at one level only) gets NaN
    estimates, ``converged`` False and the reason in ``note``.
    """
    from facelab.analysis.psychometric import FIT_COLUMNS, fit_psychometric

    require(data, [level, correct, *([subject] if subject else [])])
    rng = np.random.default_rng(0) if rng is None else rng
    frame = data.copy()
    if "n" in frame.columns:  # per level: proportion and count
        frame["_n"] = frame["n"].astype(float)
        frame["_k"] = np.round(frame[correct].astype(float) * frame["_n"])
    else:
        values = frame[correct].astype(float)
        if not values.isin([0.0, 1.0]).all():
            raise AnalysisError(
                f"column {correct!r} must be 0/1 per trial (or proportions with an 'n' column)"
            )
        frame["_n"], frame["_k"] = 1.0, values
    groups = list(frame.groupby(subject, sort=True)) if subject else []
    if not subject or pooled:
        groups.append(("pooled", frame))
    rows = []
    from tqdm import tqdm  # a bar on a terminal only: the bootstrap is the slow step

    quiet = n_boot == 0 or len(groups) < 2 or not sys.stderr.isatty()
    for key, part in tqdm(groups, desc="psychometric fits", leave=False, disable=quiet):
        counts = (
            part.groupby(level, sort=True)[["_n", "_k"]]
            .sum()
            .rename(columns={"_n": "n", "_k": "k"})
            .reset_index()
            .rename(columns={level: "level"})
        )
        posterior = per_subject == "posterior" and key != "pooled" and sigmoid == "logistic"
        try:
            if posterior:
                fit = _posterior_row(counts, gamma=gamma, drops=drops)
            else:
                fit = asdict(
                    fit_psychometric(
                        counts, sigmoid=sigmoid, gamma=gamma, lapse_bounds=lapse_bounds,
                        n_boot=n_boot, rng=rng,
                    )
                )  # fmt: skip
                fit["estimate"] = "ml"
        except AnalysisError as exc:
            fit = dict.fromkeys(FIT_COLUMNS, float("nan"))
            fit.update(sigmoid=sigmoid, gamma=gamma, converged=False, n_boot=0, note=str(exc))
            fit.update(n_trials=int(counts["n"].sum()), n_levels=len(counts))
            fit.update(estimate="posterior" if posterior else "ml")
        fit = {_FIT_RENAMES.get(k, k): v for k, v in fit.items()}
        rows.append({"subject": key, **fit})
    return pd.DataFrame(rows, columns=list(PSYCHOMETRIC_COLUMNS))


def _calibration_note(drops: tuple[float, float]) -> str:
    """How the calibrated intervals end, in words (an infinite drop: the whole grid)."""
    if all(np.isfinite(drops)):
        return (
            "intervals calibrated on the design simulated at the pooled estimate (they end "
            f"{drops[0]:.2f} / {drops[1]:.2f} below the mode for midpoint / slope; "
            "uncalibrated 1.92)"
        )
    ends = [
        f"the {name}'s interval ends {drop:.2f} below the mode"
        if np.isfinite(drop)
        else f"the {name}'s interval is the prior's whole range: too many simulated "
        "participants' priors excluded the pooled estimate for a finite drop"
        for name, drop in zip(("midpoint", "slope"), drops, strict=True)
    ]
    return (
        "intervals calibrated on the design simulated at the pooled estimate ("
        + "; ".join(ends)
        + "; uncalibrated 1.92)"
    )


def _posterior_row(
    counts: pd.DataFrame, *, gamma: float, drops: tuple[float, float] | None
) -> dict[str, Any]:
    """One subject's posterior fit in the engine's column names (no deviance: no ML fit)."""
    from facelab.analysis.bayes_psychometric import posterior_fit
    from facelab.psychometric_function import slope_at_midpoint

    post = posterior_fit(counts, gamma=gamma, drops=drops)
    notes = ["posterior mode, 95 % profile intervals (psignifit's default priors)"]
    if drops is not None:
        notes.append(_calibration_note(drops))
    notes += [f"the data alone do not bound the {name} (its interval's ends are the prior's)"
              for name, at_limit in (("midpoint", post.midpoint_at_limit),
                                     ("slope", post.slope_at_limit)) if at_limit]  # fmt: skip
    return {
        "sigmoid": "logistic",
        "gamma": gamma,
        "alpha": post.midpoint,
        "beta": post.slope,
        "lapse": post.lapse,
        "midpoint": post.midpoint,
        "slope_at_midpoint": float(slope_at_midpoint("logistic", post.midpoint, post.slope)),
        "deviance": float("nan"),
        "deviance_df": len(counts) - 3,
        "log_likelihood": float("nan"),
        "n_trials": post.n_trials,
        "n_levels": post.n_levels,
        "converged": True,
        "midpoint_ci_low": post.midpoint_ci_low,
        "midpoint_ci_high": post.midpoint_ci_high,
        "beta_ci_low": post.slope_ci_low,
        "beta_ci_high": post.slope_ci_high,
        "lapse_ci_low": post.lapse_ci_low,
        "lapse_ci_high": post.lapse_ci_high,
        "n_boot": 0,
        "estimate": "posterior",
        "note": "; ".join(notes),
    }


def mean_t_interval(
    values: np.ndarray, *, level: float = 0.95, bounds: tuple[float, float] | None = None
) -> tuple[float, float, float]:
    """(mean, low, high): the mean of ``values`` (shape (n,)) with its t interval; the
    interval is NaN for fewer than two values, everything NaN for none. ``bounds``: the
    range the measure cannot leave (a share right: (0, 1)); the interval is cut there (a t
    interval of shares near 1 reaches past 1)."""
    n = len(values)
    mean = float(values.mean()) if n else np.nan
    half = (float(stats.t.ppf(0.5 + level / 2, n - 1) * values.std(ddof=1) / np.sqrt(n))
            if n > 1 else np.nan)  # fmt: skip
    low, high = mean - half, mean + half
    if bounds is not None and n > 1:
        low, high = max(low, bounds[0]), min(high, bounds[1])
    return mean, low, high


def series_comparison(
    table: pd.DataFrame,
    *,
    measures: Sequence[str],
    series: str = "condition",
    subject: str = "participant",
    note: str = "note",
    concerns: Mapping[str, str] | None = None,
    bounds: Mapping[str, tuple[float, float]] | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Per-participant estimates (one row per participant and series, e.g. each one's
    window or threshold per animation method) summarised and compared within participants.

    Returns ``(summary, tests)``: per series the participants' mean of each measure with a
    95 % t interval (``<measure>_mean``, ``_ci_low``, ``_ci_high``, and ``_n`` the
    participants it is over; ``participants``, and ``determined`` - rows without a
    ``note``); per measure a repeated-measures ANOVA over the
    series (Greenhouse-Geisser p, as ``a = b = "all"``) and Holm-adjusted paired t tests
    (``measure, a, b, f, t, df, df2, p_unc, p_adj, d_z, participants``), over participants
    with every series determined (three or more needed; a series fewer than three participants
    determined is left out of the tests, the others compared). Rows with a ``note`` (an
    estimate the data do not determine) are left out of both - of one measure's only, when
    ``concerns`` maps each measure to how its notes begin (``{"pss_ms": "the PSS"}``: a
    note of ``"; "``-joined parts that all begin with another measure's phrase leaves the
    row in for this one). ``bounds``: per measure the range it cannot leave, where its
    interval is cut (:func:`mean_t_interval`)."""
    notes = (table[note].fillna("").astype(str) if note in table
             else pd.Series("", index=table.index))  # fmt: skip
    clean = table[notes.eq("")]

    def determined(measure: str) -> pd.DataFrame:
        if not concerns or measure not in concerns:
            return clean
        others = tuple(v for k, v in concerns.items() if k != measure)
        ok = notes.map(lambda text: all(part.startswith(others)
                                        for part in text.split("; ") if part))  # fmt: skip
        return table[ok]

    usable = {measure: determined(measure) for measure in measures}
    summary = []
    for name, part in table.groupby(series, sort=False):
        row: dict = {series: name, "participants": len(part),
                     "determined": int((clean[series] == name).sum())}  # fmt: skip
        for measure in measures:
            kept = usable[measure]
            kept = kept[kept[series] == name]
            v = kept[measure].to_numpy(dtype=float)
            mean, low, high = mean_t_interval(v[np.isfinite(v)],
                                              bounds=(bounds or {}).get(measure))  # fmt: skip
            row |= {f"{measure}_mean": mean, f"{measure}_ci_low": low,
                    f"{measure}_ci_high": high,
                    f"{measure}_n": int(np.isfinite(v).sum())}  # fmt: skip
        summary.append(row)
    tests = []
    for measure in measures:
        known = usable[measure]
        known = known[np.isfinite(known[measure].to_numpy(dtype=float))]
        # a series nobody (or too few) determined is left out, not every comparison with it
        counts = known.groupby(series, sort=False)[subject].nunique()
        names = [s for s in dict.fromkeys(table[series]) if counts.get(s, 0) >= 3]
        known = known[known[series].isin(names)]
        complete = known.groupby(subject)[series].nunique()
        kept = known[known[subject].isin(complete[complete == len(names)].index)]
        people = kept[subject].nunique()
        if people >= 3 and len(names) >= 2:
            try:
                anova = rm_anova(kept, dv=measure, within=series, subject=subject)
                pairs = pairwise_paired(kept, dv=measure, within=series, subject=subject)
            except AnalysisError:
                continue
            a = anova.iloc[0]
            tests.append({"measure": measure, "a": "all", "b": "all", "f": a["f"], "t": np.nan,
                          "df": a["df1"], "df2": a["df2"], "p_unc": a["p_gg"],
                          "p_adj": a["p_gg"], "d_z": np.nan, "participants": people})  # fmt: skip
            tests += [{"measure": measure, **r, "f": np.nan, "df2": np.nan,
                       "participants": people} for r in pairs.to_dict("records")]  # fmt: skip
    columns = ["measure", "a", "b", "f", "t", "df", "df2", "p_unc", "p_adj", "d_z", "participants"]
    return pd.DataFrame(summary), pd.DataFrame(tests, columns=columns)
