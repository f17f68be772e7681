"""Adaptive staircases over a pre-rendered grid of levels. Pure and deterministic.

A transformed up-down rule (Levitt, 1971): after ``down`` correct answers in a row the level
moves ``step`` grid steps towards harder, after ``up`` wrong answers in a row ``step`` steps
towards easier; it stays inside the grid. 1-up-2-down converges on 70.7 % correct, 1-up-3-down
on 79.4 %. The grid is the block's conditions ordered by their ``level``; which end is easier
is the protocol's ``easier`` (``higher``: a larger level is easier to get right).

The rule holds no randomness, so its state after any prefix of answers is a function of
those answers: a resumed session rebuilds it by replaying the logged rows of its block
(:meth:`UpDownStaircase.replay`) and continues the same staircase. Every step is also written
to the session's ``_staircase.jsonl`` (:meth:`UpDownStaircase.record`) so it can be read
without facelab, and the replay is checked against it.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from facelab.protocol import Protocol

__all__ = ["UpDownStaircase", "convergence_probability", "new_staircase", "reversal_threshold"]


def convergence_probability(*, up: int, down: int) -> float:
    """P(correct) an up/down rule converges on: ``p**down = 1/2`` for 1-up-n-down."""
    if up != 1:
        # general transformed rule: p_down = p**down equals p_up = 1 - (1 - p)**up; solve
        grid = np.linspace(1e-6, 1 - 1e-6, 200_001)
        gap = np.abs(grid**down - (1 - (1 - grid) ** up))
        return float(grid[int(np.argmin(gap))])
    return float(0.5 ** (1.0 / down))


@dataclass
class UpDownStaircase:
    """State of one staircase. ``grid`` is ordered from easiest to hardest."""

    grid: tuple[str, ...]
    levels: tuple[float, ...]
    start: int
    up: int = 1
    down: int = 2
    step: int = 1
    index: int = -1
    correct_run: int = 0
    wrong_run: int = 0
    direction: int = 0  # +1 last move harder, -1 easier, 0 none yet
    trials: int = 0
    reversals: list[float] = field(default_factory=list)

    def __post_init__(self) -> None:
        if len(self.grid) != len(self.levels) or len(self.grid) < 2:
            raise ValueError("a staircase needs two or more grid points, each with a level")
        if self.index < 0:
            self.index = self.start

    @property
    def condition(self) -> str:
        """The condition to show next."""
        return self.grid[self.index]

    @property
    def level(self) -> float:
        return self.levels[self.index]

    def update(self, correct: bool) -> bool:
        """Apply one answer at the current level; returns whether the direction reversed."""
        self.trials += 1
        move = 0
        if correct:
            self.correct_run += 1
            self.wrong_run = 0
            if self.correct_run >= self.down:
                move, self.correct_run = +1, 0
        else:
            self.wrong_run += 1
            self.correct_run = 0
            if self.wrong_run >= self.up:
                move, self.wrong_run = -1, 0
        reversal = False
        if move:
            if self.direction and move != self.direction:
                reversal = True
                self.reversals.append(self.level)
            self.direction = move
            self.index = int(np.clip(self.index + move * self.step, 0, len(self.grid) - 1))
        return reversal

    def record(self, *, trial_index: int, condition: str, correct: bool) -> dict[str, Any]:
        """Apply an answer and return the line for ``_staircase.jsonl``."""
        level = self.levels[self.grid.index(condition)]
        reversal = self.update(correct)
        return {
            "trial_index": trial_index,
            "condition": condition,
            "level": level,
            "correct": bool(correct),
            "reversal": reversal,
            "reversals": len(self.reversals),
            "next_condition": self.condition,
            "next_level": self.level,
            "trials": self.trials,
        }

    def replay(self, answers: Iterable[tuple[int, str, bool]]) -> list[dict[str, Any]]:
        """Apply logged (trial index, condition, correct) answers in order, checking each was
        the one due; returns the :meth:`record` of every step."""
        steps = []
        for trial_index, condition, correct in answers:
            if condition != self.condition:
                raise ValueError(
                    f"the log shows condition {condition!r} at trial {trial_index} where the "
                    f"staircase was at {self.condition!r}: the log does not belong to this "
                    "staircase"
                )
            steps.append(self.record(trial_index=trial_index, condition=condition, correct=correct))
        return steps


def new_staircase(protocol: Protocol, block_id: str) -> UpDownStaircase:
    """The fresh staircase of a staircase block: its conditions, easiest first."""
    block = next(b for b in protocol.blocks if b.id == block_id)
    rule = block.staircase
    if rule is None:
        raise ValueError(f"block {block_id!r} has no staircase rule")
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


def reversal_threshold(reversal_levels: Sequence[float], *, last: int = 6) -> float:
    """The usual staircase estimate: the mean level of the last ``last`` reversals (NaN if none)."""
    values = list(reversal_levels)[-last:]
    return float(np.mean(values)) if values else float("nan")
