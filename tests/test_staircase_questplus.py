"""QUEST+ staircases: checked against an independent implementation (the ``questplus``
package), their choices, estimates, resume and validation."""

from __future__ import annotations

import re

import numpy as np
import pytest
import questplus

from facelab.analysis.load import load_results
from facelab.design import build_trials
from facelab.errors import ProtocolError
from facelab.experiment.adaptive import Staircases
from facelab.experiment.simulate import simulate_study
from facelab.protocol import load_protocol
from facelab.psychometric_function import predict
from facelab.resources import protocol_path
from facelab.staircase import QuestPlusStaircase, new_staircase

LEVELS = np.round(np.linspace(0.1, 1.0, 10), 10)
THRESHOLDS = np.linspace(0.1, 1.0, 19)
SLOPES = np.geomspace(1.0, 8.0, 6)
LAPSES = np.array([0.0, 0.02, 0.04])


def _pair() -> tuple[QuestPlusStaircase, questplus.QuestPlus]:
    ours = QuestPlusStaircase(
        grid=tuple(f"x{i}" for i in range(len(LEVELS)))[::-1],  # easiest (highest) first
        levels=tuple(LEVELS[::-1]),
        gamma=0.5,
        thresholds=tuple(THRESHOLDS),
        slopes=tuple(SLOPES),
        lapses=tuple(LAPSES),
        sigmoid="weibull",
    )
    theirs = questplus.QuestPlus(
        stim_domain={"intensity": LEVELS},
        func="weibull",
        stim_scale="linear",
        param_domain={
            "threshold": THRESHOLDS,
            "slope": SLOPES,
            "lower_asymptote": 0.5,
            "lapse_rate": LAPSES,
        },
        outcome_domain={"response": ["Correct", "Incorrect"]},
        stim_selection_method="min_entropy",
        param_estimation_method="mean",
    )
    return ours, theirs


def _their_expected_entropy(q: questplus.QuestPlus) -> np.ndarray:
    """questplus's expected entropies per intensity (the quantity its next_stim minimises)."""
    post = q.posterior * q.likelihoods
    pk = post.sum(dim=list(q.param_domain))
    post = post / pk
    with np.errstate(divide="ignore", invalid="ignore"):
        h = -(post * np.log(post)).sum(dim=list(q.param_domain))
    return (pk * h).sum(dim="response").values


def test_quest_plus_matches_the_questplus_package():
    rng = np.random.default_rng(7)
    ours, theirs = _pair()
    truth = {"alpha": 0.55, "beta": 3.0, "lapse": 0.02}
    for _ in range(40):
        # the same expected entropies at every level (ours easiest first, theirs ascending)
        np.testing.assert_allclose(
            ours.expected_entropy()[::-1], _their_expected_entropy(theirs), rtol=1e-10
        )
        assert ours.level == pytest.approx(theirs.next_stim["intensity"])
        p = predict(ours.level, sigmoid="weibull", gamma=0.5, **truth)
        correct = bool(rng.random() < p)
        theirs.update(
            stim={"intensity": theirs.next_stim["intensity"]},
            outcome={"response": "Correct" if correct else "Incorrect"},
        )
        ours.update(correct)
    np.testing.assert_allclose(
        ours.posterior, theirs.posterior.values.reshape(ours.posterior.shape), atol=1e-12
    )
    estimate = ours.estimate()
    assert estimate["slope"] == pytest.approx(theirs.param_estimate["slope"], rel=1e-9)
    assert estimate["lapse"] == pytest.approx(theirs.param_estimate["lapse_rate"], rel=1e-9)
    # forty trials find a threshold near the truth's midpoint
    mid = truth["alpha"] * np.log(2) ** (1 / truth["beta"])
    assert abs(estimate["threshold"] - mid) < 2.5 * estimate["threshold_sd"] + 0.05


def test_quest_plus_converges_on_a_known_observer_and_beats_chance_placement():
    """Over 20 simulated observers (logistic, midpoint 0.3 on a 0..0.6 grid), 40 trials of
    QUEST+ estimate the midpoint with a small error, and the posterior SD is honest: the
    truth lies within 2 SD in most runs."""
    levels = np.round(np.linspace(0.0, 0.6, 13), 10)
    grid = tuple(f"l{i}" for i in range(len(levels)))[::-1]
    errors, covered = [], 0
    for seed in range(20):
        rng = np.random.default_rng(seed)
        q = QuestPlusStaircase(
            grid=grid,
            levels=tuple(levels[::-1]),
            gamma=0.5,
            thresholds=tuple(np.linspace(0.0, 0.6, 41)),
            slopes=tuple(np.geomspace(2 / 0.6, 50 / 0.6, 9)),
            lapses=(0.0, 0.02, 0.04),
        )
        for _ in range(40):
            p = predict(q.level, sigmoid="logistic", alpha=0.3, beta=20.0, gamma=0.5, lapse=0.02)
            q.update(bool(rng.random() < p))
        est = q.estimate()
        errors.append(est["threshold"] - 0.3)
        covered += abs(est["threshold"] - 0.3) <= 2 * est["threshold_sd"]
    assert np.sqrt(np.mean(np.square(errors))) < 0.06
    assert covered >= 16


def test_quest_plus_is_deterministic_and_takes_the_start_given():
    protocol = load_protocol(protocol_path("gain_questplus"))
    a, b = new_staircase(protocol, "main"), new_staircase(protocol, "main")
    assert isinstance(a, QuestPlusStaircase)
    assert a.grid[0] == "g160"  # easiest first
    answers = [True, True, False, True, True, True, False, True, False, True]
    assert [
        a.record(trial_index=i, condition=a.condition, correct=c) for i, c in enumerate(answers)
    ] == [b.record(trial_index=i, condition=b.condition, correct=c) for i, c in enumerate(answers)]
    fixed = QuestPlusStaircase(
        grid=a.grid,
        levels=a.levels,
        gamma=0.5,
        thresholds=a.thresholds,
        slopes=a.slopes,
        lapses=a.lapses,
        start=0,
    )
    assert fixed.condition == "g160"


def test_resumed_quest_plus_session_continues_the_same_run(tmp_path):
    path = protocol_path("gain_questplus")
    protocol = load_protocol(path)
    simulate_study(protocol, protocol_path=path, results=tmp_path, participants=1, seed=3)
    records = (
        load_results(tmp_path, study=protocol.study.id)
        .sort_values("trial_index")
        .to_dict("records")
    )
    trials = build_trials(protocol, participant="P01")
    assert len({r["condition"] for r in records}) >= 3  # it moved over the grid
    for cut in (1, 9, 29):
        resumed = Staircases(protocol, logged=records[:cut], record=None)
        assert resumed.resolve(trials[cut]) == records[cut]["condition"]


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("rule: quest_plus,", "rule: up_down,", "rule 'up_down' needs a 'start'"),
        ("trials: 30,", "trials: 30, up: 2,", "'up' belongs to rule up_down"),
        ("sigmoid: logistic", "sigmoid: weibull", None),
        (
            "easier: higher, sigmoid: logistic",
            "easier: lower, sigmoid: weibull",
            "use easier: higher",
        ),
        ("easier: higher", "easier: lower", None),
        ("level: 0.05}", "level: -0.05}", None),
        ("lapse_rates: [0.0, 0.02, 0.04]", "lapse_rates: [0.5]", "less than or equal to 0.2"),
        ("lapse_rates: [0.0, 0.02, 0.04]", "lapse_rates: [0.0]", "needs a lapse rate above 0"),
    ],
)
def test_quest_plus_rule_is_validated(tmp_path, old, new, message):
    text = protocol_path("gain_questplus").read_text(encoding="utf-8")
    assert old in text
    path = tmp_path / "p.yaml"
    path.write_text(text.replace(old, new), encoding="utf-8")
    if message is None:  # the variants that are fine
        stair = new_staircase(load_protocol(path), "main")
        if "lower" in new:  # a logistic QUEST+ may run downwards: lower levels easier
            assert stair.grid[0] == "g105" and stair.sign == -1
        elif "weibull" in new:  # every level of the block is > 0
            assert stair.sigmoid == "weibull" and min(stair.levels) > 0
        else:  # a negative level is fine for the logistic, not for the Weibull
            path.write_text(path.read_text().replace("sigmoid: logistic", "sigmoid: weibull"))
            with pytest.raises(ProtocolError, match="needs every level > 0"):
                load_protocol(path)
        return
    with pytest.raises(ProtocolError, match=re.escape(message)):
        load_protocol(path)


def test_quest_plus_in_30_trials_is_as_precise_as_up_down_in_50():
    """The claim in gain_questplus.yaml, on its simulated observer: over 200 runs the RMSE of
    QUEST+'s midpoint after 30 trials is no larger than the 1-up-2-down reversal estimate's
    after 50 (gain_staircase.yaml)."""
    quest = load_protocol(protocol_path("gain_questplus"))
    updown = load_protocol(protocol_path("gain_staircase"))
    obs = quest.simulation.observer

    def rmse(protocol, trials: int) -> float:
        errors = []
        for seed in range(200):
            rng = np.random.default_rng(seed)
            stair = new_staircase(protocol, "main")
            for _ in range(trials):
                p = predict(stair.level, sigmoid="logistic", alpha=obs.midpoint,
                            beta=obs.slope, gamma=0.5, lapse=obs.lapse)  # fmt: skip
                stair.update(bool(rng.random() < p))
            errors.append(stair.estimate()["threshold"] - obs.midpoint)
        return float(np.sqrt(np.mean(np.square(errors))))

    assert rmse(quest, 30) <= rmse(updown, 50)
