"""The Simulator Sickness Questionnaire's tables (``presentation.ssq``): each questionnaire
scored as Kennedy et al. (1993) (:mod:`facelab.sickness_questionnaire`), summarised per
moment, and the change from before to after within participants.

* ``ssq`` - one row per participant, session and moment (before / after): the nausea,
  oculomotor, disorientation and total scores, their raw sums, and how many of the 16
  symptoms were answered (a questionnaire with any missing is not scored: NaN, and the
  report's notes name it).
* ``ssq_summary`` - per moment and for ``change`` (after minus before, participants with
  both): n, mean with its 95 % t interval, sd and median of each score.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from facelab import sickness_questionnaire as ssq
from facelab.analysis.stats import mean_t_interval

__all__ = ["SCORES", "is_ssq_row", "ssq_tables"]

#: the scores of one questionnaire, in the order the tables give them
SCORES = ("N", "O", "D", "total")


def is_ssq_row(data: pd.DataFrame) -> pd.Series:
    """Rows of the log that answer the questionnaire (screen ``ssq``)."""
    return data["screen"].fillna("") == "ssq"


def ssq_tables(rows: pd.DataFrame) -> tuple[dict[str, pd.DataFrame], list[str]]:
    """(``{"ssq", "ssq_summary"}``, notes) from the questionnaire's log rows (item
    ``ssq_<moment>_<symptom>``, response 0-3); empty without rows."""
    if rows.empty:
        return {}, []
    notes: list[str] = []
    scored = []
    for (pid, ses, moment), group in _by_questionnaire(rows):
        answers = {symptom: int(value) for symptom, value in group}
        base = {"participant": pid, "session": int(ses), "moment": moment,
                "symptoms_answered": len(answers)}  # fmt: skip
        if len(answers) < len(ssq.SYMPTOMS):
            notes.append(
                f"SSQ {moment} of {pid} (session {ses}): {len(answers)} of "
                f"{len(ssq.SYMPTOMS)} symptoms answered; not scored."
            )
            scored.append(base | dict.fromkeys((*SCORES, "N_raw", "O_raw", "D_raw"), np.nan))
            continue
        scored.append(base | ssq.scores(answers))
    table = pd.DataFrame(scored)
    table = table.sort_values(
        ["participant", "session", "moment"],
        key=lambda c: c.map({m: i for i, m in enumerate(ssq.MOMENTS)}) if c.name == "moment" else c,
    ).reset_index(drop=True)
    return {"ssq": table, "ssq_summary": _summary(table)}, notes


def _by_questionnaire(rows: pd.DataFrame):
    """((participant, session, moment), [(symptom, answer)]) per questionnaire; the last
    answer of a symptom counts (a resumed session never logs one twice)."""
    parsed = rows["item"].map(ssq.parse_item)
    frame = rows.assign(
        moment=parsed.map(lambda p: p[0] if p else None),
        symptom=parsed.map(lambda p: p[1] if p else None),
        value=pd.to_numeric(rows["response"], errors="coerce"),
    ).dropna(subset=["moment", "symptom", "value"])
    frame = frame.drop_duplicates(["participant", "session", "moment", "symptom"], keep="last")
    for key, group in frame.groupby(["participant", "session", "moment"], sort=True):
        yield key, list(zip(group["symptom"], group["value"], strict=True))


def _summary(table: pd.DataFrame) -> pd.DataFrame:
    out = []
    complete = table.dropna(subset=["total"])
    for moment in ssq.MOMENTS:
        out += _describe(complete[complete["moment"] == moment], moment)
    wide = complete.pivot_table(index=["participant", "session"], columns="moment",
                                values=list(SCORES))  # fmt: skip
    if {"before", "after"} <= set(complete["moment"]):
        change = pd.DataFrame({s: wide[(s, "after")] - wide[(s, "before")] for s in SCORES})
        out += _describe(change.dropna(), "change (after - before)")
    return pd.DataFrame(out)


def _describe(frame: pd.DataFrame, moment: str) -> list[dict[str, object]]:
    rows = []
    for score in SCORES:
        values = frame[score].to_numpy(dtype=float)
        mean, low, high = mean_t_interval(values)
        rows.append({
            "moment": moment, "score": score, "n": len(values), "mean": round(mean, 4),
            "ci_low": round(low, 4), "ci_high": round(high, 4),
            "sd": round(float(values.std(ddof=1)), 4) if len(values) > 1 else np.nan,
            "median": round(float(np.median(values)), 4) if len(values) else np.nan,
        })  # fmt: skip
    return rows
