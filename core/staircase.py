"""Adaptive staircases over a pre-rendered grid of levels. Pure and deterministic.

Two rules, one interface (``condition``, ``level``, ``record``, ``replay``, ``estimate``):

* :class:`UpDownStaircase` - a transformed up-down rule (Levitt, 1971): after ``down`` correct
  answers in a row the level moves ``step`` grid steps towards harder, after ``up`` wrong
  answers in a row ``step`` steps towards easier; it stays inside the grid. 1-up-2-down
  converges on 70.7 % correct, 1-up-3-down on 79.4 %. Its estimate is the mean level of the
  last reversals.
* :class:`BrandKollmeierStaircase` - the procedure of matrix sentence tests (Brand &
  Kollmeier, 2002, J. Acoust. Soc. Am. 111(6):2801-2810): after each sentence the level moves
  by ``-f(i) * (score - target) / slope``, ``score`` the share of the sentence's words
  understood (not just right or wrong), ``slope`` the intelligibility function's assumed slope
  at the target (per level unit), ``f(i) = f_start * f_decay**-i`` after ``i`` reversals of
  the level's direction (floored at ``f_min``). The tracked level is continuous; each trial
  shows the grid level nearest to it. Its estimate is the mean level of the last
  :data:`LAST_TRIALS` trials (the analysis fits the function to every answer).
* :class:`QuestPlusStaircase` - QUEST+ (Watson, 2017, J. Vision 17(3):10): a posterior over a
  grid of psychometric functions ``P = gamma + (1 - gamma - lambda) F(x; alpha, beta)``
  (:mod:`facelab.psychometric_function`), uniform at the start and multiplied by the
  likelihood of each answer; each trial shows the grid level whose answer is expected to
  leave the least entropy in the posterior. ``gamma`` is the task's guess rate (1/2 for
  2AFC, 1/k for identification among k labels). Its estimate is the posterior mean of the
  midpoint of F (and its posterior SD). ``tests/test_staircase_questplus.py`` checks the
  expected entropies and choices against the ``questplus`` package.

The grid is the block's conditions ordered by their ``level``, easiest first; which end is
easier is the protocol's ``easier`` (``higher``: a larger level is easier to get right).
Neither rule draws random numbers (ties go to the easier level), so the state after any
prefix of answers is a function of those answers: a resumed session rebuilds it by replaying
the logged rows of its block (``replay``) and continues the same staircase. Every step is also
written to the session's ``_staircase.jsonl`` (``record``) so it can be read without facelab,
and the replay is checked against it.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from facelab.protocol import ChoiceTask, MatrixTask, Protocol, TypedTask
from facelab.psychometric_function import midpoint, predict

__all__ = [
    "BrandKollmeierStaircase",
    "QuestPlusStaircase",
    "Staircase",
    "UpDownStaircase",
    "convergence_probability",
    "guess_rate",
    "new_staircase",
    "reversal_threshold",
]

#: Reversals averaged for the up-down estimate.
LAST_REVERSALS = 6
#: Trials whose levels the Brand-Kollmeier estimate averages.
LAST_TRIALS = 10


def convergence_probability(*, up: int, down: int) -> float:
    """P(correct) an up/down rule converges on: ``p**down = 1/2`` for 1-up-n-down."""
    if up != 1:
        # general transformed rule: p_down = p**down equals p_up = 1 - (1 - p)**up; solve
        grid = np.linspace(1e-6, 1 - 1e-6, 200_001)
        gap = np.abs(grid**down - (1 - (1 - grid) ** up))
        return float(grid[int(np.argmin(gap))])
    return float(0.5 ** (1.0 / down))


class _Rule(abc.ABC):
    """What both rules share: the grid, the record of a step and the replay of a log.

    Subclasses set ``grid`` (condition ids, easiest first), ``levels``, ``index`` (the grid
    point shown next), ``trials`` and ``reversals`` and implement :meth:`_move` and
    :meth:`estimate`."""

    grid: tuple[str, ...]
    levels: tuple[float, ...]
    index: int
    trials: int
    reversals: list[float]
    direction: int

    @property
    def condition(self) -> str:
        """The condition to show next."""
        return self.grid[self.index]

    @property
    def level(self) -> float:
        return self.levels[self.index]

    def _check_grid(self) -> None:
        if len(self.grid) != len(self.levels) or len(self.grid) < 2:
            raise ValueError("a staircase needs two or more grid points, each with a level")

    @abc.abstractmethod
    def _move(self, correct: bool, score: float) -> int:
        """Apply an answer at the current level and return the next grid index."""

    @abc.abstractmethod
    def estimate(self) -> dict[str, Any]:
        """The rule's threshold estimate (level units) so far."""

    def _direction(self, shown: int) -> int:
        """+1 when the last answer made the level harder, -1 easier, 0 neither."""
        return int(self.index > shown) - int(self.index < shown)  # sign, run per trial

    def update(self, correct: bool, score: float | None = None) -> bool:
        """Apply one answer at the current level (``score``: the share of its units right,
        1 or 0 by ``correct`` when not given); returns whether the direction of the level
        reversed (harder -> easier or back)."""
        self.trials += 1
        shown = self.index
        score = float(bool(correct)) if score is None else float(score)
        self.index = self._move(bool(correct), score)
        move = self._direction(shown)
        reversal = False
        if move:
            if self.direction and move != self.direction:
                reversal = True
                self.reversals.append(self.levels[shown])
            self.direction = move
        return reversal

    def record(
        self, *, trial_index: int, condition: str, correct: bool, score: float | None = None
    ) -> dict[str, Any]:
        """Apply an answer and return the line for ``_staircase.jsonl``."""
        level = self.levels[self.grid.index(condition)]
        score = float(bool(correct)) if score is None else float(score)
        reversal = self.update(correct, score)
        return {
            "trial_index": trial_index,
            "condition": condition,
            "level": level,
            "correct": bool(correct),
            "score": score,
            "reversal": reversal,
            "reversals": len(self.reversals),
            "next_condition": self.condition,
            "next_level": self.level,
            "trials": self.trials,
            **self.estimate(),
        }

    def replay(
        self, answers: Iterable[tuple[int, str, bool, float | None]]
    ) -> list[dict[str, Any]]:
        """Apply logged (trial index, condition, correct, score) answers in order, checking
        each was the one due; returns the :meth:`record` of every step."""
        steps = []
        for trial_index, condition, correct, score in answers:
            if condition != self.condition:
                raise ValueError(
                    f"the log shows condition {condition!r} at trial {trial_index} where the "
                    f"staircase was at {self.condition!r}: the log does not belong to this "
                    "staircase"
                )
            steps.append(self.record(trial_index=trial_index, condition=condition,
                                     correct=correct, score=score))  # fmt: skip
        return steps


@dataclass
class UpDownStaircase(_Rule):
    """State of one transformed up-down staircase. ``grid`` is ordered from easiest to
    hardest."""

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
        self._check_grid()
        if self.index < 0:
            self.index = self.start

    def _move(self, correct: bool, score: float) -> int:
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
        return min(max(self.index + move * self.step, 0), len(self.grid) - 1)

    def estimate(self) -> dict[str, Any]:
        return {
            "estimate": f"mean of the last {LAST_REVERSALS} reversals",
            "threshold": reversal_threshold(self.reversals, last=LAST_REVERSALS),
        }


#: Decimals the expected entropies are rounded to before the smallest is chosen, so that
#: floating-point noise between machines cannot turn a tie into a different choice.
ENTROPY_DECIMALS = 10


@dataclass
class QuestPlusStaircase(_Rule):
    """State of one QUEST+ run over ``grid`` (easiest first) at ``levels``.

    The parameter grid is ``thresholds`` x ``slopes`` x ``lapses`` (alpha in level units,
    beta, lambda); ``sign`` is +1 when a higher level is easier, -1 when a lower one is (F is
    then evaluated at ``-level`` with thresholds ``-alpha``, so ``thresholds`` stay in level
    units). ``start`` (a grid index or None) fixes the first trial; without it the first trial
    is chosen like every other."""

    grid: tuple[str, ...]
    levels: tuple[float, ...]
    gamma: float
    thresholds: tuple[float, ...]
    slopes: tuple[float, ...]
    lapses: tuple[float, ...]
    sigmoid: str = "logistic"
    sign: int = 1
    start: int | None = None
    index: int = -1
    direction: int = 0
    trials: int = 0
    reversals: list[float] = field(default_factory=list)
    posterior: np.ndarray = field(init=False, repr=False)
    likelihood: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._check_grid()
        if not 0.0 <= self.gamma < 1.0 or any(
            not 0.0 <= lp < 1.0 - self.gamma for lp in self.lapses
        ):
            raise ValueError("QUEST+ needs 0 <= gamma < 1 and every lapse rate below 1 - gamma")
        x = self.sign * np.asarray(self.levels, dtype=float)[:, None, None, None]
        alpha = self.sign * np.asarray(self.thresholds, dtype=float)[None, :, None, None]
        beta = np.asarray(self.slopes, dtype=float)[None, None, :, None]
        lapse = np.asarray(self.lapses, dtype=float)[None, None, None, :]
        # P(correct | level, alpha, beta, lambda): shape (levels, thresholds, slopes, lapses)
        self.likelihood = predict(
            x, sigmoid=self.sigmoid, alpha=alpha, beta=beta, gamma=self.gamma, lapse=lapse
        )
        shape = self.likelihood.shape[1:]
        self.posterior = np.full(shape, 1.0 / np.prod(shape))
        if self.index < 0:
            self.index = self.start if self.start is not None else self._best()

    def expected_entropy(self) -> np.ndarray:
        """The posterior's expected entropy (nats) after a trial at each grid level."""
        out = np.empty(len(self.grid))
        for i, p_correct in enumerate(self.likelihood):
            h = 0.0
            for lik in (p_correct, 1.0 - p_correct):
                joint = self.posterior * lik
                p = joint.sum()
                if p > 0:
                    post = joint[joint > 0] / p
                    h += p * -np.sum(post * np.log(post))
            out[i] = h
        return out

    def _best(self) -> int:
        return int(np.argmin(np.round(self.expected_entropy(), ENTROPY_DECIMALS)))

    def _move(self, correct: bool, score: float) -> int:
        lik = self.likelihood[self.index]
        joint = self.posterior * (lik if correct else 1.0 - lik)
        total = joint.sum()
        if total <= 0:  # every function on the grid ruled out (lapse rates of 0 only)
            raise ValueError(
                "the answers are impossible under every psychometric function of the grid; "
                "allow a lapse rate above 0"
            )
        self.posterior = joint / total
        return self._best()

    def estimate(self) -> dict[str, Any]:
        alpha = np.asarray(self.thresholds, dtype=float)[:, None, None]
        beta = np.asarray(self.slopes, dtype=float)[None, :, None]
        mid = np.broadcast_to(midpoint(self.sigmoid, alpha, beta), self.posterior.shape)
        mean = float(np.sum(self.posterior * mid))
        sd = float(np.sqrt(max(0.0, np.sum(self.posterior * (mid - mean) ** 2))))
        lapse = float(np.sum(self.posterior.sum(axis=(0, 1)) * np.asarray(self.lapses)))
        slope = float(np.sum(self.posterior.sum(axis=(0, 2)) * np.asarray(self.slopes)))
        return {
            "estimate": "QUEST+ posterior mean of the midpoint",
            "threshold": mean,
            "threshold_sd": sd,
            "slope": slope,
            "lapse": lapse,
        }


@dataclass
class BrandKollmeierStaircase(_Rule):
    """State of one Brand & Kollmeier (2002) track over ``grid`` (easiest first) at
    ``levels``; ``sign`` is +1 when a higher level is easier. ``value`` is the tracked level
    (continuous, kept inside the grid's range); the grid point nearest to it is shown."""

    grid: tuple[str, ...]
    levels: tuple[float, ...]
    start: int
    target: float = 0.5
    slope: float = 0.15
    f_start: float = 1.5
    f_decay: float = 1.41
    f_min: float = 0.1
    sign: int = 1
    index: int = -1
    value: float = math.nan
    moved: int = 0  # the sign of the tracked level's last change (+1 harder)
    direction: int = 0
    trials: int = 0
    reversals: list[float] = field(default_factory=list)
    shown: list[float] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._check_grid()
        if not 0.0 < self.target < 1.0 or self.slope <= 0 or self.f_start <= 0:
            raise ValueError("Brand-Kollmeier needs 0 < target < 1, slope > 0 and f_start > 0")
        if self.index < 0:
            self.index = self.start
        if math.isnan(self.value):
            self.value = self.levels[self.index]

    def step_factor(self) -> float:
        """f(i) after the reversals so far."""
        return max(self.f_min, self.f_start * self.f_decay ** -len(self.reversals))

    def _move(self, correct: bool, score: float) -> int:
        self.shown.append(self.levels[self.index])
        # a score above the target makes it harder: a lower level when higher is easier
        change = -self.step_factor() * (score - self.target) / self.slope * self.sign
        low, high = min(self.levels), max(self.levels)
        value = float(np.clip(self.value + change, low, high))
        self.moved = int(np.sign(-(value - self.value) * self.sign))
        self.value = value
        return int(np.argmin(np.abs(np.asarray(self.levels) - value)))

    def _direction(self, shown: int) -> int:
        return self.moved

    def estimate(self) -> dict[str, Any]:
        last = self.shown[-LAST_TRIALS:]
        return {
            "estimate": f"mean level of the last {LAST_TRIALS} trials",
            "threshold": float(np.mean(last)) if last else float("nan"),
            "tracked_level": self.value,
            "step_factor": self.step_factor(),
        }


#: Any rule.
Staircase = UpDownStaircase | QuestPlusStaircase | BrandKollmeierStaircase


def guess_rate(protocol: Protocol, block_id: str) -> float:
    """P(correct) by guessing in a staircase block's task: 1/2 for 2AFC, 1/k for an identify
    task with k labels, 0 for typed answers, a matrix's mean 1/column length."""
    block = next(b for b in protocol.blocks if b.id == block_id)
    task = next(t for t in protocol.tasks if t.id == block.task)
    if isinstance(task, MatrixTask):
        return task.guess_rate()  # a word of each column right by chance
    if isinstance(task, TypedTask):
        return 0.0  # an open set: no answer is right by chance
    return 0.5 if isinstance(task, ChoiceTask) else 1.0 / len(task.labels)


def new_staircase(protocol: Protocol, block_id: str) -> Staircase:
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
    levels = tuple(float(protocol.condition(c).level or 0.0) for c in conditions)
    start = conditions.index(rule.start) if rule.start is not None else None
    if rule.rule == "up_down":
        if start is None:
            raise ValueError(f"block {block_id!r}: rule up_down needs a start")
        return UpDownStaircase(
            grid=tuple(conditions),
            levels=levels,
            start=start,
            up=rule.up,
            down=rule.down,
            step=rule.step,
        )
    if rule.rule == "brand_kollmeier":
        if start is None:
            raise ValueError(f"block {block_id!r}: rule brand_kollmeier needs a start")
        return BrandKollmeierStaircase(
            grid=tuple(conditions), levels=levels, start=start, target=rule.target_score,
            slope=rule.assumed_slope, f_start=rule.step_start, f_decay=rule.step_decay,
            f_min=rule.step_min, sign=1 if rule.easier == "higher" else -1,
        )  # fmt: skip
    low, high = min(levels), max(levels)
    span = high - low
    if rule.slopes is not None:
        slopes = tuple(rule.slopes)
    elif rule.sigmoid == "logistic":
        slopes = tuple(np.geomspace(2.0 / span, 50.0 / span, 9))
    else:
        slopes = tuple(np.geomspace(1.0, 10.0, 9))
    return QuestPlusStaircase(
        grid=tuple(conditions),
        levels=levels,
        gamma=guess_rate(protocol, block_id),
        thresholds=tuple(np.linspace(low, high, rule.threshold_points)),
        slopes=slopes,
        lapses=tuple(rule.lapse_rates),
        sigmoid=rule.sigmoid,
        sign=1 if rule.easier == "higher" else -1,
        start=start,
    )


def reversal_threshold(reversal_levels: Sequence[float], *, last: int = LAST_REVERSALS) -> float:
    """The usual staircase estimate: the mean level of the last ``last`` reversals (NaN if none)."""
    values = [float(v) for v in list(reversal_levels)[-last:]]
    if not values:
        return float("nan")
    # numpy's mean adds up to seven values in order, as sum() does: the same number, without
    # numpy's overhead (this runs once per simulated trial)
    return sum(values) / len(values) if len(values) < 8 else float(np.mean(values))
