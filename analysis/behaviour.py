"""Behaviour counts as covariates (seed 003): did a condition's effect come from how much the
head moved?

Every clip rendered with a behaviour layer has an event log ``<clip_id>.behaviour.json``
beside it (``facelab render``). :func:`clip_behaviour` reads them into one row per clip: the
number of events per layer (``n_posture n_mannerism n_gesture n_blink``) and per unit
(``unit_<name>``), and the motion energy. :func:`covariate_model` fits, per item, a linear
mixed model ``rating ~ C(condition) + n_posture + n_mannerism + n_gesture + n_blink`` with
random intercepts per participant and per participant x condition (statsmodels MixedLM,
REML), returning every fixed effect - so the condition effect is read with the amount of
behaviour held fixed; the covariates themselves are tested between clips
(:func:`clip_regression`), since that is where they vary. Covariates that do not vary (or
are collinear with the conditions) are dropped and named in the ``note`` column.
:func:`identification_covariates` does the same for identification answers: a logistic GEE of
a right answer on the condition and the counts (:func:`facelab.analysis.identification.
correct_model`), so "composite behaviour was recognised more often" can be read with the
number of events held fixed.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats as sps

from facelab.analysis.identification import MODEL_COLUMNS, correct_model
from facelab.analysis.stats import levels, require, screen_covariates
from facelab.errors import AnalysisError, FormatError
from facelab.formats import behaviour_log_path, read_behaviour_log, read_manifest

__all__ = [
    "COVARIATE_COLUMNS",
    "LAYER_COUNTS",
    "clip_behaviour",
    "clip_logit",
    "clip_regression",
    "covariate_model",
    "identification_covariates",
]

LAYER_COUNTS = ("n_posture", "n_mannerism", "n_gesture", "n_blink")
COVARIATE_COLUMNS = (
    "item",
    "term",
    "estimate",
    "se",
    "t",
    "df",
    "p",
    "n_obs",
    "n_participants",
    "note",
)


def clip_behaviour(clips_dir: Path) -> pd.DataFrame:
    """One row per clip of ``clips_dir/clips.csv`` that has a behaviour log: ``clip_id,
    stimulus_set, stimulus, condition, mode``, the layer counts, ``unit_*`` counts and
    ``energy_face_per_s, energy_rotation_deg_per_s``. Empty when no clip has a log."""
    try:
        clips = pd.DataFrame(
            read_manifest(clips_dir, need=("clip_id", "stimulus_set", "stimulus", "condition"))
        )
    except FormatError as exc:
        raise AnalysisError(str(exc)) from None
    rows = []
    for clip in clips.itertuples(index=False):
        path = behaviour_log_path(clips_dir, clip.clip_id)
        if not path.is_file():
            continue
        try:
            log = read_behaviour_log(path)
        except FormatError as exc:
            raise AnalysisError(str(exc)) from None
        events = log["events"]
        row = {
            "clip_id": clip.clip_id,
            "stimulus_set": clip.stimulus_set,
            "stimulus": clip.stimulus,
            "condition": clip.condition,
            "mode": log.get("mode", ""),
            **dict.fromkeys(LAYER_COUNTS, 0),
        }
        for e in events:
            row[f"n_{e['layer']}"] = row.get(f"n_{e['layer']}", 0) + 1
            row[f"unit_{e['unit']}"] = row.get(f"unit_{e['unit']}", 0) + 1
        energy = log.get("realisation", {}).get("energy", {})
        row["energy_face_per_s"] = energy.get("face_per_s", np.nan)
        row["energy_rotation_deg_per_s"] = energy.get("rotation_deg_per_s", np.nan)
        rows.append(row)
    out = pd.DataFrame(rows)
    unit_cols = sorted(c for c in out.columns if c.startswith("unit_"))
    if unit_cols:
        out[unit_cols] = out[unit_cols].fillna(0).astype(int)
    return out


def covariate_model(
    data: pd.DataFrame,
    counts: pd.DataFrame,
    *,
    dv: str = "rating",
    item: str = "item",
    subject: str = "participant",
    condition: str = "condition",
    covariates: tuple[str, ...] = LAYER_COUNTS,
    conditions: tuple[str, ...] | None = None,
) -> pd.DataFrame:
    """Per item, ``dv ~ C(condition) + covariates`` with random intercepts per subject and
    per subject x condition, REML; the covariates tested between clips.

    The subject x condition intercept matters: ratings of one participant in one condition
    share that participant's view of the condition, so without it the condition effect's
    SE is too small - simulated with the shipped behaviour protocol, 12 participants and no
    true difference, a random-intercept-only model (ML, z test) rejected in 15 % of studies.
    With it, the condition term's SE equals the paired analysis of participant means (two
    conditions, balanced), and its ``t`` is referred to Student's t with (conditions - 1) x
    (participants - 1) df, as the RM ANOVA's error term (rejection 5 % in that simulation).

    Covariate terms vary between clips, not within participants' cells, so their evidence is
    as many clips as there are, however many people rated each: clips differ in more than
    their counts (the sentence, the moment a nod fell), and every participant sees the same
    clip's difference. Their rows come from the by-clip regression (:func:`clip_regression`:
    each clip's mean rating, participants' own means taken out, ``~ C(condition) +
    covariates`` by least squares), with ``df`` = clips - terms; in a balanced study its
    estimates equal the mixed model's and only the SE honestly grows. With no more clips
    than terms they cannot be tested (``p`` NaN, said in ``note``). Simulated (12
    participants, 8 sentences x 2 conditions, a clip-to-clip SD of 6 and a residual SD of 10
    VAS points, a count unrelated to the ratings; 200 studies), the mixed model's own
    covariate SE - each rating taken as independent evidence about its clip - rejected the
    true null in 35 % of studies, the by-clip test in 3 %.

    The condition term, like the RM ANOVA, generalises over participants for these clips: a
    difference between the clips of two conditions is a difference, whether it comes from
    the behaviour or the sentence (in the covariate simulation above, whose clips differ but
    whose conditions do not, it rejected in 20.5 % of studies). To generalise over sentences
    too, render several per condition and read the row ``C(condition)[T.x] (by clip)``: the
    same term from the by-clip regression, on clips - terms df (5.5 % there); it is given
    whenever the clips leave a df for it.

    ``data``: one row per rating with ``stimulus_set, stimulus, condition``; ``counts``: from
    :func:`clip_behaviour`. Ratings of clips without a log get zero counts (no behaviour).
    The reference condition is the first of ``conditions`` (default: order of first
    appearance); ``note`` names it and any covariate dropped."""
    require(data, (dv, item, subject, condition, "stimulus_set", "stimulus"))
    import statsmodels.formula.api as smf

    merged = _with_counts(data, counts, covariates)
    order = list(conditions) if conditions is not None else levels(merged[condition])
    merged[condition] = pd.Categorical(merged[condition], categories=order)
    parts = []
    for it, part in merged.groupby(item, sort=True):
        part = part.dropna(subset=[dv])
        used, dropped = screen_covariates(part, covariates, condition=condition)
        used, collinear = _independent_at_clip_level(part, used, condition=condition)
        dropped = [d for d in dropped if not any(d.startswith(f"{c} ") for c in collinear)]
        dropped += [f"{c} collinear with the terms before it (clip by clip)" for c in collinear]
        formula = f"{dv} ~ C({condition})" + "".join(f" + {c}" for c in used)
        present = [c for c in order if c in set(part[condition])]
        part = part.assign(**{condition: pd.Categorical(part[condition], categories=present)})
        note = "; ".join([f"reference: {present[0]}", *dropped])
        n_subjects = int(part[subject].nunique())
        cell_df = (len(present) - 1) * (n_subjects - 1)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                fit = smf.mixedlm(
                    formula,
                    part,
                    groups=part[subject],
                    re_formula="1",
                    vc_formula={"cell": f"0 + C({condition})"},
                ).fit(reml=True)
                se = fit.bse_fe
            except (ValueError, np.linalg.LinAlgError) as exc:
                raise AnalysisError(f"item {it!r}: the covariate model failed ({exc})") from None
        if not np.all(np.isfinite(se)):
            raise AnalysisError(f"item {it!r}: the covariate model did not converge")
        by_clip = clip_regression(
            part, dv=dv, subject=subject, condition=condition, covariates=tuple(used)
        )
        if used:
            note += "; " + _tested_note(by_clip)
        rows = []  # (term, estimate, se, df)
        for term in fit.fe_params.index:
            is_condition = term.startswith(f"C({condition})")
            if term in used:
                rows.append((term, by_clip["estimate"][term], by_clip["se"][term], by_clip["df"]))
                continue
            df = float(cell_df) if is_condition and cell_df > 0 else float("nan")
            rows.append((term, float(fit.fe_params[term]), float(se[term]), df))
            if is_condition and by_clip["df"] >= 1:  # generalising over the sentences too
                rows.append(
                    (
                        f"{term} (by clip)",
                        by_clip["estimate"][term],
                        by_clip["se"][term],
                        by_clip["df"],
                    )
                )
        for term, est, term_se, df in rows:
            t = est / term_se if term_se > 0 else float("nan")
            usable = np.isfinite(t) and df >= 1
            parts.append(
                {
                    "item": it,
                    "term": term,
                    "estimate": est,
                    "se": term_se,
                    "t": t,
                    "df": df if df >= 1 else float("nan"),
                    "p": float(2 * sps.t.sf(abs(t), df)) if usable else float("nan"),
                    "n_obs": len(part),
                    "n_participants": n_subjects,
                    "note": note,
                }
            )
    return pd.DataFrame(parts, columns=list(COVARIATE_COLUMNS))


def clip_regression(
    data: pd.DataFrame,
    *,
    dv: str = "rating",
    subject: str = "participant",
    condition: str = "condition",
    covariates: tuple[str, ...] = LAYER_COUNTS,
) -> dict:
    """The by-clip regression of :func:`covariate_model`: one value per clip (``stimulus_set,
    stimulus, condition``) - the mean of ``dv`` after each subject's mean is taken out (the
    grand mean added back; the plain clip mean when everyone rated every clip) - regressed on
    ``C(condition)`` and ``covariates`` by ordinary least squares.

    Returns ``{"estimate": {term: value}, "se": {term: value}, "df": clips - terms,
    "clips": n}`` with terms named as in the mixed model (``Intercept``,
    ``C(condition)[T.x]``, covariate names); ``se`` is NaN when df < 1."""
    centred = data[dv] - data.groupby(subject)[dv].transform("mean") + data[dv].mean()
    keys = ["stimulus_set", "stimulus", condition]
    clips = (
        data.assign(_y=centred)
        .groupby(keys, observed=True, sort=True)
        .agg(_y=("_y", "mean"), **{c: (c, "first") for c in covariates})
        .reset_index()
    )
    names, x = _clip_design(clips, levels(data[condition]), condition, covariates)
    y = clips["_y"].to_numpy(float)
    beta, *_ = np.linalg.lstsq(x, y, rcond=None)
    df = len(y) - np.linalg.matrix_rank(x)
    if df >= 1:
        sigma2 = float(np.sum((y - x @ beta) ** 2)) / df
        se = np.sqrt(np.diag(sigma2 * np.linalg.pinv(x.T @ x)))
    else:
        se = np.full(len(beta), np.nan)
    return {
        "estimate": dict(zip(names, beta.tolist(), strict=True)),
        "se": dict(zip(names, se.tolist(), strict=True)),
        "df": float(df),
        "clips": len(y),
    }


def _independent_at_clip_level(
    data: pd.DataFrame, covariates: list[str], *, condition: str
) -> tuple[list[str], list[str]]:
    """(kept, dropped): covariates in order, each kept only when it is not a linear
    combination, clip by clip, of the intercept, the condition terms and the covariates kept
    before it (with few clips several counts can be; the model would be singular)."""
    keys = ["stimulus_set", "stimulus", condition]
    clips = data.groupby(keys, observed=True).first().reset_index()
    _names, x = _clip_design(clips, levels(clips[condition]), condition, ())
    kept, dropped = [], []
    for c in covariates:
        candidate = np.column_stack([x, clips[c].to_numpy(float)])
        if np.linalg.matrix_rank(candidate) > np.linalg.matrix_rank(x):
            kept.append(c)
            x = candidate
        else:
            dropped.append(c)
    return kept, dropped


def identification_covariates(
    trials: pd.DataFrame,
    counts: pd.DataFrame,
    *,
    conditions: tuple[str, ...] | None = None,
    covariates: tuple[str, ...] = LAYER_COUNTS,
) -> pd.DataFrame:
    """``logit P(correct) ~ C(condition) + covariates``, clustered by participant; the
    covariates tested between clips.

    The condition and intercept rows are :func:`facelab.analysis.identification.
    correct_model`'s (logistic GEE, bias-corrected SEs, t on participants - parameters df).
    The covariates vary between clips, so, as in :func:`covariate_model`, their rows come
    from the clips: :func:`clip_logit` (each clip's right and wrong answers, a binomial GLM
    of ``C(condition) + covariates`` with its dispersion estimated from the clips - a
    quasi-binomial - and ``t`` on clips - terms df; ``se_robust`` and ``se_md`` are NaN
    there). Counts collinear clip by clip are dropped and named, as there. When the clips
    leave a df, the condition's row from that model follows its GEE row as
    ``C(condition)[T.x] (by clip)``: the odds ratio tested over sentences as well as people.
    Simulated (12 participants, 8 sentences x 2 conditions, clip-to-clip logit SD 0.6, a
    count unrelated to the answers, no true condition effect; 200 studies), the GEE's own
    covariate test rejected in 10.5 % of studies, the by-clip one in 5.0 %; the GEE's
    condition row (right for these clips) in 11 %, its by-clip row in 4 %.

    ``trials``: scored identification answers (``correct`` 0/1, ``participant``,
    ``stimulus_set, stimulus, condition``); ``counts``: from :func:`clip_behaviour`. Answers
    to clips without a log get zero counts."""
    require(trials, ("correct", "participant", "stimulus_set", "stimulus", "condition"))
    merged = _with_counts(trials, counts, covariates)
    merged = merged.dropna(subset=["correct"])
    used, dropped = screen_covariates(merged, covariates, condition="condition")
    used, collinear = _independent_at_clip_level(merged, used, condition="condition")
    model = correct_model(merged, covariates=tuple(used), conditions=conditions)
    # correct_model names what it sees in the covariates it gets; these are the ones it did not
    notes = [f"{c} collinear with the terms before it (clip by clip)" for c in collinear]
    notes += [d for d in dropped if not any(d.startswith(f"{c} ") for c in (*collinear, *used))]
    order = list(conditions) if conditions is not None else levels(merged["condition"])
    by_clip = clip_logit(merged, covariates=tuple(used), conditions=tuple(order))
    if used:
        notes.append(
            _tested_note(by_clip, how=f"quasi-binomial, dispersion {by_clip['dispersion']:.2f}")
        )
    if notes:
        model["note"] = model["note"] + "; " + "; ".join(notes)
    for c in used:
        model.loc[model["term"] == c, list(_BY_CLIP_COLUMNS)] = _by_clip_row(by_clip, c)
    is_condition = model["term"].str.startswith("C(condition)")
    if by_clip["df"] < 1 or not is_condition.any():
        return model
    extra = model[is_condition].copy()  # the condition over sentences too
    extra[list(_BY_CLIP_COLUMNS)] = [_by_clip_row(by_clip, t) for t in extra["term"]]
    extra["term"] = extra["term"] + " (by clip)"
    at = int(np.nonzero(is_condition.to_numpy())[0][-1]) + 1
    return pd.concat([model.iloc[:at], extra, model.iloc[at:]], ignore_index=True)


#: the columns of correct_model's table that a by-clip row fills (estimate ... se_md)
_BY_CLIP_COLUMNS = MODEL_COLUMNS[MODEL_COLUMNS.index("estimate") : MODEL_COLUMNS.index("se_md") + 1]


def _tested_note(by_clip: dict, *, how: str = "") -> str:
    """The note on whether the clips left degrees of freedom to test the covariates."""
    if by_clip["df"] < 1:
        terms = by_clip["clips"] - int(by_clip["df"])
        return f"covariates not tested: {by_clip['clips']} clips for {terms} terms"
    return f"covariates tested between {by_clip['clips']} clips" + (f" ({how})" if how else "")


def _by_clip_row(by_clip: dict, term: str) -> list[float]:
    """A term's values from :func:`clip_logit` in :data:`_BY_CLIP_COLUMNS` order (the
    participant-clustered SEs do not apply: NaN)."""
    est, se, df = by_clip["estimate"][term], by_clip["se"][term], by_clip["df"]
    t = est / se if se > 0 else float("nan")
    ok = df >= 1 and np.isfinite(t)
    t_crit = float(sps.t.ppf(0.975, df)) if ok else float("nan")
    return [
        est,
        se,
        t,
        df if df >= 1 else float("nan"),
        float(2 * sps.t.sf(abs(t), df)) if ok else float("nan"),
        float(np.exp(est)),
        float(np.exp(est - t_crit * se)) if ok else float("nan"),
        float(np.exp(est + t_crit * se)) if ok else float("nan"),
        float("nan"),
        float("nan"),
    ]


def _clip_design(
    clips: pd.DataFrame, present: list, condition: str, covariates: tuple[str, ...]
) -> tuple[list[str], np.ndarray]:
    """Term names and the (clips, terms) design matrix: intercept, a dummy per condition
    after the first of ``present``, the covariates - named as in the mixed model."""
    columns = {"Intercept": np.ones(len(clips))}
    for level in present[1:]:
        columns[f"C({condition})[T.{level}]"] = (clips[condition] == level).to_numpy(float)
    for c in covariates:
        columns[c] = clips[c].to_numpy(float)
    return list(columns), np.column_stack(list(columns.values()))


def clip_logit(
    trials: pd.DataFrame,
    *,
    covariates: tuple[str, ...],
    conditions: tuple[str, ...],
    correct: str = "correct",
    condition: str = "condition",
) -> dict:
    """The by-clip model of :func:`identification_covariates`: per clip (``stimulus_set,
    stimulus, condition``) the right and wrong answers; a binomial GLM (logit) of
    ``C(condition) + covariates`` whose dispersion is Pearson's chi-square / (clips - terms)
    (never below 1: clips can differ more than binomially, not less); SEs scaled by it.

    Returns ``{"estimate": {term: log odds}, "se": {...}, "df": clips - terms, "clips": n,
    "dispersion": phi}`` (``se`` NaN when df < 1 or the fit failed)."""
    import statsmodels.api as sm

    y = trials[correct].astype(float)
    keys = ["stimulus_set", "stimulus", condition]
    clips = (
        trials.assign(_r=y, _n=1.0)
        .groupby(keys, observed=True, sort=True)
        .agg(_r=("_r", "sum"), _n=("_n", "sum"), **{c: (c, "first") for c in covariates})
        .reset_index()
    )
    present = [c for c in conditions if c in set(clips[condition])]
    names, x = _clip_design(clips, present, condition, covariates)
    df = float(len(clips) - np.linalg.matrix_rank(x))
    nan = dict.fromkeys(names, float("nan"))
    endog = np.column_stack([clips["_r"], clips["_n"] - clips["_r"]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            fit = sm.GLM(endog, x, family=sm.families.Binomial()).fit()
        except (ValueError, np.linalg.LinAlgError):
            return {"estimate": nan, "se": nan, "df": df, "clips": len(clips), "dispersion": 1.0}
    params = np.asarray(fit.params, float)
    if df >= 1:
        pearson = float(np.sum(np.asarray(fit.resid_pearson, float) ** 2))
        dispersion = max(1.0, pearson / df)
        se = np.asarray(fit.bse, float) * np.sqrt(dispersion)
    else:
        dispersion, se = 1.0, np.full(len(params), np.nan)
    if not np.all(np.isfinite(params)):
        se = np.full(len(params), np.nan)
    return {
        "estimate": dict(zip(names, params.tolist(), strict=True)),
        "se": dict(zip(names, se.tolist(), strict=True)),
        "df": df,
        "clips": len(clips),
        "dispersion": dispersion,
    }


def _with_counts(
    data: pd.DataFrame, counts: pd.DataFrame, covariates: tuple[str, ...]
) -> pd.DataFrame:
    """``data`` with each clip's behaviour counts (0 for clips without a log)."""
    keys = ["stimulus_set", "stimulus", "condition"]
    missing = [c for c in (*keys, *covariates) if c not in counts.columns]
    if missing:
        raise AnalysisError(f"the behaviour counts have no column(s) {missing}")
    merged = data.merge(counts[[*keys, *covariates]], on=keys, how="left")
    merged[list(covariates)] = merged[list(covariates)].fillna(0)
    return merged
