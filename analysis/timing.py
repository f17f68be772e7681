"""Audio-visual timing: each participant's window of simultaneity (or temporal-order function)
per condition series, fitted over the conditions' ``audio_offset_ms``.

An identify task with ``timing`` (:class:`~facelab.protocol_model.TimingJudgment`) is scored as
"yes" when the answer is its ``label`` - in sync (simultaneity) or the voice first (temporal
order). The answers of one participant and one condition series (:attr:`Condition.series_id`,
e.g. one animation method at every offset) are counted per offset and fitted by maximum
likelihood with :func:`facelab.timing_function.p_timing`:

* simultaneity: ``floor + (peak - floor) * exp(-(x - pss)^2 / (2 sigma^2))``, width = the
  Gaussian's full width at half its height; the floor ("in sync" said far outside the window:
  guesses, a bias to say yes) is fitted as a share of the peak in [0, 0.6] unless the task's
  ``floor`` is ``none`` (then 0: such answers widen the window);
* temporal order: ``lapse / 2 + (1 - lapse) Phi((pss - x) / sigma)``, width = the distance
  between the 25 % and 75 % points.

Intervals are profile-likelihood intervals (the values whose likelihood ratio against the
best fit is within the chi-square(1) quantile, the other parameters re-fitted at each value).
The search is bounded - the PSS within one tested range beyond the offsets tested, sigma from
a tenth of the smallest step to four ranges, the peak in [0.02, 1], the lapse in [0, 0.2];
an interval end that would pass a bound is reported as that bound's side infinite (``-inf`` /
``inf``) and named in ``note``, as is an estimate on a bound.

:func:`window_tests` compares the series within participants: a repeated-measures ANOVA and
Holm-adjusted paired t tests of the PSS and the width, over participants whose every window
was determined.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd
from scipy import special

import facelab.analysis.stats as fstats
from facelab.analysis.profile_likelihood import (
    best_fit,
    binomial_deviance,
    binomial_loglik_and_weight,
    chi2_cutoff,
    on_bound,
    profile_interval,
)
from facelab.errors import AnalysisError
from facelab.protocol import IdentifyTask, Protocol
from facelab.timing_function import FWHM_PER_SIGMA, IQR_PER_SIGMA, p_timing

__all__ = [
    "WINDOW_COLUMNS",
    "TimingFit",
    "fit_window",
    "timing_counts",
    "window_curves",
    "window_table",
    "window_tests",
]

#: sync_window.csv (the contract of issue 52): one row per participant and condition series
WINDOW_COLUMNS = (
    "participant", "condition", "judgment", "n", "pss_ms", "pss_ci_low", "pss_ci_high",
    "width_ms", "width_ci_low", "width_ci_high", "peak", "floor", "lapse", "deviance",
    "deviance_df", "note",
)  # fmt: skip
_EPS = 1e-9


@dataclass(frozen=True)
class TimingFit:
    """One window: estimates, profile intervals at ``level`` and what the fit ran into."""

    judgment: str
    n: int
    pss_ms: float
    pss_ci_low: float
    pss_ci_high: float
    width_ms: float
    width_ci_low: float
    width_ci_high: float
    peak: float  # simultaneity: P(in sync) at the PSS (NaN for temporal order)
    floor: float  # simultaneity: P(in sync) far outside the window (NaN for temporal order)
    lapse: float  # temporal order (NaN for simultaneity)
    deviance: float  # against the saturated model (a proportion per offset)
    deviance_df: int
    note: str


def timing_counts(rows: pd.DataFrame, protocol: Protocol, task: IdentifyTask) -> pd.DataFrame:
    """``participant, condition (the series), offset_ms, n, k`` of a timing task's answer rows
    (``k``: answers naming the task's timing label)."""
    if task.timing is None:
        raise AnalysisError(f"task {task.id!r} has no 'timing'")
    conds = {c.id: c for c in protocol.conditions}
    known = rows[rows["condition"].isin(list(conds))]
    frame = pd.DataFrame({
        "participant": known["participant"].astype(str).to_numpy(),
        "condition": [conds[c].series_id for c in known["condition"]],
        "offset_ms": [conds[c].audio_offset_ms for c in known["condition"]],
        "y": (known["response"].astype(str) == task.timing.label).astype(int).to_numpy(),
    })  # fmt: skip
    out = (
        frame.groupby(["participant", "condition", "offset_ms"], sort=True)["y"]
        .agg(n="size", k="sum")
        .reset_index()
    )
    return out.astype({"n": int, "k": int})


def _per_sigma(judgment: str) -> float:
    return FWHM_PER_SIGMA if judgment == "simultaneity" else IQR_PER_SIGMA


#: the largest floor a simultaneity fit allows, as a share of its peak
FLOOR_SHARE_BOUND = 0.6


def _p(theta: np.ndarray, judgment: str, x: np.ndarray) -> np.ndarray:
    """P(the label) at ``x`` for parameters ``theta`` (pss, log sigma, peak or lapse[, floor
    as a share of the peak])."""
    floor = theta[2] * theta[3] if len(theta) > 3 else 0.0
    width = math.exp(theta[1]) * _per_sigma(judgment)
    return p_timing(judgment, x, pss=theta[0], width=width, third=theta[2], floor=floor)


def _loglik(theta: np.ndarray, judgment: str, x: np.ndarray, n: np.ndarray, k: np.ndarray) -> float:
    p = np.clip(_p(theta, judgment, x), _EPS, 1 - _EPS)
    return float(np.sum(k * np.log(p) + (n - k) * np.log1p(-p)))


def _gradient(
    theta: np.ndarray, judgment: str, x: np.ndarray, n: np.ndarray, k: np.ndarray
) -> np.ndarray:
    """d :func:`_loglik` / d theta (len(theta),): the chain rule through ``p`` (0 where
    ``p`` is clipped, as the clipped likelihood is flat there)."""
    return _loglik_and_gradient(theta, judgment, x, n, k)[1]


def _loglik_and_gradient(
    theta: np.ndarray, judgment: str, x: np.ndarray, n: np.ndarray, k: np.ndarray
) -> tuple[float, np.ndarray]:
    """:func:`_loglik` and :func:`_gradient` at once, from one evaluation of ``p``. The
    optimiser calls this hundreds of thousands of times in a study's analysis on a few
    offsets each: written for few numpy calls (a third of the time the plain form took)."""
    sigma = math.exp(theta[1])
    z = (x - theta[0]) / sigma
    if judgment == "simultaneity":
        g = np.exp(-0.5 * z * z)
        share = theta[3] if len(theta) > 3 else 0.0
        peak = theta[2]
        hg = (peak * (1.0 - share)) * g  # the peak above the floor, times the bell
        p = hg + peak * share
        hgz = hg * z
        rows = [hgz / sigma, hgz * z, (1.0 - share) * g + share]
        if len(theta) > 3:
            rows.append(peak - peak * g)
    else:
        lapse = theta[2]
        density = ((1.0 - lapse) / math.sqrt(2.0 * math.pi)) * np.exp(-0.5 * z * z)
        tail = special.ndtr(-z)
        p = (1.0 - lapse) * tail + lapse / 2
        rows = [density / sigma, density * z, 0.5 - tail]
    # the chain rule through p
    value, weight = binomial_loglik_and_weight(p, n=n, k=k, eps=_EPS)
    return value, np.array(rows) @ weight


def _bounds(judgment: str, x: np.ndarray, *, floor: bool) -> list[tuple[float, float]]:
    levels = np.unique(x)
    span = float(levels[-1] - levels[0])
    step = float(np.min(np.diff(levels)))
    third = (0.02, 1.0) if judgment == "simultaneity" else (0.0, 0.2)
    return [
        (float(levels[0]) - span, float(levels[-1]) + span),
        (math.log(step / 10.0), math.log(4.0 * span)),
        third,
        *([(0.0, FLOOR_SHARE_BOUND)] if floor else []),
    ]


def _starts(
    judgment: str, x: np.ndarray, n: np.ndarray, k: np.ndarray, *, floor: bool
) -> list[np.ndarray]:
    p = k / np.maximum(n, 1)
    base = float(np.min(p)) if floor else 0.0  # the floor's level, taken off the centre's weights
    w = np.clip(p - base, 0.0, None)
    centre = float(np.sum(x * w) / np.sum(w)) if np.sum(w) > 0 else float(np.mean(x))
    span = float(np.ptp(x)) or 1.0
    third0 = 0.9 if judgment == "simultaneity" else 0.02
    shares = (0.02, min(FLOOR_SHARE_BOUND - 0.01, base / third0 + 0.01)) if floor else (None,)
    return [
        np.array([c, math.log(s), third0, *(() if f is None else (f,))])
        for c in (centre, float(np.median(x)))
        for s in (span / 6.0, span / 2.0)
        for f in shares
    ]


def fit_window(
    counts: pd.DataFrame, *, judgment: str, level: float = 0.95, intervals: bool = True,
    floor: bool = True,
) -> TimingFit:  # fmt: skip
    """Fit one window to ``counts`` (``offset_ms, n, k``); see the module. Without
    ``intervals`` (power simulations) the interval columns are NaN; ``floor`` (simultaneity):
    fit the floor, else hold it at 0."""
    floor = floor and judgment == "simultaneity"
    counts = counts.groupby("offset_ms", sort=True)[["n", "k"]].sum().reset_index()
    x = counts["offset_ms"].to_numpy(dtype=float)
    n = counts["n"].to_numpy(dtype=float)
    k = counts["k"].to_numpy(dtype=float)
    if len(x) < 3 + floor:
        need = "four" if floor else "three"
        raise AnalysisError(f"a timing window{' with a floor' if floor else ''} needs answers "
                            f"at {need} or more offsets, got {len(x)}")  # fmt: skip
    bounds = _bounds(judgment, x, floor=floor)

    def loglik(theta: np.ndarray) -> float:
        return _loglik(theta, judgment, x, n, k)

    def gradient(theta: np.ndarray) -> np.ndarray:
        return _gradient(theta, judgment, x, n, k)

    def both(theta: np.ndarray) -> tuple[float, np.ndarray]:
        return _loglik_and_gradient(theta, judgment, x, n, k)

    theta, ll = best_fit(loglik, bounds=bounds, starts=_starts(judgment, x, n, k, floor=floor),
                         gradient=gradient, both=both)  # fmt: skip
    cutoff = chi2_cutoff(level)
    per = _per_sigma(judgment)
    pss_lo = pss_hi = ls_lo = ls_hi = math.nan
    if intervals:
        pss_lo, pss_hi = profile_interval(loglik, bounds=bounds, theta=theta, ll=ll, index=0,
                                          cutoff=cutoff, gradient=gradient,
                                          both=both)  # fmt: skip
        ls_lo, ls_hi = profile_interval(loglik, bounds=bounds, theta=theta, ll=ll, index=1,
                                        cutoff=cutoff, gradient=gradient, both=both)  # fmt: skip
    notes = []
    names = ("the PSS", "the width", "the peak" if judgment == "simultaneity" else "the lapse",
             *(("the floor",) if floor else ()))  # fmt: skip
    for i, name in enumerate(names):
        lo, hi = bounds[i]
        if i == 3 and theta[i] <= lo + 1e-6:
            continue  # no "in sync" answers far outside the window
        if i == 2 and judgment == "simultaneity" and theta[i] >= hi - 1e-6:
            continue  # a peak of 1 (never "out of sync" at the PSS) is a fine answer
        if i == 2 and judgment == "temporal_order" and theta[i] <= lo + 1e-6:
            continue  # no lapses
        if on_bound(theta[i], bounds[i]):
            notes.append(f"{name} ends on its search bound")
    if math.isinf(pss_lo) or math.isinf(pss_hi):
        notes.append("the PSS interval reaches beyond the offsets searched")
    if math.isinf(ls_lo) or math.isinf(ls_hi):
        notes.append("the width interval reaches beyond the widths searched")
    p_hat = _p(theta, judgment, x)
    width = math.exp(theta[1]) * per

    def w(v: float) -> float:
        return math.exp(v) * per if math.isfinite(v) else v

    return TimingFit(
        judgment=judgment, n=int(n.sum()), pss_ms=float(theta[0]), pss_ci_low=pss_lo,
        pss_ci_high=pss_hi, width_ms=width, width_ci_low=w(ls_lo) if ls_lo != -math.inf else 0.0,
        width_ci_high=w(ls_hi),
        peak=float(theta[2]) if judgment == "simultaneity" else math.nan,
        floor=(float(theta[2] * theta[3]) if floor
               else 0.0 if judgment == "simultaneity" else math.nan),
        lapse=float(theta[2]) if judgment == "temporal_order" else math.nan,
        deviance=binomial_deviance(k, n, p_hat), deviance_df=len(x) - len(theta),
        note="; ".join(notes),
    )  # fmt: skip


def window_table(
    rows: pd.DataFrame, protocol: Protocol, task: IdentifyTask, *, level: float = 0.95,
    intervals: bool = True,
) -> pd.DataFrame:  # fmt: skip
    """``sync_window.csv``: :data:`WINDOW_COLUMNS`, one row per participant and condition
    series, series in protocol order."""
    assert task.timing is not None
    counts = timing_counts(rows, protocol, task)
    order = list(dict.fromkeys(c.series_id for c in protocol.conditions))
    out = []
    floor = task.timing.judgment == "simultaneity" and task.timing.floor == "fit"
    for (pid, series), part in counts.groupby(["participant", "condition"], sort=True):
        if part["offset_ms"].nunique() < 3 + floor:  # too few for the window's parameters
            continue
        fit = fit_window(part, judgment=task.timing.judgment, level=level, intervals=intervals,
                         floor=floor)  # fmt: skip
        out.append({"participant": pid, "condition": series, **asdict(fit)})
    frame = pd.DataFrame(out, columns=list(WINDOW_COLUMNS))
    rank = {s: i for i, s in enumerate(order)}
    frame = frame.sort_values(["participant", "condition"], key=lambda c: c.map(rank)
                              if c.name == "condition" else c, kind="stable")  # fmt: skip
    return frame.reset_index(drop=True)


def window_curves(windows: pd.DataFrame, *, offsets: np.ndarray) -> pd.DataFrame:
    """``condition, offset_ms, p``: each series' function at the participants' median
    parameters (for figures)."""
    rows = []
    for series, part in windows.groupby("condition", sort=False):
        judgment = str(part["judgment"].iloc[0])
        third = part["peak" if judgment == "simultaneity" else "lapse"].median()
        floor = part["floor"].median() if judgment == "simultaneity" else 0.0
        p = p_timing(judgment, offsets, pss=part["pss_ms"].median(),
                     width=part["width_ms"].median(), third=third,
                     floor=0.0 if pd.isna(floor) else floor)  # fmt: skip
        rows += [{"condition": series, "offset_ms": float(o), "p": float(v)}
                 for o, v in zip(offsets, p, strict=True)]  # fmt: skip
    return pd.DataFrame(rows, columns=["condition", "offset_ms", "p"])


def window_tests(windows: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(summary, tests) of the PSS and the width between condition series
    (:func:`facelab.analysis.stats.series_comparison`; windows with a note left out - of
    the one measure it concerns, when it concerns only the PSS or only the width)."""
    return fstats.series_comparison(windows, measures=("pss_ms", "width_ms"),
                                    concerns={"pss_ms": "the PSS", "width_ms": "the width"},
                                    bounds={"width_ms": (0.0, np.inf)})  # fmt: skip
