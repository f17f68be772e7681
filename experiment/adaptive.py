"""The staircases of a session: one per staircase block, rebuilt from the log on resume.

:class:`Staircases` is what the walker asks for a staircase trial's condition
(:meth:`Staircases.resolve`) and tells the answer (:meth:`Staircases.update`); each step is
appended (fsynced) to the session's ``_staircase.jsonl``. The rule is deterministic
(:mod:`facelab.staircase`), so on resume the state is rebuilt by replaying the block's logged
answers in trial order, and checked against the last step written to ``_staircase.jsonl``.
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
from facelab.staircase import UpDownStaircase

__all__ = ["Staircases", "new_staircase"]


def new_staircase(protocol: Protocol, block_id: str) -> UpDownStaircase:
    """The fresh staircase of a staircase block: its conditions, easiest first."""
    block = next(b for b in protocol.blocks if b.id == block_id)
    rule = block.staircase
    if rule is None:
        raise SessionError(f"block {block_id!r} has no staircase rule")
    conditions = sorted(
        protocol.block_conditions(block),
        key=lambda c: float(protocol.condition(c).level or 0.0),
        reverse=rule.easier == "higher",
    )
    return UpDownStaircase(
        grid=tuple(conditions),
        levels=tuple(float(protocol.condition(c).level or 0.0) for c in conditions),
        start=conditions.index(rule.start),
        up=rule.up,
        down=rule.down,
        step=rule.step,
    )


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
        self.state: dict[str, UpDownStaircase] = {
            b.id: new_staircase(protocol, b.id) for b in protocol.blocks if b.design == "staircase"
        }
        by_block: dict[str, list[Mapping[str, Any]]] = {}
        for row in logged:
            if row.get("block") in self.state and row.get("correct") is not None:
                by_block.setdefault(row["block"], []).append(row)
        for block_id, rows in by_block.items():
            rows.sort(key=lambda r: int(r["trial_index"]))
            try:
                self.state[block_id].replay((r["condition"], bool(r["correct"])) for r in rows)
            except ValueError as exc:
                raise SessionError(f"staircase of block {block_id!r}: {exc}") from None
        self._check_record()

    def _check_record(self) -> None:
        """The replayed state must continue where ``_staircase.jsonl`` says it stopped."""
        if self.record is None or not self.record.exists():
            return
        last: dict[str, dict[str, Any]] = {}
        for line in self.record.read_text(encoding="utf-8").splitlines():
            try:
                entry = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line cut off by a crash; the log rows are the truth
            last[entry.get("block")] = entry
        for block_id, entry in last.items():
            state = self.state.get(block_id)
            if state is None or entry.get("trials") != state.trials:
                continue  # the row was not logged before the crash: replay decides
            if entry.get("next_condition") != state.condition:
                raise SessionError(
                    f"staircase of block {block_id!r}: replaying the log gives "
                    f"{state.condition!r} next, {self.record.name} says "
                    f"{entry.get('next_condition')!r}; the session's files do not agree"
                )

    def resolve(self, trial: Trial) -> str:
        """The condition a staircase trial shows."""
        return self.state[trial.block].condition

    def update(self, trial: Trial, rows: list[dict[str, Any]]) -> None:
        """Apply a staircase trial's logged answer and record the step."""
        staircase = self.state[trial.block]
        (row,) = rows
        entry = staircase.record(
            trial_index=trial.trial_index, condition=trial.condition, correct=bool(row["correct"])
        )
        if self.record is not None:
            append_jsonl(self.record, {"block": trial.block, "trials": staircase.trials, **entry})
