"""Behaviour counts as covariates (seed 003): did a condition's effect come from how much the
head moved?

Every clip rendered with a behaviour layer has an event log ``<clip_id>.behaviour.json``
beside it (``facelab render``). :func:`clip_behaviour` reads them into one row per clip: the
number of events per layer (``n_posture n_mannerism n_gesture n_blink``) and per unit
(``unit_<name>``), and the motion energy. :func:`covariate_model` fits, per item, a linear
mixed model ``rating ~ C(condition) + n_posture + n_mannerism + n_gesture + n_blink`` with a
random intercept per participant (statsmodels MixedLM, ML), returning every fixed effect -
so the condition effect is read with the amount of behaviour held fixed. Covariates that do not
vary (or are collinear with the conditions) are dropped and named in the ``note`` column.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from facelab.analysis.stats import _require
from facelab.errors import AnalysisError

__all__ = ["COVARIATE_COLUMNS", "LAYER_COUNTS", "clip_behaviour", "covariate_model"]

LAYER_COUNTS = ("n_posture", "n_mannerism", "n_gesture", "n_blink")
COVARIATE_COLUMNS = ("item", "term", "estimate", "se", "z", "p", "n_obs", "n_participants", "note")


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
) -> pd.DataFrame:
    """Per item, ``dv ~ C(condition) + covariates`` with a random intercept per subject.

    ``data``: one row per rating with ``stimulus_set, stimulus, condition``; ``counts``: from
    :func:`clip_behaviour`. Ratings of clips without a log get zero counts (no behaviour)."""
    _require(data, (dv, item, subject, condition, "stimulus_set", "stimulus"))
    import statsmodels.formula.api as smf

    keys = ["stimulus_set", "stimulus", "condition"]
    merged = data.merge(counts[[*keys, *covariates]], on=keys, how="left")
    merged[list(covariates)] = merged[list(covariates)].fillna(0)
    parts = []
    for it, part in merged.groupby(item, sort=True):
        part = part.dropna(subset=[dv])
        used, dropped = [], []
        for c in covariates:
            if part[c].nunique() < 2:
                dropped.append(f"{c} constant")
                continue
            # collinear with the condition means: the covariate adds nothing within conditions
            within = part[c] - part.groupby(condition)[c].transform("mean")
            if float(np.abs(within).max()) < 1e-12:
                dropped.append(f"{c} fixed by condition")
                continue
            used.append(c)
        formula = f"{dv} ~ C({condition})" + "".join(f" + {c}" for c in used)
        note = "; ".join(dropped)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                fit = smf.mixedlm(formula, part, groups=part[subject]).fit(reml=False)
            except (ValueError, np.linalg.LinAlgError) as exc:
                raise AnalysisError(f"item {it!r}: the covariate model failed ({exc})") from None
        for term in fit.fe_params.index:
            parts.append(
                {
                    "item": it,
                    "term": term,
                    "estimate": float(fit.fe_params[term]),
                    "se": float(fit.bse_fe[term]),
                    "z": float(fit.tvalues[term]),
                    "p": float(fit.pvalues[term]),
                    "n_obs": len(part),
                    "n_participants": part[subject].nunique(),
                    "note": note,
                }
            )
    return pd.DataFrame(parts, columns=list(COVARIATE_COLUMNS))
