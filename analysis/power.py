"""Power for the sound analysis (one-way repeated-measures ANOVA on participant means).

Effect size. ``f2 = sum_j (mu_j - mu)^2 / k / sigma_e^2`` where ``mu_j`` are the condition
means and ``sigma_e^2`` the residual (participant x condition) variance of the participant
means. With sphericity, the RM ANOVA's F is non-central F(k - 1, (k - 1)(n - 1), lambda)
with ``lambda = n k f2``; power is its tail beyond the critical F.

Where f2 comes from:

* **pilot data** (logs of a study): condition means and the RM error mean square per item x
  stimulus set; the spread of sample means is bias-corrected by (k - 1) sigma_e^2 / n.
* **a reported p-value of the paper's procedure** (one-way ANOVA on N pooled ratings): the
  implied F gives ``lambda_pooled = (F - 1)(k - 1)`` and ``f2_pooled = lambda_pooled / N``
  relative to the total rating variance. Converting to the RM analysis needs how that
  variance splits, which a p-value cannot tell: ``icc`` (participant share) and
  ``interaction_share`` (participant x condition share) are assumptions, stated in the
  output; the rest is rating-to-rating noise, divided by the ``reps`` ratings per cell.

:func:`simulate_power` checks the formula by Monte Carlo with the same sums of squares as
:func:`facelab.analysis.stats.rm_anova`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd
from scipy import optimize
from scipy import stats as sps

from facelab.analysis.stats import cell_means, rm_sums_of_squares
from facelab.errors import AnalysisError

__all__ = [
    "PowerResult",
    "f2_from_one",
    "f2_from_pilot",
    "f2_from_reported_p",
    "implied_effect",
    "participants_needed",
    "rm_power",
    "simulate_power",
]


def implied_effect(*, p: float, df1: int, df2: int) -> dict[str, float]:
    """F, partial eta squared and Cohen's f implied by a p-value of an F test."""
    if not 0 < p < 1:
        raise AnalysisError(f"p must be strictly between 0 and 1, got {p}")
    if df1 < 1 or df2 < 1:
        raise AnalysisError(f"degrees of freedom must be >= 1, got ({df1}, {df2})")
    f = float(sps.f.isf(p, df1, df2))
    if not np.isfinite(f) or p < 1e-12:
        # isf loses precision (and returns inf) for tiny p: solve log sf(F) = log p instead
        f = float(
            optimize.brentq(
                lambda x: sps.f.logsf(x, df1, df2) - np.log(p),
                1e-12,
                1e300,
                xtol=1e-12,
                rtol=1e-12,
                maxiter=2000,
            )
        )
    eta = f * df1 / (f * df1 + df2)
    return {"f": f, "eta_p_sq": eta, "cohens_f": float(np.sqrt(eta / (1 - eta)))}


def rm_power(*, n: int, k: int, f2: float, alpha: float = 0.05) -> float:
    """Power of the one-way RM ANOVA with ``n`` participants and ``k`` conditions."""
    if n < 2:
        return 0.0
    df1, df2 = k - 1, (k - 1) * (n - 1)
    crit = sps.f.isf(alpha, df1, df2)
    nc = n * k * f2
    if nc <= 0:  # no effect: the F test rejects at its size (scipy's ncf is wrong at nc = 0)
        return float(sps.f.sf(crit, df1, df2))
    return float(sps.ncf.sf(crit, df1, df2, nc))


def participants_needed(
    *, k: int, f2: float, power: float = 0.8, alpha: float = 0.05, n_max: int = 10_000
) -> int | None:
    """Smallest n with at least ``power``; None if even ``n_max`` is not enough."""
    if f2 <= 0:
        return None
    for n in range(2, n_max + 1):
        if rm_power(n=n, k=k, f2=f2, alpha=alpha) >= power:
            return n
    return None


def simulate_power(
    *, n: int, k: int, f2: float, alpha: float = 0.05, sims: int = 2000, rng: np.random.Generator
) -> float:
    """Monte Carlo power: participant means y = u + mu_j + e (sigma_e = 1), RM ANOVA F test.

    Participant offsets cancel in the RM analysis; they are drawn anyway (SD 1) so the
    simulation runs the same computation real data would.
    """
    mu = np.linspace(-1.0, 1.0, k)
    mu = mu / np.sqrt((mu**2).mean()) * np.sqrt(f2) if f2 > 0 else np.zeros(k)
    y = rng.normal(size=(sims, n, 1)) + mu[None, None, :] + rng.normal(size=(sims, n, k))
    ss_cond, _, ss_err = rm_sums_of_squares(y)
    df1, df2 = k - 1, (k - 1) * (n - 1)
    p = sps.f.sf((ss_cond / df1) / (ss_err / df2), df1, df2)
    return float((p < alpha).mean())


def f2_from_reported_p(
    *,
    p: float,
    participants: int,
    conditions: int,
    reps: int,
    icc: float = 0.3,
    interaction_share: float = 0.1,
) -> dict[str, float]:
    """RM effect size implied by the paper procedure's p (pooled one-way ANOVA)."""
    if not (0 <= icc < 1 and 0 <= interaction_share < 1 and icc + interaction_share < 1):
        raise AnalysisError("need 0 <= icc, interaction_share and icc + interaction_share < 1")
    n_ratings = participants * conditions * reps
    implied = implied_effect(p=p, df1=conditions - 1, df2=n_ratings - conditions)
    f2_pooled = max(0.0, (implied["f"] - 1) * (conditions - 1)) / n_ratings
    within_share = 1 - icc - interaction_share
    rm_error_share = interaction_share + within_share / reps
    return {
        **implied,
        "f2_pooled": f2_pooled,
        "rm_error_share": rm_error_share,
        "f2_rm": f2_pooled / rm_error_share,
    }


def f2_from_pilot(
    data: pd.DataFrame,
    *,
    dv: str = "rating",
    within: str = "condition",
    subject: str = "participant",
) -> dict[str, float]:
    """RM effect size from pilot ratings (bias-corrected), plus the pilot's own F."""
    y = cell_means(data, dv=dv, within=within, subject=subject).to_numpy()
    n, k = y.shape
    if k < 2:
        raise AnalysisError(f"the pilot's ratings hold {k} condition(s); an effect needs 2 or more")
    ss_cond, _, ss_err = rm_sums_of_squares(y)
    ms_err = ss_err / ((k - 1) * (n - 1))
    spread = ((y.mean(axis=0) - y.mean()) ** 2).mean()
    if not ms_err > 1e-12 * max(1.0, float(np.abs(y).max()) ** 2):
        raise AnalysisError(
            "every participant rated the conditions alike" if not spread > 0 else
            "every participant's condition means differ by exactly the same amounts (no "
            "participant x condition variation): the error is zero and the effect unbounded; "
            "such a pilot (or made-up data) cannot size a study"
        )  # fmt: skip
    raw = spread / ms_err
    return {
        "n_pilot": n,
        "k": k,
        "f_pilot": (ss_cond / (k - 1)) / ms_err,
        "f2_raw": float(raw),
        "f2_rm": float(max(0.0, raw - (k - 1) / (n * k))),
    }


def f2_from_one(
    data: pd.DataFrame,
    *,
    dv: str = "rating",
    within: str = "condition",
) -> dict[str, float]:
    """RM effect size from a pilot of **one** participant: the spread of the condition means
    over the error of a condition mean estimated from that person's repeated ratings of the
    same condition (ms_within / ratings per condition). One person cannot show the
    participant x condition interaction, which the RM error also holds, so this f² is an
    upper bound and the power and n that follow from it are optimistic."""
    groups = data.groupby(within, observed=True)[dv]
    means, counts = groups.mean(), groups.count()
    k = len(means)
    if k < 2:
        raise AnalysisError("one participant's pilot needs ratings of 2 or more conditions")
    if (counts < 2).any():
        once = ", ".join(str(c) for c in counts[counts < 2].index)
        raise AnalysisError(
            f"one participant's pilot needs 2 or more ratings of every condition (once: {once})"
        )
    ss_within = float(groups.apply(lambda v: ((v - v.mean()) ** 2).sum()).sum())
    ms_within = ss_within / float((counts - 1).sum())
    if not ms_within > 0:
        raise AnalysisError("the participant gave every condition the same rating each time")
    ms_err = ms_within / float(counts.mean())
    spread = float(((means - means.mean()) ** 2).mean())
    raw = spread / ms_err
    return {
        "n_pilot": 1,
        "k": k,
        "f_pilot": float(counts.mean()) * spread * k / (k - 1) / ms_within,
        "f2_raw": float(raw),
        "f2_rm": float(max(0.0, raw - (k - 1) / k)),
        "error_from": "one participant's repeated ratings (no interaction: optimistic)",
    }


@dataclass(frozen=True)
class PowerResult:
    label: str
    k: int
    f2_rm: float
    power_at_n: float
    n: int
    n_needed: int | None
    target_power: float
    simulated_power_at_needed: float | None

    def row(self) -> dict[str, object]:
        return asdict(self)
