"""Presentation quality as data: the frames each trial's clip dropped (``clip_frames_dropped``
of the session log, lab or online), summarised per condition, and trials over a threshold
left out of the analysis - with what was left out and why stated in the report."""

from __future__ import annotations

import pandas as pd

__all__ = ["QUALITY_COLUMNS", "exclude_dropped", "presentation_quality", "trials_shown"]

QUALITY_COLUMNS = (
    "stimulus_set",
    "condition",
    "trials",
    "trials_with_drops",
    "frames_dropped",
    "max_dropped",
    "excluded_trials",
)
_TRIAL = ["participant", "session", "trial_index"]


def trials_shown(data: pd.DataFrame) -> pd.DataFrame:
    """One row per shown trial (its responses share the clip): the keys, the stimulus set,
    the condition and the frames dropped (NaN when the log has no playback record)."""
    if data.empty:
        return pd.DataFrame(columns=[*_TRIAL, "stimulus_set", "condition", "dropped"])
    trials = data.drop_duplicates(_TRIAL)[[*_TRIAL, "stimulus_set", "condition"]].copy()
    trials["dropped"] = pd.to_numeric(
        data.drop_duplicates(_TRIAL)["clip_frames_dropped"], errors="coerce"
    ).to_numpy()
    return trials


def presentation_quality(
    data: pd.DataFrame, *, excluded: pd.DataFrame | None = None
) -> pd.DataFrame:
    """Per stimulus set and condition: trials shown, trials whose clip dropped frames, frames
    dropped in all and at most in one trial, and trials excluded (``excluded``: responses
    left out by :func:`exclude_dropped`)."""
    both = data if excluded is None or excluded.empty else pd.concat([data, excluded])
    trials = trials_shown(both)
    gone = trials_shown(excluded) if excluded is not None else None
    out_keys = set() if gone is None else set(map(tuple, gone[_TRIAL].to_numpy()))
    trials["excluded"] = [tuple(k) in out_keys for k in trials[_TRIAL].to_numpy()]
    rows = []
    for (sset, cond), part in trials.groupby(["stimulus_set", "condition"], sort=True):
        dropped = part["dropped"].fillna(0)
        rows.append(
            {
                "stimulus_set": sset,
                "condition": cond,
                "trials": len(part),
                "trials_with_drops": int((dropped > 0).sum()),
                "frames_dropped": int(dropped.sum()),
                "max_dropped": int(dropped.max()) if len(part) else 0,
                "excluded_trials": int(part["excluded"].sum()),
            }
        )
    return pd.DataFrame(rows, columns=list(QUALITY_COLUMNS))


def exclude_dropped(
    data: pd.DataFrame, *, max_dropped: int
) -> tuple[pd.DataFrame, pd.DataFrame, str | None]:
    """Responses to trials whose clip dropped more than ``max_dropped`` frames left out:
    ``(kept, excluded, note)``; the note (None when nothing was left out) says how many per
    condition and why."""
    dropped = pd.to_numeric(data["clip_frames_dropped"], errors="coerce").fillna(0)
    over = dropped > max_dropped
    kept, excluded = data[~over].reset_index(drop=True), data[over].reset_index(drop=True)
    if excluded.empty:
        return kept, excluded, None
    per = trials_shown(excluded).groupby("condition").size()
    listed = ", ".join(f"{c}: {n}" for c, n in per.items())
    note = (
        f"excluded {len(excluded)} responses of {int(per.sum())} trials whose clip dropped more "
        f"than {max_dropped} frames (--max-dropped-frames), per condition {listed}"
    )
    return kept, excluded, note
