"""The live conversation's rows (``presentation.conversation``, issue 53.4): outside the trial
design, checked as the session wrote them, and tabulated.

A session with a conversation logs it on its own trial (index 0, block ``conversation``,
stimulus ``partner``, the conversation's condition): item ``conversation`` on screen
``conversation`` (``response`` how it ended - ``time`` or ``talker`` -, ``score`` the turns
the participant's page was sent, ``rt_s`` how long it lasted, s), then one VAS row per item
asked about the partner.

* ``conversation`` - one row per participant and session: condition, ended, seconds, turns,
  and the rating of each partner item (NaN when not answered).
* ``conversation_summary`` - per partner item: n participants (a participant's sessions are
  averaged first), mean with its 95 % t interval, sd, median and quartiles.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from facelab.analysis.stats import mean_t_interval
from facelab.errors import AnalysisError
from facelab.protocol import Protocol

__all__ = [
    "BLOCK",
    "check_conversation_rows",
    "conversation_items",
    "conversation_tables",
    "is_conversation_row",
]

BLOCK = "conversation"  #: the block of the conversation's rows in the logs


def conversation_items(protocol: Protocol) -> list[str]:
    """The log items a session with the protocol's conversation writes: ``conversation``
    and the partner items (none without a conversation)."""
    conv = protocol.presentation.conversation
    if conv is None:
        return []
    return ["conversation"] + [i.id for i in protocol.items
                               if conv.items is None or i.id in conv.items]  # fmt: skip


def is_conversation_row(data: pd.DataFrame, protocol: Protocol) -> pd.Series:
    """Rows of the log on the conversation's trial (block ``conversation``) of a protocol
    with one (without one, a block may have that id)."""
    if protocol.presentation.conversation is None:
        return pd.Series(False, index=data.index)
    return data["block"].astype(str) == BLOCK


def check_conversation_rows(data: pd.DataFrame, protocol: Protocol) -> None:
    """The conversation's rows are what a session writes - refused naming the first that is
    not (an edited log, or rows from another protocol)."""
    conv = protocol.presentation.conversation
    talks = data["screen"].astype(str) == "conversation"
    if conv is None:
        if talks.any():
            first = data[talks].iloc[0]
            raise AnalysisError(f"{first.get('source', 'the logs')}: participant "
                                f"{first['participant']}: rows of a live conversation, but the "
                                f"protocol {protocol.study.id!r} has none "
                                "(presentation.conversation); pass the protocol these sessions "
                                "ran")  # fmt: skip
        return
    rows = data[is_conversation_row(data, protocol) | talks]
    if rows.empty:
        return
    items = set(conversation_items(protocol))
    for _, row in rows.iterrows():
        where = (f"{row.get('source', 'the logs')}: participant {row['participant']} "
                 f"item {row['item']!r}")
        expected = {"trial_index": 0, "block": BLOCK, "stimulus": "partner",
                    "condition": conv.condition}  # fmt: skip
        for column, value in expected.items():
            if str(row[column]) != str(value):
                raise AnalysisError(f"{where}: {column} is {row[column]!r}, expected {value!r} "
                                    "(the conversation's trial); the log was edited")  # fmt: skip
        if row["item"] not in items:
            raise AnalysisError(f"{where}: not an item of the conversation "
                                f"({', '.join(sorted(items))})")  # fmt: skip
        screen = "conversation" if row["item"] == "conversation" else "vas"
        if str(row["screen"]) != screen:
            raise AnalysisError(f"{where}: screen {row['screen']!r}, expected {screen!r}; the "
                                "log was edited")  # fmt: skip
        if screen == "conversation" and str(row["response"]) not in ("time", "talker"):
            raise AnalysisError(f"{where}: response {row['response']!r}, expected 'time' or "
                                "'talker' (how the conversation ended)")  # fmt: skip
        numbers = ("score", "rt_s") if screen == "conversation" else ("rating",)
        for column in numbers:
            value = pd.to_numeric(pd.Series([row[column]]), errors="coerce").iloc[0]
            if not np.isfinite(value) or value < 0:
                raise AnalysisError(f"{where}: {column} is {row[column]!r}, expected a number "
                                    "from 0; the log was edited")  # fmt: skip


def conversation_tables(
    rows: pd.DataFrame, protocol: Protocol
) -> tuple[dict[str, pd.DataFrame], list[str]]:
    """(``{"conversation", "conversation_summary"}``, notes) from the conversation's log rows;
    a note and no tables when the protocol has a conversation but the logs none."""
    conv = protocol.presentation.conversation
    if conv is None:
        return {}, []
    if rows.empty:
        return {}, ["the protocol has a live conversation (presentation.conversation), but "
                    "the logs have no rows of it"]  # fmt: skip
    partner = conversation_items(protocol)[1:]
    out = []
    for (pid, ses), group in rows.groupby(["participant", "session"], sort=True):
        talk = group[group["item"] == "conversation"]
        record: dict[str, object] = {
            "participant": pid,
            "session": int(ses),
            "condition": conv.condition,
            "ended": talk["response"].iloc[0] if len(talk) else None,
            "seconds": round(float(talk["rt_s"].iloc[0]), 3) if len(talk) else np.nan,
            "turns": int(talk["score"].iloc[0]) if len(talk) else None,
        }
        for item in partner:
            answer = group.loc[group["item"] == item, "rating"]
            record[item] = float(answer.iloc[0]) if len(answer) else np.nan
        out.append(record)
    table = pd.DataFrame(out)
    notes = []
    short = table[table["ended"] == "talker"]
    if len(short):
        notes.append(f"{len(short)} conversation(s) were ended by the talker before their "
                     f"{conv.minutes:g} minutes (conversation.csv: ended)")  # fmt: skip
    summary = []
    for item in partner:
        per = table.groupby("participant")[item].mean().dropna().to_numpy(dtype=float)
        scale = next(i.range for i in protocol.items if i.id == item)
        mean, lo, hi = mean_t_interval(per, bounds=(min(scale), max(scale)))
        q1, median, q3 = np.percentile(per, [25, 50, 75]) if len(per) else (np.nan,) * 3
        summary.append({"item": item, "condition": conv.condition, "n": len(per),
                        "mean": mean, "ci_low": lo, "ci_high": hi,
                        "sd": float(per.std(ddof=1)) if len(per) > 1 else np.nan,
                        "median": median, "q1": q1, "q3": q3})  # fmt: skip
    tables = {"conversation": table}
    if summary:
        tables["conversation_summary"] = pd.DataFrame(summary).round(6)
    return tables, notes
