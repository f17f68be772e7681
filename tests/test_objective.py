"""The objective measures as per-stimulus covariates of the ratings (issue 49.4):
``objective_covariate`` recovers a known slope of the rating on a clip's tracked aperture
correlation within conditions, covers 0 when the ratings do not follow it, and says in words
when the slope cannot be estimated."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from facelab.analysis.objective import COVARIATE_COLUMNS, objective_covariate


def _study(
    *, slope: float, rng: np.random.Generator, stimuli: int = 6, participants: int = 24
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """objective.csv rows (tracked aperture correlation per condition x stimulus against the
    reference ``human``) and VAS ratings: 50 + condition effect + slope * x + participant
    intercept + noise."""
    conditions = {"viseme": -8.0, "vowel": 4.0}
    objective, ratings = [], []
    x = {(c, k): float(rng.uniform(0.3, 0.95)) for c in conditions for k in range(stimuli)}
    for (c, k), value in x.items():
        objective.append({"stimulus_set": "s", "stimulus": f"t{k}", "condition": c,
                          "reference": "human", "measure": "aperture_correlation",
                          "channel": "tracked", "value": value, "unit": "r"})  # fmt: skip
    for p in range(participants):
        intercept = rng.normal(0, 8)
        for (c, k), value in x.items():
            for cond in (c, "human") if c == "viseme" else (c,):
                xv = value if cond != "human" else np.nan
                effect = conditions.get(cond, 10.0) + (slope * value if cond != "human" else 0)
                ratings.append({"participant": f"P{p:02d}", "item": "natural",
                                "condition": cond, "stimulus_set": "s", "stimulus": f"t{k}",
                                "rating": 50 + effect + intercept + rng.normal(0, 6),
                                "x": xv})  # fmt: skip
    return pd.DataFrame(objective), pd.DataFrame(ratings)


def test_a_known_slope_is_recovered_within_conditions() -> None:
    objective, vas = _study(slope=30.0, rng=np.random.default_rng(11))
    table = objective_covariate(objective, vas)
    assert list(table.columns) == list(COVARIATE_COLUMNS)
    (row,) = table.to_dict("records")
    assert row["item"] == "natural" and row["measure"] == "aperture_correlation"
    assert row["ci_low"] < 30.0 < row["ci_high"] and row["p"] < 0.001
    assert abs(row["estimate"] - 30.0) < 3 * row["se"]
    # the reference's own ratings have no measure: left out, not imputed
    assert row["n_ratings"] == 24 * 12 and row["n_cells"] == 12 and row["n_participants"] == 24


def test_ratings_that_do_not_follow_the_measure_give_an_interval_over_zero() -> None:
    covered = 0
    for seed in range(20):
        objective, vas = _study(slope=0.0, rng=np.random.default_rng(100 + seed))
        (row,) = objective_covariate(objective, vas).to_dict("records")
        covered += row["ci_low"] < 0 < row["ci_high"]
    assert covered >= 17  # nominal 95 %: 19 of 20 expected, 17 is p < 0.08 by chance


@pytest.mark.parametrize(
    ("stimuli", "participants", "said"),
    [(1, 10, "does not vary between the stimuli"), (4, 1, "fewer than 2 participants")],
)
def test_a_slope_that_cannot_be_estimated_is_said_in_words(
    stimuli: int, participants: int, said: str
) -> None:
    objective, vas = _study(slope=10.0, rng=np.random.default_rng(3), stimuli=stimuli,
                            participants=participants)  # fmt: skip
    (row,) = objective_covariate(objective, vas).to_dict("records")
    assert row["procedure"] == "not estimable" and said in row["note"]
    assert np.isnan(row["estimate"])


def test_nothing_without_tracking() -> None:
    objective, vas = _study(slope=10.0, rng=np.random.default_rng(3))
    objective["channel"] = "jawOpen"
    assert objective_covariate(objective, vas).empty
