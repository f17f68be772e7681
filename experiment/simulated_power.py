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
  over the set's conditions, Greenhouse-Geisser corrected - the primary analysis, on the rows
  ``facelab analyze`` selects (:func:`facelab.analysis.study.rating_cells`: participants
  lacking a condition left out);
* ``identification``: per identify task whose conditions each portray several labels, each
  condition's term of the logistic GEE against the first condition;
* ``trend``: per item x stimulus set of a graded design, the linear trend contrast;
* ``srt``: per speech-in-noise task, the RM ANOVA of the participants' SRTs over the
  condition series and of their benefit against audio alone over the audio-visual series;
* ``timing``: per timing task, the RM ANOVA of the participants' PSS and of their window
  widths over the condition series (Greenhouse-Geisser; windows the data do not determine
  left out).

A run whose fit fails (e.g. every answer in a condition right) counts as not significant
and is counted in ``failed``.

Forced-choice tasks (constant stimuli or staircases) estimate a threshold rather than test
a difference, so for them the question is precision (:func:`protocol_estimates`): the
pooled psychometric midpoint of each simulated study, summarised per n as its mean, its SD
across studies (the standard error a study of that size will have) and its root mean
squared error against the simulated observer's midpoint. Timing tasks add each series'
mean PSS and window width against ``simulation.timing``, and speech-in-noise tasks each
series' mean SRT and benefit against ``simulation.srt``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np
import pandas as pd

from facelab.analysis import graded, identification, psychometric, srt, stats, timing
from facelab.analysis.load import frame_from_rows
from facelab.analysis.study import rating_cells
from facelab.analysis.tasks import (
    choice_outcome,
    compares_conditions,
    graded_ratings,
    in_protocol_order,
    score_identification,
)
from facelab.blas_threads import one_blas_thread
from facelab.errors import AnalysisError, StageError
from facelab.experiment.simulate import check_effects, simulated_rows
from facelab.grid import Cluster, GridTask, run_grid
from facelab.protocol import ChoiceTask, IdentifyTask, Protocol, TypedTask
from facelab.protocol_model import TimingObserver

__all__ = [
    "POWER_COLUMNS",
    "PRECISION_COLUMNS",
    "ProtocolSimulation",
    "estimate_truths",
    "protocol_estimates",
    "protocol_tests",
    "simulated_power",
]

POWER_COLUMNS = ("test", "kind", "n", "sims", "power", "mc_se", "failed")
PRECISION_COLUMNS = ("estimate", "n", "sims", "truth", "mean", "sd", "rmse", "failed")


@dataclass(frozen=True)
class ProtocolSimulation:
    """What :func:`simulated_power` measured: ``power`` (:data:`POWER_COLUMNS`, one row per
    test and n) and ``precision`` (:data:`PRECISION_COLUMNS`, one row per estimate and n)."""

    power: pd.DataFrame
    precision: pd.DataFrame


def protocol_tests(data: pd.DataFrame, protocol: Protocol) -> dict[tuple[str, str], float]:
    """``{(test, kind): p}`` for every test the protocol's analysis makes (see the module);
    a test that cannot be computed on ``data`` has p = NaN."""
    out: dict[tuple[str, str], float] = {}
    for cell in rating_cells(data.dropna(subset=["rating"]), protocol):  # facelab analyze's
        if cell.rm_sub is None:  # selection: one path, participants lacking a condition out
            continue
        try:
            rm = stats.rm_anova(cell.rm_sub, dv="rating", within="condition",
                                subject="participant")  # fmt: skip
            p = float(rm["p_gg"].iloc[0])
        except AnalysisError:
            p = float("nan")
        out[(f"{cell.item.id}/{cell.sset.id}", "rm_anova")] = p
    for task in protocol.tasks:
        if not isinstance(task, IdentifyTask):
            continue
        rows = data[(data["item"] == task.id) & (data["screen"] == task.type)]
        scored = score_identification(rows, task)
        if scored.empty or not compares_conditions(scored) or srt.is_noise_task(protocol, task):
            continue  # (words in noise: compared by their thresholds, below)
        present = [c for c, _ in in_protocol_order(scored, protocol)]
        try:
            p_of = identification.correct_model(scored, conditions=present).set_index("term")["p"]
        except AnalysisError:
            p_of = pd.Series(dtype=float)
        for c in present[1:]:
            p = p_of.get(f"C(condition)[T.{c}]", float("nan"))
            out[(f"{task.id}: {c} vs {present[0]}", "identification")] = float(p)
    for task, table in _srt_estimates(data, protocol):  # thresholds between series
        reference = srt.audio_only_series(protocol)
        _, tests = srt.srt_tests(table, reference=reference)
        visual = {c.series_id for c in protocol.conditions if c.noise is not None} - {reference}
        for measure in ("srt_db", "benefit_db"):  # a benefit is compared between two or more
            if measure == "benefit_db" and (reference is None or len(visual) < 2):
                continue  # audio-visual series (with one, there is nothing to compare)
            row = tests[(tests["measure"] == measure) & (tests["a"] == "all")]
            p = float(row["p_adj"].iloc[0]) if len(row) else float("nan")
            out[(f"{task.id}: {measure} between series", "srt")] = p
    for task, windows in _timing_windows(data, protocol):  # PSS and width between series
        clean = windows[windows["note"] == ""]
        if clean["condition"].nunique() < 2:
            continue
        _, tests = timing.window_tests(windows)
        for measure in ("pss_ms", "width_ms"):
            row = tests[(tests["measure"] == measure) & (tests["a"] == "all")]
            p = float(row["p_adj"].iloc[0]) if len(row) else float("nan")
            out[(f"{task.id}: {measure} between series", "timing")] = p
    graded_vas = graded_ratings(data, protocol)
    if not graded_vas.empty:
        trend = graded.trend_contrast(graded_vas, by=("item", "stimulus_set"))
        for r in trend.itertuples():
            out[(f"{r.item}/{r.stimulus_set}", "trend")] = float(r.p)
    return out


def _timing_windows(
    data: pd.DataFrame, protocol: Protocol
) -> list[tuple[IdentifyTask, pd.DataFrame]]:
    """Each timing task's windows (point estimates only: no intervals are needed here)."""
    out = []
    for task in protocol.tasks:
        if isinstance(task, IdentifyTask) and task.timing is not None:
            rows = data[(data["item"] == task.id) & (data["screen"] == task.type)]
            if not rows.empty:
                windows = timing.window_table(rows, protocol, task, intervals=False)
                out.append((task, windows.assign(note=windows["note"].fillna(""))))
    return out


def _srt_estimates(
    data: pd.DataFrame, protocol: Protocol
) -> list[tuple[IdentifyTask | TypedTask, pd.DataFrame]]:
    """Each speech-in-noise task's SRTs (point estimates only)."""
    out = []
    for task in protocol.tasks:
        if isinstance(task, IdentifyTask | TypedTask) and srt.is_noise_task(protocol, task):
            rows = data[(data["item"] == task.id) & (data["screen"] == task.type)]
            if not rows.empty:
                table = srt.srt_table(rows, protocol, task, intervals=False)
                out.append((task, table.assign(note=table["note"].fillna(""))))
    return out


def estimate_truths(protocol: Protocol) -> dict[str, float]:
    """The simulated truth of each estimate :func:`protocol_estimates` names."""
    out = {f"{t.id} midpoint": protocol.simulation.observer.midpoint
           for t in protocol.tasks if isinstance(t, ChoiceTask)}  # fmt: skip
    reference = srt.audio_only_series(protocol)
    for task in protocol.tasks:
        if isinstance(task, IdentifyTask | TypedTask) and srt.is_noise_task(protocol, task):
            for series, truth in protocol.simulation.srt.items():
                out[f"{task.id} {series} srt_db"] = truth.srt_db
                if reference in protocol.simulation.srt and series != reference:
                    base = protocol.simulation.srt[reference].srt_db
                    out[f"{task.id} {series} benefit_db"] = base - truth.srt_db
        if isinstance(task, IdentifyTask) and task.timing is not None:
            for series in dict.fromkeys(c.series_id for c in protocol.conditions):
                truth = protocol.simulation.timing.get(series, TimingObserver())
                out[f"{task.id} {series} pss_ms"] = truth.pss_ms
                out[f"{task.id} {series} width_ms"] = truth.width_ms
    return out


def protocol_estimates(data: pd.DataFrame, protocol: Protocol) -> dict[str, float]:
    """``{"<task> midpoint": value}``: each forced-choice task's pooled psychometric midpoint
    (maximum likelihood, the task's guess rate, logistic); NaN when the fit fails. For a
    timing task, ``"<task> <series> pss_ms"`` and ``"… width_ms"``: the mean of the
    participants' windows (those the data determine)."""
    out: dict[str, float] = {}
    for task, table in _srt_estimates(data, protocol):
        clean = table[table["note"] == ""]
        for series in dict.fromkeys(table["condition"]):
            mine = clean[clean["condition"] == series]
            for measure in ("srt_db", "benefit_db"):
                values = mine[measure].dropna()
                if measure == "srt_db" or len(values):
                    out[f"{task.id} {series} {measure}"] = (
                        float(values.mean()) if len(values) else float("nan"))
    for task, windows in _timing_windows(data, protocol):
        clean = windows[windows["note"] == ""]
        for series in dict.fromkeys(windows["condition"]):
            mine = clean[clean["condition"] == series]
            for measure in ("pss_ms", "width_ms"):
                value = float(mine[measure].mean()) if len(mine) else float("nan")
                out[f"{task.id} {series} {measure}"] = value
    for task in protocol.tasks:
        if not isinstance(task, ChoiceTask):
            continue
        rows = data[(data["item"] == task.id) & (data["screen"] == task.type)]
        if rows.empty:
            continue
        y, gamma = choice_outcome(rows, task)
        counts = psychometric.count_responses(rows.assign(y=y.to_numpy()), x="level", y="y")
        try:
            fit = psychometric.fit_psychometric(counts, gamma=gamma)
            value = fit.midpoint if fit.converged else float("nan")
        except AnalysisError:
            value = float("nan")
        out[f"{task.id} midpoint"] = float(value)
    return out


def _one_study(
    study: tuple[Protocol, list[str], np.random.Generator, Mapping[str, float] | None],
) -> tuple[dict[tuple[str, str], float], dict[str, float]]:
    """One simulated study of participants ``ids``, analysed: (tests, estimates). Numpy's
    BLAS is held to one thread (:func:`facelab.blas_threads.one_blas_thread`)."""
    protocol, ids, study_rng, effects = study
    with one_blas_thread():
        log = [
            row
            for pid, child in zip(ids, study_rng.spawn(len(ids)), strict=True)
            for row in simulated_rows(protocol, participant=pid, rng=child, effects=effects)
        ]
        data = frame_from_rows(log)
        return protocol_tests(data, protocol), protocol_estimates(data, protocol)


def _study_chunk(studies: list) -> list:
    return [_one_study(study) for study in studies]


def _on_cluster(studies: list, cluster: Cluster) -> list:
    """The studies' outcomes, in study order, computed on ``cluster`` (chunks of studies: one
    study is milliseconds, less than a task's round trip)."""
    size = max(1, len(studies) // 64)
    chunks = [studies[i : i + size] for i in range(0, len(studies), size)]
    report = run_grid(
        [GridTask(f"studies-{i:05d}", _study_chunk, (chunk,)) for i, chunk in enumerate(chunks)],
        cluster=cluster,
    )
    if report.failed:
        raise StageError("; ".join(f"{k}: {why}" for k, why in sorted(report.failed.items())))
    return [o for i in range(len(chunks)) for o in report.results[f"studies-{i:05d}"]]


def simulated_power(
    protocol: Protocol,
    *,
    n_values: Sequence[int],
    sims: int,
    rng: np.random.Generator,
    alpha: float = 0.05,
    effects: Mapping[str, float] | None = None,
    progress: Callable[[int, float], None] | None = None,
    jobs: int = 1,
    cluster: Cluster | None = None,
) -> ProtocolSimulation:
    """Power of every test and precision of every estimate of ``protocol`` for each number
    of participants in ``n_values`` (``sims`` simulated studies each, drawn from ``rng``).
    ``effects`` replaces ``simulation.effects``; ``progress(n, seconds)`` is called after
    each n. ``jobs`` > 1 runs the studies in that many processes; every study draws from its
    own generator spawned from ``rng`` beforehand, so the result does not depend on ``jobs``.
    A Dask ``cluster`` (``--workers``/``--scheduler``) takes the place of ``jobs``: the
    studies go to it in chunks, with the same result."""
    if sims < 2:
        raise StageError(f"--sims must be at least 2, got {sims}")
    bad = [n for n in n_values if n < 2]
    if bad or not n_values:
        raise StageError(f"numbers of participants must be 2 or more, got {list(n_values)}")
    if not 0 < alpha < 1:
        raise StageError(f"alpha must lie strictly between 0 and 1, got {alpha}")
    if jobs < 1:
        raise StageError(f"--jobs must be at least 1, got {jobs}")
    check_effects(protocol, effects)
    truths = estimate_truths(protocol)
    power_rows, precision_rows = [], []
    for n in n_values:
        started = time.perf_counter()
        width = max(2, len(str(n)))
        ids = [f"P{i:0{width}d}" for i in range(1, n + 1)]
        p_values: dict[tuple[str, str], list[float]] = {}
        estimates: dict[str, list[float]] = {}
        studies = [(protocol, ids, study_rng, effects) for study_rng in rng.spawn(sims)]
        if cluster is not None and not cluster.serial:
            outcomes = _on_cluster(studies, cluster)
        elif jobs > 1:
            with ProcessPoolExecutor(max_workers=jobs) as pool:
                outcomes = list(pool.map(_one_study, studies, chunksize=max(1, sims // jobs // 4)))
        else:
            outcomes = [_one_study(study) for study in studies]
        for tests, values in outcomes:  # in study order, whatever the number of jobs
            for key, p in tests.items():
                p_values.setdefault(key, []).append(p)
            for key, value in values.items():
                estimates.setdefault(key, []).append(value)
        if progress is not None:
            progress(n, time.perf_counter() - started)
        for (test, kind), ps in p_values.items():
            arr = np.asarray(ps, dtype=float)
            power = float(np.sum(arr < alpha) / sims)
            power_rows.append(
                {
                    "test": test,
                    "kind": kind,
                    "n": n,
                    "sims": sims,
                    "power": power,
                    "mc_se": float(np.sqrt(power * (1 - power) / sims)),
                    # a run without the test (its fit refused) failed too
                    "failed": int(np.isnan(arr).sum()) + sims - len(arr),
                }
            )
        for name, values in estimates.items():
            arr = np.asarray(values, dtype=float)
            ok = arr[np.isfinite(arr)]
            truth = truths.get(name, float("nan"))
            precision_rows.append(
                {
                    "estimate": name,
                    "n": n,
                    "sims": sims,
                    "truth": truth,
                    "mean": float(ok.mean()) if len(ok) else float("nan"),
                    "sd": float(ok.std(ddof=1)) if len(ok) > 1 else float("nan"),
                    "rmse": float(np.sqrt(np.mean((ok - truth) ** 2))) if len(ok) else float("nan"),
                    "failed": sims - len(ok),
                }
            )
    if not power_rows and not precision_rows:
        raise StageError(
            f"protocol {protocol.study.id!r} has nothing to simulate: no VAS item compared "
            "between conditions, identification compared between conditions, graded design "
            "or forced-choice task"
        )
    return ProtocolSimulation(
        power=pd.DataFrame(power_rows, columns=list(POWER_COLUMNS)),
        precision=pd.DataFrame(precision_rows, columns=list(PRECISION_COLUMNS)),
    )
