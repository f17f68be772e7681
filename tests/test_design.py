"""Trial design: counts per set, determinism, randomness across participants, Latin squares."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest

from facelab.design import (
    balanced_latin_square,
    build_trials,
    participant_seed,
    trials_frame,
)
from facelab.errors import StageError
from facelab.protocol import Protocol, load_protocol


@pytest.fixture(scope="module")
def kato() -> Protocol:
    return load_protocol(Path(__file__).resolve().parents[1] / "protocols" / "kato2021.yaml")


def test_kato_design_has_18_trials_with_the_papers_counts(kato: Protocol) -> None:
    frame = trials_frame(build_trials(kato, participant="P01"))
    assert len(frame) == 18
    assert list(frame.trial_index) == list(range(1, 19))
    assert Counter(frame.block) == {"vowels": 12, "sentences": 6}
    assert list(frame.block[:12]) == ["vowels"] * 12  # vowels first, as in the paper
    per_block = frame.groupby(["block", "condition"]).size()
    assert set(per_block["vowels"]) == {4} and set(per_block["sentences"]) == {2}


@pytest.mark.parametrize("seed", range(200))
def test_every_set_holds_each_condition_the_asked_number_of_times(
    kato: Protocol, seed: int
) -> None:
    frame = trials_frame(build_trials(kato, participant=f"P{seed:03d}", seed=seed))
    for (block_id, _set), group in frame.groupby(["block", "set_index"]):
        block = next(b for b in kato.blocks if b.id == block_id)
        counts = Counter(group.condition)
        assert counts == {
            c: block.presentations_per_condition for c in ("baseline", "standard", "emphasized")
        }
        # repetition numbers the showings of each (stimulus, condition) pair within the set
        for _, pair in group.groupby(["stimulus", "condition"]):
            assert list(pair.repetition) == list(range(1, block.presentations_per_condition + 1))


def test_same_inputs_give_the_same_list(kato: Protocol) -> None:
    for pid in ("P01", "P02", "X9"):
        assert build_trials(kato, participant=pid) == build_trials(kato, participant=pid)
        assert build_trials(kato, participant=pid, seed=5) == build_trials(
            kato, participant=pid, seed=5
        )


def test_orders_differ_across_participants_and_seeds(kato: Protocol) -> None:
    def order(pid: str, seed: int | None = None) -> tuple[str, ...]:
        return tuple(t.condition for t in build_trials(kato, participant=pid, seed=seed))

    orders = [order(f"P{i:02d}") for i in range(1, 61)]
    assert len(set(orders)) >= 55  # 60 participants, ~10^7 possible orders
    assert order("P01", seed=1) != order("P01", seed=2)
    # no condition is favoured in the first position of a set
    firsts = Counter(
        t.condition
        for i in range(600)
        for t in build_trials(kato, participant=f"Q{i}")
        if t.trial_index in (1, 7, 13, 16)
    )
    assert all(0.28 < n / 2400 < 0.39 for n in firsts.values()), firsts


def test_participant_seed_is_stable_and_depends_on_both_inputs() -> None:
    # pinned value: changing the derivation would silently change every published design
    assert participant_seed(20210527, "P01") == participant_seed(20210527, "P01")
    assert participant_seed(20210527, "P01") != participant_seed(20210527, "P02")
    assert participant_seed(1, "P01") != participant_seed(2, "P01")
    assert 0 <= participant_seed(0, "A") < 2**63


@pytest.mark.parametrize("k", [2, 3, 4, 5, 6])
def test_balanced_latin_square(k: int) -> None:
    rows = balanced_latin_square(k)
    assert len(rows) == (k if k % 2 == 0 else 2 * k)
    for row in rows:
        assert sorted(row) == list(range(k))
    for pos in range(k):  # each item in each position equally often
        assert len(set(Counter(r[pos] for r in rows).values())) == 1
    pairs = Counter((r[i], r[i + 1]) for r in rows for i in range(k - 1))
    assert len(pairs) == k * (k - 1) and len(set(pairs.values())) == 1  # carry-over balanced


def _with_order(kato: Protocol, order: str) -> Protocol:
    blocks = [b.model_copy(update={"order": order}) for b in kato.blocks]
    return kato.model_copy(update={"blocks": blocks})


def test_latin_square_order_rotates_over_participants(kato: Protocol) -> None:
    p = _with_order(kato, "latin_square")
    first_sets = {
        tuple(t.condition for t in build_trials(p, participant=f"P{i}")[:3]) for i in range(1, 7)
    }
    assert len(first_sets) == 6  # 3 conditions -> 6 Williams rows, all used by P1..P6
    with pytest.raises(StageError, match="ending in a number"):
        build_trials(p, participant="alice")


def test_fixed_order_follows_the_protocol(kato: Protocol) -> None:
    p = _with_order(kato, "fixed")
    conds = [t.condition for t in build_trials(p, participant="P01")]
    assert conds[:6] == ["baseline", "standard", "emphasized"] * 2
    assert build_trials(p, participant="P01") == build_trials(p, participant="P02")


def test_bad_participant_id(kato: Protocol) -> None:
    with pytest.raises(StageError, match="letters or digits"):
        build_trials(kato, participant="sub-01")


def test_block_order_latin_square_spreads_each_block_over_every_place() -> None:
    """``presentation.block_order: latin_square`` (the shipped matrix test): over six
    participants each of three blocks comes first, second and third twice, and after each
    other block equally often; a participant's trials follow their blocks whole, staircases
    included; the practice trial asks the first block's task; ids without a number are
    refused in words. ``fixed`` keeps the protocol's order for everyone."""
    from facelab.design import block_sequence
    from facelab.experiment.timeline import compile_timeline
    from facelab.resources import protocol_path

    matrix = load_protocol(protocol_path("kato2021_srt_matrix"))
    assert matrix.presentation.block_order == "latin_square"
    orders = [[b.id for b in block_sequence(matrix, participant=f"P{n:02d}")]
              for n in range(1, 7)]  # fmt: skip
    ids = [b.id for b in matrix.blocks]
    for place in range(3):
        assert Counter(order[place] for order in orders) == dict.fromkeys(ids, 2)
    follows = Counter((o[i], o[i + 1]) for o in orders for i in range(2))
    assert set(follows.values()) == {2} and len(follows) == 6
    trials = build_trials(matrix, participant="P02")
    seen = list(dict.fromkeys(t.block for t in trials))
    assert seen == orders[1] != ids and len(trials) == 60
    assert [t.trial_index for t in trials] == list(range(1, 61))
    screens = compile_timeline(matrix, trials, participant="P02", session=1)
    practice = next(s for s in screens if getattr(s, "practice", False) and hasattr(s, "task"))
    assert practice.task.id == "sentence"
    with pytest.raises(StageError, match=r"block_order.*ending in a number"):
        build_trials(matrix, participant="alice")
    fixed = matrix.model_copy(update={"presentation": matrix.presentation.model_copy(
        update={"block_order": "fixed"})})  # fmt: skip
    for n in (1, 2, 5):
        assert [b.id for b in block_sequence(fixed, participant=f"P{n}")] == ids


def test_the_calibration_of_intervals_runs_on_a_latin_square_block_order() -> None:
    """``facelab analyze`` calibrates a 2AFC's per-participant intervals by simulating one
    participant through the design; with the blocks in a Latin-square order that participant
    needs a number (it was called 'calibration' and the analysis stopped)."""
    import numpy as np

    from facelab.experiment.simulate import design_sampler
    from facelab.resources import protocol_path

    p = load_protocol(protocol_path("gain_2afc"))
    second = p.blocks[0].model_copy(update={"id": "again"})
    p = p.model_copy(update={
        "blocks": [p.blocks[0], second],
        "presentation": p.presentation.model_copy(update={"block_order": "latin_square"}),
    })  # fmt: skip
    task = next(t.id for t in p.tasks if t.type == "choice_2afc")
    rows = design_sampler(p)(task, 0.5, 1.0, 0.02, np.random.default_rng(3))
    assert len(rows) == 2 * len([t for t in build_trials(p, participant="P1")
                                 if t.block == "again"])  # fmt: skip
