"""Trial design: (protocol, participant, seed) -> the ordered trial list. Pure and deterministic.

Each block has ``sets`` sets; one set shows every (stimulus, condition) pair of the block's
stimulus set ``presentations_per_condition`` times. The order inside a set is

* ``random_within_set`` - shuffled anew for every set with the participant's generator;
* ``fixed`` - protocol order: repetition, then stimulus, then condition;
* ``latin_square`` - the condition order is a row of a balanced (Williams) Latin square,
  row ``(participant number - 1 + set_index - 1) mod rows``, so participants 1..rows see
  every order and every condition follows every other equally often; repeated as needed.

The blocks come in the protocol's order, or with ``presentation.block_order: latin_square``
in the order of row ``(participant number - 1) mod rows`` of a balanced Latin square of the
blocks (:func:`block_sequence`).

The participant's generator is seeded by :func:`participant_seed`, a reproducible function of
the study seed and the participant id, so the same inputs always give the same trial list and
different participants get different orders.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

import numpy as np
import pandas as pd

from facelab.errors import StageError
from facelab.protocol import Block, Protocol

__all__ = [
    "CHOICE_COLUMNS",
    "PENDING",
    "TRIAL_COLUMNS",
    "Trial",
    "balanced_latin_square",
    "block_sequence",
    "block_trials",
    "build_trials",
    "count_trials",
    "needs_numbered_ids",
    "participant_number",
    "participant_seed",
    "trial_order",
    "trials_frame",
    "validate_participant_id",
]

_PARTICIPANT_RE = re.compile(r"^[A-Za-z0-9]{1,32}$")


@dataclass(frozen=True)
class Trial:
    """One clip presentation. Indices are 1-based, as people count them."""

    trial_index: int  # position in the session, 1..N
    block: str  # block id
    set_index: int  # 1..block.sets
    stimulus_set: str
    stimulus: str
    condition: str
    repetition: int  # 1..presentations_per_condition: nth showing of this pair in this set
    standard: str | None = None  # choice_2afc: the standard condition shown with this one
    position: int | None = None  # choice_2afc: 1 = the comparison is shown first, 2 = second


#: The design CSV's columns (DESIGN.md); ``standard`` and ``position`` follow when a block has a
#: forced-choice task.
TRIAL_COLUMNS: tuple[str, ...] = tuple(f.name for f in fields(Trial))[:7]
CHOICE_COLUMNS: tuple[str, ...] = ("standard", "position")

#: The condition of a staircase trial before the staircase has chosen it (at run time).
PENDING = "*"


def validate_participant_id(participant: str) -> str:
    """Participant ids are 1-32 letters or digits (BIDS labels: used in folder names)."""
    if not _PARTICIPANT_RE.match(participant):
        raise StageError(
            f"participant id {participant!r} is not valid: expected 1-32 letters or digits "
            "(e.g. P01), no spaces, dashes or underscores"
        )
    return participant


def participant_number(participant: str) -> int | None:
    """The trailing number of a participant id (``P07`` -> 7), or None if it has none."""
    match = re.search(r"(\d+)$", participant)
    return int(match.group(1)) if match else None


def participant_seed(study_seed: int, participant: str) -> int:
    """A 63-bit seed from the study seed and the participant id (stable across versions).

    SHA-256 of ``"<study_seed>:<participant>"``, first 8 bytes, top bit cleared.

    Parameters
    ----------
    study_seed : int
        The protocol's ``seed``.
    participant : str
        The participant id (e.g. ``P01``).

    Returns
    -------
    int
        A seed in ``[0, 2**63)`` for ``numpy.random.default_rng``.

    Examples
    --------
    >>> participant_seed(2021, "P01") == participant_seed(2021, "P01")
    True
    >>> participant_seed(2021, "P01") != participant_seed(2021, "P02")
    True
    """
    digest = hashlib.sha256(f"{study_seed}:{participant}".encode()).digest()
    return int.from_bytes(digest[:8], "big") & (2**63 - 1)


def balanced_latin_square(k: int) -> list[list[int]]:
    """Williams' balanced Latin square over ``k`` items, as rows of item indices.

    For even ``k`` there are ``k`` rows; for odd ``k`` the square and its mirror image,
    ``2k`` rows, so that first-order carry-over is balanced.

    Parameters
    ----------
    k : int
        The number of items (conditions), at least 1.

    Returns
    -------
    list of list of int
        ``k`` (even ``k``) or ``2k`` (odd ``k``) orders, each a permutation of ``range(k)``;
        every item follows every other item equally often.

    Examples
    --------
    >>> balanced_latin_square(4)
    [[0, 1, 3, 2], [1, 2, 0, 3], [2, 3, 1, 0], [3, 0, 2, 1]]
    >>> len(balanced_latin_square(3))  # odd: the square and its mirror
    6
    """
    if k < 1:
        raise ValueError("k must be >= 1")
    base = [0]
    lo, hi = 1, k - 1
    for j in range(1, k):
        if j % 2:
            base.append(lo)
            lo += 1
        else:
            base.append(hi)
            hi -= 1
    rows = [[(x + r) % k for x in base] for r in range(k)]
    if k % 2:
        rows += [list(reversed(row)) for row in rows]
    return rows


def needs_numbered_ids(protocol: Protocol) -> bool:
    """True when the design orders something by participant number (a Latin-square block
    order, or a block's Latin-square condition order): its participant ids must end in one."""
    return protocol.presentation.block_order == "latin_square" or any(
        b.order == "latin_square" for b in protocol.blocks
    )


def _number(participant: str, what: str) -> int:
    number = participant_number(participant)
    if number is None:
        raise StageError(f"{what} uses order 'latin_square', which needs participant ids "
                         f"ending in a number (e.g. P01); got {participant!r}")  # fmt: skip
    return number


def block_sequence(protocol: Protocol, *, participant: str) -> list[Block]:
    """The blocks in the order ``participant`` does them: the protocol's, or with
    ``presentation.block_order: latin_square`` row ``(participant number - 1) mod rows`` of
    a balanced Latin square of the blocks.

    Examples
    --------
    >>> from facelab.resources import protocol_path
    >>> from facelab.protocol import load_protocol
    >>> matrix = load_protocol(protocol_path("kato2021_srt_matrix"))
    >>> for n in (1, 2, 3):
    ...     print(" ".join(b.id for b in block_sequence(matrix, participant=f"P{n}")))
    audio baseline emphasized
    baseline emphasized audio
    emphasized audio baseline
    """
    blocks = list(protocol.blocks)
    if protocol.presentation.block_order == "fixed" or len(blocks) < 2:
        return blocks
    rows = balanced_latin_square(len(blocks))
    row = rows[(_number(participant, "presentation.block_order") - 1) % len(rows)]
    return [blocks[i] for i in row]


def _set_sequence(
    *,
    protocol: Protocol,
    block: Block,
    set_index: int,
    participant: str,
    rng: np.random.Generator,
) -> list[tuple[str, str]]:
    """(stimulus, condition) pairs of one set, in presentation order."""
    conditions = protocol.block_conditions(block)
    stimuli = [s.id for s in protocol.stimulus_set(block.stimulus_set).stimuli]
    reps = block.presentations_per_condition
    if block.order == "latin_square":
        number = _number(participant, f"block {block.id!r}")
        rows = balanced_latin_square(len(conditions))
        row = rows[(number - 1 + set_index - 1) % len(rows)]
        conditions = [conditions[i] for i in row]
    pairs = [(stim, cond) for _ in range(reps) for stim in stimuli for cond in conditions]
    if block.order == "random_within_set":
        order = rng.permutation(len(pairs))
        pairs = [pairs[i] for i in order]
    return pairs


def build_trials(protocol: Protocol, *, participant: str, seed: int | None = None) -> list[Trial]:
    """The ordered trial list for one participant.

    The generator is ``numpy.random.default_rng(participant_seed(seed, participant))``, so a
    participant's order is the same on every machine and in every facelab version.

    Parameters
    ----------
    protocol : Protocol
        A validated protocol (:func:`facelab.protocol.load_protocol`).
    participant : str
        Participant id (letters and digits).
    seed : int, optional
        The study seed to use instead of ``protocol.seed`` (e.g. ``--seed``).

    Returns
    -------
    list of Trial
        In presentation order, numbered from 1.

    Examples
    --------
    >>> from facelab.resources import protocol_path
    >>> from facelab.protocol import load_protocol
    >>> kato = load_protocol(protocol_path("kato2021"))
    >>> trials = build_trials(kato, participant="P01")
    >>> len(trials), sorted({t.condition for t in trials})
    (18, ['baseline', 'emphasized', 'standard'])
    """
    validate_participant_id(participant)
    study_seed = protocol.seed if seed is None else seed
    rng = np.random.default_rng(participant_seed(study_seed, participant))
    trials: list[Trial] = []
    for block in block_sequence(protocol, participant=participant):
        task = protocol.block_task(block)
        standard = task.standard if task is not None and task.type == "choice_2afc" else None
        if block.design == "staircase":
            trials += _staircase_trials(
                protocol, block=block, start=len(trials), standard=standard, rng=rng
            )
            continue
        for set_index in range(1, block.sets + 1):
            seen: dict[tuple[str, str], int] = {}
            for stim, cond in _set_sequence(
                protocol=protocol,
                block=block,
                set_index=set_index,
                participant=participant,
                rng=rng,
            ):
                seen[(stim, cond)] = seen.get((stim, cond), 0) + 1
                trials.append(
                    Trial(
                        trial_index=len(trials) + 1,
                        block=block.id,
                        set_index=set_index,
                        stimulus_set=block.stimulus_set,
                        stimulus=stim,
                        condition=cond,
                        repetition=seen[(stim, cond)],
                        standard=standard,
                    )
                )
        if standard is not None:
            trials = _balance_positions(trials, block=block.id, rng=rng)
    return trials


def _balance_positions(trials: list[Trial], *, block: str, rng: np.random.Generator) -> list[Trial]:
    """Counterbalance which interval holds the comparison: the showings of each (stimulus,
    condition) in the block alternate 1, 2, 1, 2… from a random first position, so every pair
    is shown first and second equally often (to one when the count is odd)."""
    first: dict[tuple[str, str], int] = {}
    count: dict[tuple[str, str], int] = {}
    out = []
    for t in trials:
        if t.block != block:
            out.append(t)
            continue
        key = (t.stimulus, t.condition)
        if key not in first:
            first[key] = int(rng.integers(1, 3))
        k = count.get(key, 0)
        count[key] = k + 1
        out.append(replace(t, position=1 + (first[key] - 1 + k) % 2))
    return out


def _staircase_trials(
    protocol: Protocol,
    *,
    block: Block,
    start: int,
    standard: str | None,
    rng: np.random.Generator,
) -> list[Trial]:
    """``staircase.trials`` slots whose condition the staircase picks at run time
    (:data:`PENDING`); stimuli cycle through the set in shuffled rounds, positions of a
    forced choice are balanced within every two trials and drawn in advance."""
    assert block.staircase is not None  # guaranteed by the protocol checks
    stimuli = [s.id for s in protocol.stimulus_set(block.stimulus_set).stimuli]
    n = block.staircase.trials
    order: list[str] = []
    while len(order) < n:
        order += [stimuli[i] for i in rng.permutation(len(stimuli))]
    positions: list[int | None] = [None] * n
    if standard is not None:
        pairs = [int(rng.integers(1, 3)) for _ in range((n + 1) // 2)]
        positions = [p if j % 2 == 0 else 3 - p for p in pairs for j in range(2)][:n]
    return [
        Trial(
            trial_index=start + i + 1,
            block=block.id,
            set_index=1,
            stimulus_set=block.stimulus_set,
            stimulus=order[i],
            condition=PENDING,
            repetition=i + 1,
            standard=standard,
            position=positions[i],
        )
        for i in range(n)
    ]


def block_trials(protocol: Protocol, block: Block) -> int:
    """How many trials one block gives each participant."""
    if block.design == "staircase" and block.staircase is not None:
        return block.staircase.trials
    return (
        block.sets
        * len(protocol.stimulus_set(block.stimulus_set).stimuli)
        * len(protocol.block_conditions(block))
        * block.presentations_per_condition
    )


def count_trials(protocol: Protocol) -> int:
    """How many trials :func:`build_trials` gives each participant (without building them)."""
    return sum(block_trials(protocol, block) for block in protocol.blocks)


def trial_order(trials: Sequence[Trial]) -> list[list[Any]]:
    """The trial order as a session's JSON records it (lab and online sessions alike)."""
    return [[t.block, t.set_index, t.stimulus, t.condition, t.repetition] for t in trials]


def trials_frame(trials: list[Trial]) -> pd.DataFrame:
    """Trials as a tidy DataFrame with :data:`TRIAL_COLUMNS` (and :data:`CHOICE_COLUMNS` when
    a trial has a forced choice)."""
    columns = list(TRIAL_COLUMNS)
    if any(t.standard is not None for t in trials):
        columns += list(CHOICE_COLUMNS)
    frame = pd.DataFrame([asdict(t) for t in trials], columns=columns)
    if "position" in frame:
        frame["position"] = frame["position"].astype("Int64")
    return frame
