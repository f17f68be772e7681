"""Behaviour counts as covariates (seed 003): did a condition's effect come from how much the
head moved?

Every clip rendered with a behaviour layer has an event log ``<clip_id>.behaviour.json``
beside it (``facelab render``). :func:`clip_behaviour` reads them into one row per clip: the
number of events per layer (``n_posture n_mannerism n_gesture n_blink``) and per unit
(``unit_<name>``), and the motion energy. :func:`covariate_model` fits, per item, a linear
mixed model ``rating ~ C(condition) + n_posture + n_mannerism + n_gesture + n_blink`` with
random intercepts per participant and per participant x condition (statsmodels MixedLM,
REML), returning every fixed effect - so the condition effect is read with the amount of
behaviour held fixed. Covariates that do not vary (or are collinear with the conditions) are
dropped and named in the ``note`` column.
:func:`identification_covariates` does the same for identification answers: a logistic GEE of
a right answer on the condition and the counts (:func:`facelab.analysis.identification.
correct_model`), so "composite behaviour was recognised more often" can be read with the
number of events held fixed.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats as sps

from facelab.analysis.identification import correct_model
from facelab.analysis.stats import _require, levels, screen_covariates
from facelab.errors import AnalysisError

__all__ = [
    "COVARIATE_COLUMNS",
    "LAYER_COUNTS",
    "clip_behaviour",
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
    manifest = Path(clips_dir) / "clips.csv"
    if not manifest.is_file():
        raise AnalysisError(f"{manifest}: no clip manifest (render the clips first)")
    clips = pd.read_csv(manifest, dtype=str)
    rows = []
    for clip in clips.itertuples(index=False):
        path = Path(clips_dir) / f"{clip.clip_id}.behaviour.json"
        if not path.is_file():
            continue
        try:
            log = json.loads(path.read_text(encoding="utf-8"))
            events = log["events"]
        except (OSError, ValueError, KeyError) as exc:
            raise AnalysisError(f"{path}: not a behaviour log ({exc})") from None
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
    per subject x condition, REML.

    The subject x condition intercept matters: ratings of one participant in one condition
    share that participant's view of the condition, so without it the condition effect's
    SE is too small - simulated with the shipped behaviour protocol, 12 participants and no
    true difference, a random-intercept-only model (ML, z test) rejected in 15 % of studies.
    With it, the condition term's SE equals the paired analysis of participant means (two
    conditions, balanced), and its ``t`` is referred to Student's t with (conditions - 1) x
    (participants - 1) df, as the RM ANOVA's error term (rejection 5 % in that simulation).
    Covariate terms vary between clips, not within participants' cells: their ``df`` is NaN
    and ``p`` is from the normal distribution (no random stimulus effect is modelled, so read
    them as descriptive).

    ``data``: one row per rating with ``stimulus_set, stimulus, condition``; ``counts``: from
    :func:`clip_behaviour`. Ratings of clips without a log get zero counts (no behaviour).
    The reference condition is the first of ``conditions`` (default: order of first
    appearance); ``note`` names it and any covariate dropped."""
    _require(data, (dv, item, subject, condition, "stimulus_set", "stimulus"))
    import statsmodels.formula.api as smf

    merged = _with_counts(data, counts, covariates)
    order = list(conditions) if conditions is not None else levels(merged[condition])
    merged[condition] = pd.Categorical(merged[condition], categories=order)
    parts = []
    for it, part in merged.groupby(item, sort=True):
        part = part.dropna(subset=[dv])
        used, dropped = screen_covariates(part, covariates, condition=condition)
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
        for term in fit.fe_params.index:
            est, t = float(fit.fe_params[term]), float(fit.fe_params[term] / se[term])
            is_condition = term.startswith(f"C({condition})")
            df = float(cell_df) if is_condition and cell_df > 0 else float("nan")
            parts.append(
                {
                    "item": it,
                    "term": term,
                    "estimate": est,
                    "se": float(se[term]),
                    "t": t,
                    "df": df,
                    "p": float(
                        2 * sps.t.sf(abs(t), df) if np.isfinite(df) else 2 * sps.norm.sf(abs(t))
                    ),
                    "n_obs": len(part),
                    "n_participants": n_subjects,
                    "note": note,
                }
            )
    return pd.DataFrame(parts, columns=list(COVARIATE_COLUMNS))


def identification_covariates(
    trials: pd.DataFrame,
    counts: pd.DataFrame,
    *,
    conditions: tuple[str, ...] | None = None,
    covariates: tuple[str, ...] = LAYER_COUNTS,
) -> pd.DataFrame:
    """``logit P(correct) ~ C(condition) + covariates``, clustered by participant.

    ``trials``: scored identification answers (``correct`` 0/1, ``participant``,
    ``stimulus_set, stimulus, condition``); ``counts``: from :func:`clip_behaviour`. Answers
    to clips without a log get zero counts."""
    _require(trials, ("correct", "participant", "stimulus_set", "stimulus", "condition"))
    merged = _with_counts(trials, counts, covariates)
    return correct_model(merged, covariates=covariates, conditions=conditions)


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
