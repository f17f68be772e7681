"""Power of a whole protocol by simulation: how many participants does this study need?

The closed-form power of :mod:`facelab.analysis.power` covers one repeated-measures ANOVA.
A study with an identification task compared between conditions, a graded design or
several items has no such formula; here the protocol's own ``simulation`` section is taken
as the truth (effects in VAS points, identifier accuracy per condition, the variance
components of the rating model) and the study is run ``sims`` times in memory for each
number of participants - the same design (counterbalancing, randomisation, staircases),
timeline and answer models as ``facelab simulate`` - and analysed as ``facelab analyze``
analyses it. Power is the share of runs in which a test reaches ``p < alpha``; its Monte
Carlo standard error is ``sqrt(power (1 - power) / sims)``.

The tests of a protocol (:func:`protocol_tests`):

* ``rm_anova``: per VAS item x stimulus set, the one-way RM ANOVA on participant means
  over the set's conditions, Greenhouse-Geisser corrected (the primary analysis);
* ``identification``: per identify task whose conditions each portray several labels, each
  condition's term of the logistic GEE against the first condition;
* ``trend``: per item x stimulus set of a graded design, the linear trend contrast.

A run whose fit fails (e.g. every answer in a condition right) counts as not significant
and is counted in ``failed``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd

from facelab.analysis import graded, identification, stats
from facelab.analysis.load import frame_from_rows
from facelab.analysis.tasks import (
    compares_conditions,
    graded_ratings,
    in_protocol_order,
    score_identification,
)
from facelab.errors import AnalysisError, StageError
from facelab.experiment.simulate import simulated_rows
from facelab.protocol import IdentifyTask, Protocol

__all__ = ["POWER_COLUMNS", "protocol_tests", "simulated_power"]

POWER_COLUMNS = ("test", "kind", "n", "sims", "power", "mc_se", "failed")


def protocol_tests(data: pd.DataFrame, protocol: Protocol) -> dict[tuple[str, str], float]:
    """``{(test, kind): p}`` for every test the protocol's analysis makes (see the module);
    a test that cannot be computed on ``data`` has p = NaN."""
    out: dict[tuple[str, str], float] = {}
    rating_blocks = {b.id for b in protocol.blocks if b.task is None}
    vas = data[(data["screen"].fillna("vas") == "vas") & data["block"].isin(rating_blocks)]
    vas = vas.dropna(subset=["rating"])
    for (item, sset), part in vas.groupby(["item", "stimulus_set"], sort=True):
        if part["condition"].nunique() < 2:
            continue
        try:
            rm = stats.rm_anova(part, dv="rating", within="condition", subject="participant")
            p = float(rm["p_gg"].iloc[0])
        except AnalysisError:
            p = float("nan")
        out[(f"{item}/{sset}", "rm_anova")] = p
    for task in protocol.tasks:
        if not isinstance(task, IdentifyTask):
            continue
        rows = data[(data["item"] == task.id) & (data["screen"] == task.type)]
        scored = score_identification(rows, task)
        if scored.empty or not compares_conditions(scored):
            continue
        present = [c for c, _ in in_protocol_order(scored, protocol)]
        try:
            model = identification.correct_model(scored, conditions=present)
        except AnalysisError:
            for c in present[1:]:
                out[(f"{task.id} C(condition)[T.{c}]", "identification")] = float("nan")
            continue
        for r in model[model["term"].str.startswith("C(")].itertuples():
            out[(f"{task.id} {r.term}", "identification")] = float(r.p)
    graded_vas = graded_ratings(data, protocol)
    if not graded_vas.empty:
        trend = graded.trend_contrast(graded_vas, by=("item", "stimulus_set"))
        for r in trend.itertuples():
            out[(f"{r.item}/{r.stimulus_set}", "trend")] = float(r.p)
    return out


def simulated_power(
    protocol: Protocol,
    *,
    n_values: Sequence[int],
    sims: int,
    rng: np.random.Generator,
    alpha: float = 0.05,
    effects: Mapping[str, float] | None = None,
) -> pd.DataFrame:
    """Power of every test of ``protocol`` for each number of participants in ``n_values``
    (``sims`` simulated studies each, drawn from ``rng``); one row per test and n
    (:data:`POWER_COLUMNS`). ``effects`` replaces ``simulation.effects``."""
    if sims < 2:
        raise StageError(f"--sims must be at least 2, got {sims}")
    bad = [n for n in n_values if n < 2]
    if bad or not n_values:
        raise StageError(f"numbers of participants must be 2 or more, got {list(n_values)}")
    if not 0 < alpha < 1:
        raise StageError(f"alpha must lie strictly between 0 and 1, got {alpha}")
    rows = []
    for n in n_values:
        width = max(2, len(str(n)))
        ids = [f"P{i:0{width}d}" for i in range(1, n + 1)]
        hits: dict[tuple[str, str], int] = {}
        failed: dict[tuple[str, str], int] = {}
        present: dict[tuple[str, str], int] = {}
        for study_rng in rng.spawn(sims):
            log = [
                row
                for pid, child in zip(ids, study_rng.spawn(n), strict=True)
                for row in simulated_rows(protocol, participant=pid, rng=child, effects=effects)
            ]
            for key, p in protocol_tests(frame_from_rows(log), protocol).items():
                hits.setdefault(key, 0)
                failed.setdefault(key, 0)
                present[key] = present.get(key, 0) + 1
                if np.isnan(p):
                    failed[key] += 1
                elif p < alpha:
                    hits[key] += 1
        for (test, kind), k in hits.items():
            power = k / sims
            rows.append(
                {
                    "test": test,
                    "kind": kind,
                    "n": n,
                    "sims": sims,
                    "power": power,
                    "mc_se": float(np.sqrt(power * (1 - power) / sims)),
                    # a run without the test (its fit refused) failed too
                    "failed": failed[(test, kind)] + sims - present[(test, kind)],
                }
            )
    if not rows:
        raise StageError(
            f"protocol {protocol.study.id!r} has no test to simulate (VAS items compared "
            "between conditions, an identification compared between conditions, or a graded "
            "design)"
        )
    return pd.DataFrame(rows, columns=list(POWER_COLUMNS))
