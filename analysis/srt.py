"""Speech in noise: each participant's speech reception threshold (SRT) per condition series,
the audio-visual benefit against audio alone, and the comparison of the methods.

The answers of an identify task with answers (the word said) on conditions with ``noise``
are scored right or wrong; a typed task's answers count each scoring unit (keyword or mora of
what was said, :attr:`TypedTask.scoring`) right or wrong - a sentence of four keywords with
three understood is 3 of 4 (the units of one sentence are taken as independent, as matrix
tests' word scoring does; they are not quite, so intervals from sentences are somewhat
narrow). They are fitted per participant and series (:attr:`Condition.series_id`,
e.g. one animation method at every SNR) by maximum likelihood with
:func:`facelab.intelligibility_function.p_correct`: the guess rate 1/k of the task's k labels
(0 for typed answers: an open set; a word matrix's mean 1/column length, its words
scored one by one),
the SRT (50 % right), the slope at the SRT (per dB, in [0.005, 1]) and a lapse rate in
[0, 0.1]. The SRT's interval is a profile-likelihood interval
(:mod:`facelab.analysis.profile_likelihood`; the slope and lapse re-fitted along it); ``note``
names an SRT the answers do not determine (on its bound, its interval open, the answers
never crossing 50 % within the SNRs tested, or every answer at one SNR - a track stuck at
the procedure's easy or hard end: such a series keeps its row, without an SRT), and such
rows are left out of the comparisons. The
SNRs may come from a staircase (one per block) or from constant stimuli.

Against the series whose conditions are ``audio_only`` (the voice with a still face or none):

* ``benefit_db`` - the audio-only SRT minus the series' SRT (positive: the face lowers the
  threshold), with a Wald interval from the two profile intervals' half-widths;
* ``visual_enhancement`` - Sumby & Pollack's (1954) ``(P_AV - P_A) / (1 - P_A)`` at the
  participant's audio-only SRT, where ``P_A`` is 1/2 by definition and ``P_AV`` the series'
  fitted P there (not estimated, NaN, when the series' slope sits on its bound: P away from
  the SRT is then not known).

:func:`srt_tests` summarises the series and compares them within participants
(:func:`facelab.analysis.stats.series_comparison`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd
from scipy import special, stats

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
from facelab.intelligibility_function import p_correct
from facelab.protocol import IdentifyTask, MatrixTask, Protocol, TypedTask

__all__ = [
    "SRT_COLUMNS",
    "SrtFit",
    "audio_only_series",
    "fit_srt",
    "guess_rate",
    "is_noise_task",
    "noise_trials",
    "scoring_units",
    "srt_curves",
    "srt_table",
    "srt_tests",
]

#: srt.csv (the contract of issue 52): one row per participant and condition series
SRT_COLUMNS = (
    "participant", "condition", "n", "srt_db", "srt_ci_low", "srt_ci_high", "slope_per_db",
    "lapse", "benefit_db", "benefit_ci_low", "benefit_ci_high", "visual_enhancement",
    "deviance", "deviance_df", "note",
)  # fmt: skip
_EPS = 1e-9
LAPSE_BOUND = (0.0, 0.1)
#: proportion correct per dB at the SRT; an estimate on a bound says only that the function is
#: steeper (or shallower) than the SNRs tested can show - the SRT's interval still holds
SLOPE_BOUND = (0.005, 1.0)


@dataclass(frozen=True)
class SrtFit:
    """One participant's threshold in one series."""

    n: int
    srt_db: float
    srt_ci_low: float
    srt_ci_high: float
    slope_per_db: float
    lapse: float
    deviance: float
    deviance_df: int
    note: str


NoiseTask = IdentifyTask | TypedTask


def guess_rate(task: NoiseTask) -> float:
    """P(right) by guessing: 1/k for k labels, 0 for typed answers (an open set), a word
    matrix's mean 1/column length."""
    if isinstance(task, MatrixTask):
        return task.guess_rate()
    return 0.0 if isinstance(task, TypedTask) else 1.0 / len(task.labels)


def scoring_units(protocol: Protocol, task: TypedTask) -> dict[tuple[str, str], int]:
    """(stimulus set, stimulus) -> how many units a typed answer to it is scored on: its
    keywords that have a reading, or the morae of what was said (as
    :func:`facelab.analysis.typed_scoring.score_typed` counts them)."""
    from facelab.japanese_reading import morae, pronunciation

    out = {}
    for stimulus_set in protocol.stimulus_sets:
        for st in stimulus_set.stimuli:
            if isinstance(task, MatrixTask):  # a word from each column
                if task.words_said(st) is not None:
                    out[(stimulus_set.id, st.id)] = len(task.columns)
                continue
            said = task.said(st)
            if said is None:
                continue
            if task.scoring == "morae":
                out[(stimulus_set.id, st.id)] = len(morae(pronunciation(said)))
            else:
                words = task.keywords_of(st) or said.split() or [said]
                out[(stimulus_set.id, st.id)] = sum(1 for w in words if pronunciation(w))
    return out


def noise_trials(rows: pd.DataFrame, protocol: Protocol, task: NoiseTask) -> pd.DataFrame:
    """``participant, condition (the series), snr_db, correct, units, hits`` of a task's
    answer rows on conditions with noise: an identify task's rows with a portrayed label
    (``units`` 1, ``hits`` = ``correct``), a typed task's rows with ``units`` the stimulus'
    scoring units and ``hits`` those the answer reproduced (``score`` x ``units``)."""
    conds = {c.id: c for c in protocol.conditions if c.noise is not None}
    known = rows[rows["condition"].isin(list(conds))]
    frame = pd.DataFrame({
        "participant": known["participant"].astype(str).to_numpy(),
        "condition": [conds[c].series_id for c in known["condition"]],
        "snr_db": [conds[c].noise.snr_db for c in known["condition"]],  # type: ignore[union-attr]
    })  # fmt: skip
    if isinstance(task, TypedTask):
        units = scoring_units(protocol, task)
        n = np.array([units.get((a, b), np.nan) for a, b in zip(
            known["stimulus_set"], known["stimulus"], strict=True)], dtype=float)  # fmt: skip
        frame["correct"] = known["correct"].to_numpy()
        frame["units"] = n
        frame["hits"] = np.round(known["score"].to_numpy(dtype=float) * n)
        return frame.dropna(subset=["units", "hits"]).reset_index(drop=True)
    frame["target"] = [task.target(condition=c, stimulus=s) for c, s in zip(
        known["condition"], known["stimulus"], strict=True)]  # fmt: skip
    frame["response"] = known["response"].astype(str).to_numpy()
    frame = frame.dropna(subset=["target"])
    frame["correct"] = (frame["response"] == frame["target"]).astype(int)
    frame["units"], frame["hits"] = 1.0, frame["correct"].astype(float)
    return frame.drop(columns=["target", "response"]).reset_index(drop=True)


def is_noise_task(protocol: Protocol, task: NoiseTask) -> bool:
    """A task scored on words heard in noise at several SNRs (analysed by its thresholds):
    typed answers, or an identify task with answers judging no timing; and a block showing
    it has a condition series in noise at two or more SNRs. A fixed-SNR design is compared
    per condition."""
    if isinstance(task, IdentifyTask) and (
        not task.answers or task.timing is not None or len(task.labels) < 3
    ):
        return False
    conds = {c.id: c for c in protocol.conditions}
    snrs: dict[str, set[float]] = {}
    for block in protocol.blocks:
        if block.task == task.id:
            for c in protocol.block_conditions(block):
                noise = conds[c].noise if c in conds else None
                if noise is not None:
                    snrs.setdefault(conds[c].series_id, set()).add(noise.snr_db)
    return any(len(v) >= 2 for v in snrs.values())


def audio_only_series(protocol: Protocol) -> str | None:
    """The one series of audio-only conditions with noise (the benefit's reference), if any."""
    names = {c.series_id for c in protocol.conditions
             if c.modality == "audio_only" and c.noise is not None}  # fmt: skip
    return next(iter(names)) if len(names) == 1 else None


def _loglik_and_gradient(
    theta: np.ndarray, *, x: np.ndarray, n: np.ndarray, k: np.ndarray, guess: float
) -> tuple[float, np.ndarray]:
    """The binomial log-likelihood of ``k`` of ``n`` right at SNRs ``x`` (dB) and its
    derivatives (3,) in ``theta`` = (srt dB, log slope per dB, lapse), from one evaluation
    (0 where ``p`` is clipped, as the clipped likelihood is flat there).

    With ``s = 1 - guess - lapse``, ``f = (1/2 - guess) / s``, ``beta = slope / (s f (1 -
    f))`` and ``u = beta (x - srt) + logit(f)``, P = guess + s * logistic(u); ``s f`` does
    not depend on the lapse, which gives du/dlapse = (beta f (x - srt) + 1) / (s (1 - f))."""
    srt, slope, lapse = theta[0], math.exp(theta[1]), theta[2]
    s = 1.0 - guess - lapse
    f = (0.5 - guess) / s
    beta = slope / (s * f * (1.0 - f))
    d = x - srt
    sig = special.expit(beta * d + math.log(f / (1.0 - f)))
    p = s * sig + guess
    slope_at = s * sig * (1.0 - sig)  # dP/du
    # few numpy calls: the optimiser evaluates this hundreds of thousands of times
    rows = [-beta * slope_at, (beta * d) * slope_at,
            slope_at * ((beta * f) * d + 1.0) / (s * (1.0 - f)) - sig]  # fmt: skip
    value, weight = binomial_loglik_and_weight(p, n=n, k=k, eps=_EPS)
    return value, np.array(rows) @ weight


def fit_srt(
    trials: pd.DataFrame, *, guess: float, level: float = 0.95, intervals: bool = True,
    snr_range: tuple[float, float] | None = None,
) -> SrtFit:  # fmt: skip
    """Fit one participant's SRT to ``trials`` (``snr_db, correct``, or ``snr_db, units,
    hits``); see the module. ``snr_range``: the lowest and highest SNR the procedure can
    show in this series (default the SNRs answered): answers that never cross 50 % are
    noted only when they reach that end (a track stuck at the procedure's limit)."""
    if "units" in trials:
        counts = (trials.groupby("snr_db", sort=True)[["units", "hits"]].sum()
                  .rename(columns={"units": "n", "hits": "k"}).reset_index())  # fmt: skip
    else:
        counts = (trials.groupby("snr_db", sort=True)["correct"].agg(n="size", k="sum")
                  .reset_index())  # fmt: skip
    x = counts["snr_db"].to_numpy(dtype=float)
    n = counts["n"].to_numpy(dtype=float)
    k = counts["k"].to_numpy(dtype=float)
    if len(x) < 2:
        raise AnalysisError(f"an SRT needs answers at two or more SNRs, got {len(x)}")
    span = float(x[-1] - x[0])
    bounds = [(float(x[0]) - span, float(x[-1]) + span),
              (math.log(SLOPE_BOUND[0]), math.log(SLOPE_BOUND[1])), LAPSE_BOUND]  # fmt: skip

    def loglik(theta: np.ndarray) -> float:
        p = p_correct(x, srt=theta[0], slope=math.exp(theta[1]), guess=guess, lapse=theta[2])
        p = np.clip(p, _EPS, 1 - _EPS)
        return float(np.sum(k * np.log(p) + (n - k) * np.log1p(-p)))

    def both(theta: np.ndarray) -> tuple[float, np.ndarray]:
        return _loglik_and_gradient(theta, x=x, n=n, k=k, guess=guess)

    share = k / n
    above = x[share >= 0.5]
    start = float(above.min()) if len(above) else float(x[-1])
    starts = [np.array([c, math.log(s), 0.02]) for c in (start, float(np.median(x)))
              for s in (0.05, 0.15)]  # fmt: skip
    theta, ll = best_fit(loglik, bounds=bounds, starts=starts, both=both)
    lo = hi = math.nan
    if intervals:
        lo, hi = profile_interval(loglik, bounds=bounds, theta=theta, ll=ll, index=0,
                                  cutoff=chi2_cutoff(level), both=both)  # fmt: skip
    notes = []
    side = _unbracketed(share, srt_db=float(theta[0]), x=x,
                        snr_range=snr_range or (float(x[0]), float(x[-1])))
    if side:
        most = "more than half" if side == "below" else "half or fewer"
        notes.append(f"{most} right at every SNR tested ({x[0]:g} to {x[-1]:g} dB): the SRT "
                     f"lies {side} them; the answers bound it, they do not place it (the "
                     "procedure's SNR range does not reach this participant's threshold)")
    elif on_bound(theta[0], bounds[0]):
        notes.append("the SRT ends on its search bound (outside the SNRs tested)")
    if math.isinf(lo) or math.isinf(hi):
        notes.append("the SRT interval reaches beyond the SNRs searched")
    p_hat = p_correct(x, srt=theta[0], slope=math.exp(theta[1]), guess=guess, lapse=theta[2])
    return SrtFit(
        n=int(n.sum()), srt_db=float(theta[0]), srt_ci_low=lo, srt_ci_high=hi,
        slope_per_db=math.exp(theta[1]), lapse=float(theta[2]),
        deviance=binomial_deviance(k, n, p_hat), deviance_df=max(0, len(x) - 3),
        note="; ".join(notes),
    )  # fmt: skip


def _unbracketed(
    share: np.ndarray, *, srt_db: float, x: np.ndarray, snr_range: tuple[float, float]
) -> str:
    """``"below"`` when more than half were right at every SNR ``x``, the lowest of them is
    the procedure's lowest and the fitted SRT lies below them all; ``"above"`` when at most
    half were right everywhere, the highest is the procedure's highest and it lies above
    them (the answers never cross 50 %: a track stuck at the procedure's easy or hard end);
    ``""`` otherwise."""
    if bool(np.all(share > 0.5)) and srt_db < x[0] and x[0] <= snr_range[0] + 1e-9:
        return "below"
    if bool(np.all(share <= 0.5)) and srt_db > x[-1] and x[-1] >= snr_range[1] - 1e-9:
        return "above"
    return ""


def _one_snr(part: pd.DataFrame) -> SrtFit:
    """The row of a series answered at a single SNR (a track that never left one end of its
    range, or one trial): no SRT, and the note says which side of that SNR it lies on."""
    units = part["units"] if "units" in part else pd.Series(1.0, index=part.index)
    hits = part["hits"] if "hits" in part else part["correct"].astype(float)
    n, k, snr = float(units.sum()), float(hits.sum()), float(part["snr_db"].iloc[0])
    side = "below" if k > n / 2 else "above" if k < n / 2 else "near"
    return SrtFit(
        n=int(n), srt_db=math.nan, srt_ci_low=math.nan, srt_ci_high=math.nan,
        slope_per_db=math.nan, lapse=math.nan, deviance=math.nan, deviance_df=0,
        note=(f"every answer at one SNR ({snr:g} dB, {k:g} of {n:g} scored units right): the "
              f"SRT lies {side} it and is not estimated (the procedure's SNR range does not "
              "reach this participant's threshold)"),
    )  # fmt: skip


def srt_table(
    rows: pd.DataFrame, protocol: Protocol, task: NoiseTask, *, level: float = 0.95,
    intervals: bool = True,
) -> pd.DataFrame:  # fmt: skip
    """``srt.csv``: :data:`SRT_COLUMNS`, one row per participant and series (protocol order);
    the benefit columns against :func:`audio_only_series` (NaN without one, and on its own
    rows)."""
    trials = noise_trials(rows, protocol, task)
    guess = guess_rate(task)
    order = list(dict.fromkeys(c.series_id for c in protocol.conditions if c.noise is not None))
    out = []
    fits: dict[tuple[str, str], SrtFit] = {}
    ranges: dict[str, list[float]] = {}
    for c in protocol.conditions:
        if c.noise is not None:
            ranges.setdefault(c.series_id, []).append(c.noise.snr_db)
    for (pid, series), part in trials.groupby(["participant", "condition"], sort=True):
        if part["snr_db"].nunique() < 2:
            fits[(str(pid), str(series))] = _one_snr(part)
            continue
        snrs = ranges.get(str(series)) or list(part["snr_db"])
        fits[(str(pid), str(series))] = fit_srt(part, guess=guess, level=level,
                                                intervals=intervals,
                                                snr_range=(min(snrs), max(snrs)))  # fmt: skip
    reference = audio_only_series(protocol)
    z = float(stats.norm.ppf(0.5 + level / 2))
    for (pid, series), fit in fits.items():
        row = {"participant": pid, "condition": series, **asdict(fit),
               "benefit_db": math.nan, "benefit_ci_low": math.nan, "benefit_ci_high": math.nan,
               "visual_enhancement": math.nan}  # fmt: skip
        ref = fits.get((pid, reference)) if reference is not None else None
        if ref is not None and ref.note:  # the audio-only SRT is not determined: no benefit
            ref = None
        if ref is not None and series != reference:
            benefit = ref.srt_db - fit.srt_db
            se = math.sqrt(sum(((f.srt_ci_high - f.srt_ci_low) / (2 * z)) ** 2
                               for f in (fit, ref)))  # fmt: skip
            p_av = float(p_correct(ref.srt_db, srt=fit.srt_db, slope=fit.slope_per_db,
                                   guess=guess, lapse=fit.lapse))  # fmt: skip
            # a slope on its bound says only "steeper (or shallower) than the SNRs show":
            # P_AV away from the SRT, and so the enhancement, is then not estimated
            steep = on_bound(math.log(fit.slope_per_db), tuple(map(math.log, SLOPE_BOUND)))
            row |= {"benefit_db": benefit, "benefit_ci_low": benefit - z * se,
                    "benefit_ci_high": benefit + z * se,
                    "visual_enhancement": math.nan if steep else (p_av - 0.5) / 0.5}  # fmt: skip
        out.append(row)
    frame = pd.DataFrame(out, columns=list(SRT_COLUMNS))
    rank = {s: i for i, s in enumerate(order)}
    frame = frame.sort_values(["participant", "condition"], key=lambda c: c.map(rank)
                              if c.name == "condition" else c, kind="stable")  # fmt: skip
    return frame.reset_index(drop=True)


def srt_tests(table: pd.DataFrame, *, reference: str | None) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(summary, tests): the series' mean SRT (and benefit) with 95 % t intervals, and the
    within-participant comparisons of the SRT over all series and of the benefit over the
    audio-visual series (participants with a note on a series left out)."""
    summary, tests = fstats.series_comparison(table, measures=("srt_db",))
    visual = table[table["condition"] != reference] if reference is not None else table.iloc[:0]
    if not visual.empty:
        more, more_tests = fstats.series_comparison(
            visual, measures=("benefit_db", "visual_enhancement"),
            bounds={"visual_enhancement": (-1.0, 1.0)})  # (p_av - 0.5) / 0.5
        summary = summary.merge(more.drop(columns=["participants", "determined"]),
                                on="condition", how="left")  # fmt: skip
        tests = pd.concat([tests, more_tests], ignore_index=True)
    return summary, tests


def srt_curves(
    trials: pd.DataFrame, *, guess: float, snr: np.ndarray, order: list[str]
) -> pd.DataFrame:
    """``condition, snr_db, p``: each series' function fitted to everyone's answers pooled
    (for figures; the participants' own fits are noisier than their sum), series in
    ``order``."""
    rows = []
    for series in order:
        part = trials[trials["condition"] == series]
        if part["snr_db"].nunique() < 2:
            continue
        fit = fit_srt(part, guess=guess, intervals=False)
        p = p_correct(snr, srt=fit.srt_db, slope=fit.slope_per_db, guess=guess, lapse=fit.lapse)
        rows += [{"condition": series, "snr_db": float(s), "p": float(v)}
                 for s, v in zip(snr, p, strict=True)]  # fmt: skip
    return pd.DataFrame(rows, columns=["condition", "snr_db", "p"])
