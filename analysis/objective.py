"""Objective comparison with a reference condition (``analysis: {reference: CONDITION}``, e.g.
a captured human): how far every other condition's motion is from the reference's, per
stimulus, in ``objective.csv``, and how those distances go with the ratings.

Measures (tidy rows: ``stimulus_set, stimulus, condition, reference, measure, channel, value,
unit``), from what the clips were drawn with (``<clip>.track.bin``) and what the face tracker
saw in them (``face_tracking.csv``, written by the stimulus checks):

* ``correlation`` and ``rmse`` per mouth channel (``jaw*``, ``mouth*``, ``viseme_*``) both
  tracks drive, frame by frame (weights 0-1);
* ``lag_ms``: the lag of the condition's tracked lip aperture behind the reference's that
  maximises their cross-correlation (within ±500 ms; positive: the condition is later) -
  method-independent, so a viseme method and an ARKit capture are comparable;
* ``aperture_correlation``, ``aperture_error`` (mean |difference| in face heights) and the same
  for ``width``, over frames where both faces were found.

Pure pandas/numpy on the files; :func:`objective_vs_ratings` relates them to the VAS ratings
per condition and per (condition, stimulus) cell, and :func:`objective_covariate` takes a
tracked measure as a per-stimulus covariate of the ratings: ``rating ~ C(condition) + x +
(1 | participant)`` per item, where x is the measure of the trial's (condition, stimulus) clip
(centred), fitted by REML (statsmodels MixedLM). Its slope says whether, within a condition,
stimuli closer to the reference are rated differently - what the condition means alone
cannot tell.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from facelab.errors import AnalysisError, FormatError
from facelab.formats import read_face_tracking_rows, read_manifest, read_track
from facelab.protocol import Protocol

__all__ = [
    "COVARIATE_COLUMNS",
    "OBJECTIVE_COLUMNS",
    "objective_covariate",
    "objective_distances",
    "objective_vs_ratings",
]

OBJECTIVE_COLUMNS = ("stimulus_set", "stimulus", "condition", "reference", "measure", "channel",
                     "value", "unit")  # fmt: skip
_MOUTH = ("jaw", "mouth", "viseme_")
_MAX_LAG_S = 0.5


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    if len(a) < 3 or np.std(a) < 1e-9 or np.std(b) < 1e-9:
        return float("nan")
    return float(np.corrcoef(a, b)[0, 1])


def _lag_frames(a: np.ndarray, b: np.ndarray, max_lag: int) -> int | None:
    """The lag (frames) of ``b`` behind ``a`` maximising their correlation."""
    best, best_r = None, -np.inf
    for lag in range(-max_lag, max_lag + 1):
        lo, hi = max(0, -lag), min(len(a), len(b) - lag)
        if hi - lo < 10:
            continue
        r = _corr(a[lo:hi], b[lo + lag : hi + lag])
        if np.isfinite(r) and r > best_r:
            best, best_r = lag, r
    return best


def _tracking(clips_dir: Path) -> dict[str, pd.DataFrame]:
    rows = read_face_tracking_rows(clips_dir)
    if not rows:
        return {}
    df = pd.DataFrame(rows)
    for col in ("frame", "time_s", "detection", "aperture", "width", "face_height"):
        df[col] = pd.to_numeric(df[col], errors="coerce")
    return {clip: g.sort_values("frame") for clip, g in df.groupby("clip")}


def objective_distances(protocol: Protocol, *, clips_dir: Path) -> pd.DataFrame:
    """``objective.csv``'s rows (see the module docstring); empty when the protocol names no
    reference. AnalysisError when the reference's clips or their tracks are missing."""
    ref = protocol.analysis.reference
    if ref is None:
        return pd.DataFrame(columns=list(OBJECTIVE_COLUMNS))
    try:
        manifest = read_manifest(clips_dir, need=("clip_id", "stimulus_set", "stimulus",
                                                  "condition", "fps", "track_file"))  # fmt: skip
    except FormatError as exc:
        raise AnalysisError(f"analysis.reference {ref!r}: {exc}") from None
    tracking = _tracking(clips_dir)
    by_stim: dict[tuple[str, str], dict[str, dict]] = {}
    for m in manifest:
        by_stim.setdefault((m["stimulus_set"], m["stimulus"]), {})[m["condition"]] = m
    rows: list[dict] = []
    for (set_id, stim_id), clips in by_stim.items():
        if ref not in clips:
            continue
        ref_track = read_track(clips_dir / clips[ref]["track_file"])
        for cond, m in clips.items():
            if cond == ref:
                continue
            base = {"stimulus_set": set_id, "stimulus": stim_id, "condition": cond,
                    "reference": ref}  # fmt: skip

            def add(measure: str, channel: str, value: float, unit: str = "") -> None:
                rows.append({**base, "measure": measure, "channel": channel,  # noqa: B023
                             "value": value, "unit": unit})  # fmt: skip

            track = read_track(clips_dir / m["track_file"])
            n = min(len(track.values), len(ref_track.values))
            shared = [c for c in track.names if c.startswith(_MOUTH) and c in ref_track.names]
            for name in shared:
                a, b = ref_track.channel(name)[:n], track.channel(name)[:n]
                if np.ptp(a) < 1e-6 and np.ptp(b) < 1e-6:
                    continue  # neither moves it
                add("correlation", name, _corr(a, b))
                add("rmse", name, float(np.sqrt(np.mean((a - b) ** 2))), "weight")
            ta, tb = tracking.get(clips[ref]["clip_id"]), tracking.get(m["clip_id"])
            if ta is None or tb is None:
                continue
            k = min(len(ta), len(tb))
            fa, fb = ta.iloc[:k], tb.iloc[:k]
            seen = (fa["detection"].to_numpy() > 0.1) & (fb["detection"].to_numpy() > 0.1)
            seen &= np.isfinite(fa["aperture"].to_numpy()) & np.isfinite(fb["aperture"].to_numpy())
            if seen.sum() < 10:
                continue
            for what in ("aperture", "width"):
                a, b = fa[what].to_numpy()[seen], fb[what].to_numpy()[seen]
                add(f"{what}_correlation", "tracked", _corr(a, b))
                add(f"{what}_error", "tracked", float(np.mean(np.abs(a - b))), "face height")
            fps = float(m["fps"])
            a = np.nan_to_num(fa["aperture"].to_numpy(), nan=0.0)
            b = np.nan_to_num(fb["aperture"].to_numpy(), nan=0.0)
            lag = _lag_frames(a, b, round(_MAX_LAG_S * fps))
            if lag is not None:
                add("lag_ms", "tracked", 1000.0 * lag / fps, "ms")
    return pd.DataFrame(rows, columns=list(OBJECTIVE_COLUMNS))


def objective_vs_ratings(objective: pd.DataFrame, vas: pd.DataFrame) -> pd.DataFrame:
    """Per item, condition and stimulus (each a row; and per condition over stimuli, stimulus
    ``all``): the mean rating and its count beside the condition's tracked aperture
    correlation and error and lag against the reference. Empty without both."""
    if objective.empty or vas.empty or "rating" not in vas:
        return pd.DataFrame()
    wide = objective[objective["channel"] == "tracked"].pivot_table(
        index=["stimulus_set", "stimulus", "condition"], columns="measure", values="value"
    )
    keep = [c for c in ("aperture_correlation", "aperture_error", "lag_ms") if c in wide]
    if not keep:
        return pd.DataFrame()
    wide = wide[keep].reset_index()
    cells = (
        vas.groupby(["item", "condition", "stimulus_set", "stimulus"], observed=True)["rating"]
        .agg(mean_rating="mean", n_ratings="count")
        .reset_index()
    )
    per_stim = cells.merge(wide, on=["condition", "stimulus_set", "stimulus"], how="inner")
    if per_stim.empty:
        return pd.DataFrame()
    per_cond = per_stim.groupby(["item", "condition"], observed=True).agg(
        mean_rating=("mean_rating", "mean"), n_ratings=("n_ratings", "sum"),
        **{c: (c, "mean") for c in keep},
    ).reset_index()  # fmt: skip
    per_cond["stimulus_set"], per_cond["stimulus"] = "all", "all"
    out = pd.concat([per_cond, per_stim], ignore_index=True)
    cols = ["item", "condition", "stimulus_set", "stimulus", "mean_rating", "n_ratings", *keep]
    return out[cols].round(6)


#: the columns of :func:`objective_covariate`
COVARIATE_COLUMNS = ("item", "measure", "estimate", "se", "ci_low", "ci_high", "p", "n_ratings",
                     "n_participants", "n_cells", "x_sd", "procedure", "note")  # fmt: skip


def objective_covariate(
    objective: pd.DataFrame,
    vas: pd.DataFrame,
    *,
    measures: tuple[str, ...] = ("aperture_correlation", "aperture_error"),
) -> pd.DataFrame:
    """Per VAS item and tracked measure: the slope of the rating on the measure of the rated
    clip, with the condition as a factor and a random intercept per participant (REML;
    Wald 95 % interval and p). Rows whose (condition, stimulus) clip has no measure (the
    reference itself) are left out. A model that cannot be estimated - the measure does not
    vary within a condition, fewer than two participants - is a row with ``procedure``
    ``not estimable`` and the reason in ``note``. Empty without both tables."""
    if objective.empty or vas.empty or "rating" not in vas:
        return pd.DataFrame(columns=list(COVARIATE_COLUMNS))
    tracked = objective[(objective["channel"] == "tracked")
                        & objective["measure"].isin(measures)]  # fmt: skip
    if tracked.empty:
        return pd.DataFrame(columns=list(COVARIATE_COLUMNS))
    wide = tracked.pivot_table(index=["stimulus_set", "stimulus", "condition"],
                               columns="measure", values="value").reset_index()  # fmt: skip
    rows = []
    for item, ratings in vas.groupby("item", observed=True, sort=False):
        data = ratings.merge(wide, on=["condition", "stimulus_set", "stimulus"], how="inner")
        for measure in (m for m in measures if m in wide):
            frame = data[["participant", "condition", "stimulus", "rating", measure]].dropna()
            rows.append({"item": item, "measure": measure,
                         **_covariate_fit(frame, measure)})  # fmt: skip
    out = pd.DataFrame(rows, columns=list(COVARIATE_COLUMNS))
    return out.round(6)


def _covariate_fit(frame: pd.DataFrame, measure: str) -> dict[str, object]:
    """The covariate's slope in ``rating ~ C(condition) + x + (1 | participant)``."""
    import warnings

    from scipy import stats

    n_cells = int(frame[["condition", "stimulus"]].drop_duplicates().shape[0])
    base = {"n_ratings": len(frame), "n_participants": int(frame["participant"].nunique()),
            "n_cells": n_cells}  # fmt: skip
    x = frame[measure].astype(float)
    within = x - x.groupby(frame["condition"]).transform("mean")
    base["x_sd"] = float(within.std(ddof=0)) if len(frame) else float("nan")
    reason = None
    if base["n_participants"] < 2:
        reason = "fewer than 2 participants"
    elif not np.isfinite(base["x_sd"]) or base["x_sd"] < 1e-9:
        reason = (f"{measure} does not vary between the stimuli of a condition (one stimulus "
                  "per condition, or identical clips)")  # fmt: skip
    if reason is not None:
        return {**base, "procedure": "not estimable", "note": reason}
    import statsmodels.formula.api as smf

    data = pd.DataFrame({"y": frame["rating"].astype(float), "x": x - x.mean(),
                         "c": frame["condition"].astype(str),
                         "s": frame["participant"].astype(str)})  # fmt: skip
    formula = "y ~ C(c) + x" if data["c"].nunique() > 1 else "y ~ x"
    fit = None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # boundary fits (no participant variance) are valid
        for method in ("lbfgs", "bfgs", "powell"):
            try:
                candidate = smf.mixedlm(formula, data, groups="s").fit(
                    reml=True, method=method, maxiter=2000
                )
            except (np.linalg.LinAlgError, ValueError):
                continue
            if candidate.converged and np.isfinite(candidate.bse.get("x", np.nan)):
                fit = candidate
                break
    if fit is None:
        return {**base, "procedure": "not estimable", "note": "the mixed model did not converge"}
    est, se = float(fit.fe_params["x"]), float(fit.bse["x"])
    z = est / se if se > 0 else float("nan")
    return {**base, "estimate": est, "se": se, "ci_low": est - 1.959964 * se,
            "ci_high": est + 1.959964 * se, "p": float(2 * stats.norm.sf(abs(z))),
            "procedure": f"mixed model {formula} + (1 | participant), REML, Wald",
            "note": f"rating change per unit of {measure}, within conditions"}  # fmt: skip
