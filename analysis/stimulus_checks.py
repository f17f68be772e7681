"""The clips' stimulus checks (``stimulus_checks.csv``) as a section of the analysis report.

The checks themselves run where the clips are made (``facelab check`` / ``render``); the report
states what they found for the clips the participants saw: per check and condition how many
measures passed, failed, were accepted by name or only warned, and every failure and warning
row in full, so a reader sees an accepted failure beside the ratings it may explain.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from facelab.formats import STIMULUS_CHECK_COLUMNS, STIMULUS_CHECKS_NAME, read_stimulus_checks

__all__ = ["StimulusCheckSummary", "summarize_stimulus_checks"]


@dataclass(frozen=True)
class StimulusCheckSummary:
    """``summary``: one sentence; ``table``: per check x condition counts; ``problems``:
    the failed (accepted or not) and warning rows as written."""

    summary: str
    table: pd.DataFrame
    problems: pd.DataFrame


def summarize_stimulus_checks(clips: Path) -> StimulusCheckSummary | None:
    """The summary of ``clips/stimulus_checks.csv``, or None when the clips were not checked."""
    rows = read_stimulus_checks(clips)
    if rows is None:
        return None
    frame = pd.DataFrame(rows, columns=list(STIMULUS_CHECK_COLUMNS))
    judged = frame[frame["passed"] != ""]
    failed = judged["passed"] == "false"
    accepted = failed & (judged["accepted"] == "true")
    error = judged["severity"] == "error"
    kinds = pd.DataFrame(
        {
            "check": judged["check"],
            "condition": judged["condition"],
            "measures": 1,
            "passed": (~failed).astype(int),
            "failed": (failed & error & ~accepted).astype(int),
            "accepted": (accepted & error).astype(int),
            "warnings": (failed & ~error).astype(int),
        }
    )
    table = kinds.groupby(["check", "condition"], sort=False, as_index=False).sum()
    first = {name: k for k, name in enumerate(dict.fromkeys(judged["check"]))}  # as measured
    table = table.sort_values("check", key=lambda c: c.map(first), kind="stable")
    table = table.reset_index(drop=True)
    problems = frame[(frame["passed"] == "false")][
        ["clip", "condition", "check", "measure", "value", "threshold", "severity", "accepted",
         "note"]
    ].reset_index(drop=True)  # fmt: skip
    names = frame["clip"]
    clips_n = names[(names != "") & ~names.str.contains("~", regex=False)].nunique()  # a~b: pairs
    n_failed, n_accepted = int(table["failed"].sum()), int(table["accepted"].sum())
    summary = (
        f"{clips_n} clips in {clips / STIMULUS_CHECKS_NAME}: {len(judged)} judged measures, "
        f"{n_failed} failed, {n_accepted} failed and accepted by name, "
        f"{int(table['warnings'].sum())} warnings."
    )
    if n_accepted:
        names = sorted(set(problems.loc[problems["accepted"] == "true", "check"]))
        summary += f" Accepted checks: {', '.join(names)} (the rows below say what they measured)."
    return StimulusCheckSummary(summary=summary, table=table, problems=problems)
