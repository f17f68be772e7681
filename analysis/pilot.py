"""What a pilot should show before the study (and any study, per session): completion,
timing, dropped frames, the distribution of each item's ratings, and items that everyone
answers the same - tables for the report, notes for what needs a look."""

from __future__ import annotations

import pandas as pd

from facelab.analysis.integrity import DataCheck
from facelab.analysis.presentation import trials_shown

__all__ = ["below_chance", "pilot_items", "pilot_sessions", "same_rating_everywhere"]


def pilot_sessions(data: pd.DataFrame, check: DataCheck) -> pd.DataFrame:
    """One row per participant session: responses of those expected, minutes from the first
    to the last response, median response time (s), trials whose clip dropped frames and the
    frames dropped."""
    rows = []
    expected = check.sessions.set_index(["participant", "session"])["expected"]
    shown = trials_shown(data)
    for (pid, ses), g in data.groupby(["participant", "session"], sort=True):
        stamps = pd.to_datetime(g["timestamp"], errors="coerce", utc=True).dropna()
        mine = shown[(shown["participant"] == pid) & (shown["session"] == ses)]
        dropped = mine["dropped"].fillna(0)
        rows.append(
            {
                "participant": pid,
                "session": int(ses),
                "responses": len(g),
                "expected": int(expected.get((pid, ses), len(g))),
                "minutes": round((stamps.max() - stamps.min()).total_seconds() / 60, 2)
                if len(stamps) > 1
                else float("nan"),
                "median_rt_s": round(float(pd.to_numeric(g["rt_s"], errors="coerce").median()), 3),
                "trials_with_drops": int((dropped > 0).sum()),
                "frames_dropped": int(dropped.sum()),
            }
        )
    return pd.DataFrame(rows)


def pilot_items(vas: pd.DataFrame) -> tuple[pd.DataFrame, list[str]]:
    """Per VAS item and stimulus set: ratings, mean, SD, min, quartiles, max, and whether
    every rating is the same; with notes naming items without variation (a scale nobody
    used, or a question everyone answered alike, says nothing about the conditions)."""
    rows, notes = [], []
    if vas.empty:
        return pd.DataFrame(), notes
    for (item, sset), g in vas.groupby(["item", "stimulus_set"], sort=True):
        r = pd.to_numeric(g["rating"], errors="coerce").dropna()
        q = r.quantile([0.25, 0.5, 0.75]) if len(r) else pd.Series([float("nan")] * 3)
        same = len(r) > 1 and float(r.max() - r.min()) == 0.0
        rows.append(
            {
                "item": item,
                "stimulus_set": sset,
                "ratings": len(r),
                "mean": r.mean(),
                "sd": r.std(ddof=1) if len(r) > 1 else float("nan"),
                "min": r.min(),
                "q25": float(q.iloc[0]),
                "median": float(q.iloc[1]),
                "q75": float(q.iloc[2]),
                "max": r.max(),
                "all_the_same": same,
            }
        )
        if same:
            notes.append(
                f"{item} / {sset}: every one of {len(r)} ratings is {r.iloc[0]:g}; the item "
                "shows no variation to analyse (check the question and the scale)"
            )
    return pd.DataFrame(rows), notes


def same_rating_everywhere(vas: pd.DataFrame) -> list[str]:
    """Notes naming participants who gave one item the same rating on every trial (five or
    more): a scale left at its start, or a participant not looking - their ratings enter the
    tests as they are."""
    notes = []
    if vas.empty:
        return notes
    for (pid, item), g in vas.groupby(["participant", "item"], sort=True):
        r = pd.to_numeric(g["rating"], errors="coerce").dropna()
        if len(r) >= 5 and float(r.max() - r.min()) == 0.0:
            notes.append(f"participant {pid} rated {item} {r.iloc[0]:g} on every one of "
                         f"{len(r)} trials (a scale left untouched, or not looking?); the "
                         "ratings are analysed as given - leave them out with --exclude "
                         f"{pid} if they are not answers")  # fmt: skip
    return notes


def below_chance(scored: pd.DataFrame, *, task: str, chance: float) -> list[str]:
    """Notes naming participants right less often than guessing allows (``scored``:
    ``participant`` and boolean-like ``y`` per trial; one-sided binomial test at 0.01 against
    ``chance``): reversed keys or a misread question more likely than a threshold."""
    from scipy import stats as sps

    notes = []
    for pid, g in scored.groupby("participant", sort=True):
        n, k = len(g), int(g["y"].astype(float).sum())
        p = float(sps.binom.cdf(k, n, chance))
        if n >= 10 and p < 0.01:
            notes.append(f"task {task!r}: participant {pid} was right on {k} of {n} trials, "
                         f"below guessing ({chance:.0%}; binomial p = {p:.2g}) - reversed "
                         "keys or a misread question? Their answers are analysed as "
                         "given")  # fmt: skip
    return notes
