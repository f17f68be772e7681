"""The Simulator Sickness Questionnaire's tables (``presentation.ssq``): each questionnaire
scored as Kennedy et al. (1993) (:mod:`facelab.sickness_questionnaire`), summarised per
moment, and the change from before to after within participants.

* ``ssq`` - one row per participant, session and moment (before / after): the nausea,
  oculomotor, disorientation and total scores, their raw sums, and how many of the 16
  symptoms were answered (a questionnaire with any missing is not scored: NaN, and the
  report's notes name it).
* ``ssq_summary`` - per moment the protocol asks for, and for ``change`` (after minus before,
  participants with both): n participants (a participant's sessions are averaged first),
  mean with its 95 % t interval, sd, median and quartiles of each score; for the change also
  the Wilcoxon signed-rank test's p (scores pile up at 0 and are skewed, so the t interval
  alone can mislead; pairs with no change are dropped, as Wilcoxon's test does).
* ``ssq_symptoms`` - per moment and symptom: how many answered none, slight, moderate and
  severe, and the mean answer.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd
from scipy import stats

from facelab import sickness_questionnaire as ssq
from facelab.analysis.stats import mean_t_interval

__all__ = ["SCORES", "is_ssq_row", "ssq_tables"]

#: the scores of one questionnaire, in the order the tables give them
SCORES = ("N", "O", "D", "total")


def is_ssq_row(data: pd.DataFrame) -> pd.Series:
    """Rows of the log that answer the questionnaire (screen ``ssq``)."""
    return data["screen"].fillna("") == "ssq"


def ssq_tables(
    rows: pd.DataFrame, *, moments: Sequence[str] = ssq.MOMENTS
) -> tuple[dict[str, pd.DataFrame], list[str]]:
    """(``{"ssq", "ssq_summary", "ssq_symptoms"}``, notes) from the questionnaire's log rows
    (item ``ssq_<moment>_<symptom>``, response 0-3) of the ``moments`` asked for; empty
    without rows."""
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
    summary = _summary(table, moments=[m for m in ssq.MOMENTS if m in moments])
    return {"ssq": table, "ssq_summary": summary, "ssq_symptoms": _symptoms(rows)}, notes


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


def _summary(table: pd.DataFrame, *, moments: Sequence[str]) -> pd.DataFrame:
    complete = table.dropna(subset=["total"])
    # one value per participant and moment: their sessions averaged
    per = complete.groupby(["participant", "moment"], sort=True)[list(SCORES)].mean()
    out = []
    for moment in moments:
        out += _describe(per.xs(moment, level="moment") if moment in set(complete["moment"])
                         else per.iloc[:0], moment)  # fmt: skip
    if {"before", "after"} <= set(moments) and {"before", "after"} <= set(complete["moment"]):
        wide = per.unstack("moment")
        change = pd.DataFrame({s: wide[(s, "after")] - wide[(s, "before")] for s in SCORES})
        out += _describe(change.dropna(), "change (after - before)", test=True)
    return pd.DataFrame(out)


def _describe(frame: pd.DataFrame, moment: str, *, test: bool = False) -> list[dict[str, object]]:
    rows = []
    for score in SCORES:
        values = frame[score].to_numpy(dtype=float)
        # scores cannot go below 0; their change (after - before) can
        mean, low, high = mean_t_interval(values, bounds=None if test else (0.0, np.inf))
        q25, median, q75 = (np.percentile(values, (25, 50, 75)) if len(values)
                            else (np.nan, np.nan, np.nan))  # fmt: skip
        row = {
            "moment": moment, "score": score, "n": len(values), "mean": round(mean, 4),
            "ci_low": round(low, 4), "ci_high": round(high, 4),
            "sd": round(float(values.std(ddof=1)), 4) if len(values) > 1 else np.nan,
            "median": round(float(median), 4), "q25": round(float(q25), 4),
            "q75": round(float(q75), 4),
        }  # fmt: skip
        if test:
            moved = values[values != 0]
            row["wilcoxon_p"] = (round(float(stats.wilcoxon(moved).pvalue), 6)
                                 if len(moved) else np.nan)  # fmt: skip
        rows.append(row)
    return rows


def _symptoms(rows: pd.DataFrame) -> pd.DataFrame:
    out = []
    answers = dict(_by_questionnaire(rows))
    for moment in ssq.MOMENTS:
        given = [dict(a) for (_, _, m), a in answers.items() if m == moment]
        if not given:
            continue
        for symptom in ssq.SYMPTOMS:
            values = [int(a[symptom.id]) for a in given if symptom.id in a]
            counts = {f"n_{ssq.ANSWERS[v][1]['en'].lower()}": values.count(v) for v in range(4)}
            mean = round(float(np.mean(values)), 4) if values else np.nan
            out.append({"moment": moment, "symptom": symptom.id, "n": len(values), **counts,
                        "mean": mean})  # fmt: skip
    return pd.DataFrame(out)
