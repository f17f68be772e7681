"""The staircases of a session: one per staircase block, rebuilt from the log on resume.

:class:`Staircases` is what the walker asks for a staircase trial's condition
(:meth:`Staircases.resolve`) and tells the answer (:meth:`Staircases.update`); each step is
appended (fsynced) to the session's ``_staircase.jsonl``. The rule is deterministic
(:mod:`facelab.staircase`), so on resume the state is rebuilt by replaying the block's logged
answers in trial order and checked against every step written to ``_staircase.jsonl``; a
step whose answer was logged just before a crash is written then (``"rebuilt": true``).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from facelab.design import Trial
from facelab.errors import SessionError
from facelab.protocol import Protocol
from facelab.sessionlog import append_jsonl
from facelab.staircase import Staircase, new_staircase

__all__ = ["Staircases"]


class Staircases:
    """Every staircase of one session."""

    def __init__(
        self,
        protocol: Protocol,
        *,
        logged: Iterable[Mapping[str, Any]] = (),
        record: Path | None = None,
    ):
        self.protocol = protocol
        self.record = record
        self.state: dict[str, Staircase] = {
            b.id: new_staircase(protocol, b.id) for b in protocol.blocks if b.design == "staircase"
        }
        by_block: dict[str, list[Mapping[str, Any]]] = {}
        for row in logged:
            if row.get("block") in self.state and row.get("correct") is not None:
                by_block.setdefault(row["block"], []).append(row)
        written = self._written()
        for block_id, rows in by_block.items():
            rows.sort(key=lambda r: int(r["trial_index"]))
            try:
                steps = self.state[block_id].replay(
                    (int(r["trial_index"]), r["condition"], bool(r["correct"]), r.get("score"))
                    for r in rows
                )
            except ValueError as exc:
                raise SessionError(f"staircase of block {block_id!r}: {exc}") from None
            for step in steps:
                key = (block_id, step["trial_index"])
                if key in written and written[key].get("next_condition") != step["next_condition"]:
                    raise SessionError(
                        f"staircase of block {block_id!r}: replaying the log gives "
                        f"{step['next_condition']!r} after trial {step['trial_index']}, "
                        f"{self.record.name if self.record else ''} says "
                        f"{written[key].get('next_condition')!r}; the session's files disagree"
                    )
                if key not in written and self.record is not None:
                    # the answer was logged but the process ended before its step was written
                    append_jsonl(self.record, {"block": block_id, **step, "rebuilt": True})

    def _written(self) -> dict[tuple[str, int], dict[str, Any]]:
        """Steps already in ``_staircase.jsonl`` by (block, trial index)."""
        if self.record is None or not self.record.exists():
            return {}
        out: dict[tuple[str, int], dict[str, Any]] = {}
        for line in self.record.read_text(encoding="utf-8").split("\n"):
            if not line.strip():
                continue
            try:
                entry = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line cut off by a crash; the log rows are the truth
            out[(entry.get("block"), int(entry.get("trial_index", -1)))] = entry
        return out

    def resolve(self, trial: Trial) -> str:
        """The condition a staircase trial shows."""
        return self.state[trial.block].condition

    def update(self, trial: Trial, rows: list[dict[str, Any]]) -> None:
        """Apply a staircase trial's logged answer and record the step."""
        staircase = self.state[trial.block]
        (row,) = rows
        entry = staircase.record(
            trial_index=trial.trial_index, condition=trial.condition,
            correct=bool(row["correct"]), score=row.get("score"),
        )  # fmt: skip
        if self.record is not None:
            append_jsonl(self.record, {"block": trial.block, **entry})
