"""The analyses of a protocol's tasks and graded designs, as tidy tables and figures.

* forced choice (``choice_2afc``), constant stimuli or staircase: a psychometric fit of each
  participant and of everyone pooled (:mod:`facelab.analysis.psychometric`); y is "correct"
  when the task has a correct answer (guess rate 1/2), "chose the comparison" for a
  preference (guess rate 0); x is the comparison's level. Given a :class:`DesignSampler`
  (``facelab analyze`` passes one that runs the protocol's own design), each participant's
  profile intervals are calibrated on 200 participants simulated at the pooled estimate
  (:func:`calibrate_design`). A session with fewer trials than the design (stopped early) is
  calibrated on complete sessions and its note says so: calibrating it on simulated sessions
  cut as early was tried and held the slope less often (every session of 8 cut after 25
  staircase / 30 constant-stimuli trials, seed 23: 0.89 / 0.87 against 0.945 / 0.91);
* staircases: also the rule's own estimate per participant - the mean level of the last
  reversals (up-down) or the posterior mean of the midpoint with its SD (QUEST+);
* identification: confusion matrix, accuracy, per-class recall and Cohen's kappa
  (:mod:`facelab.analysis.identification`); when two or more conditions each portray
  several labels (e.g. emotions under two behaviour conditions), also accuracy and kappa per
  condition, a confusion matrix per condition, and a logistic GEE of a right answer on the
  condition;
* audio-visual timing (an identify task with ``timing``): each participant's window of
  simultaneity or temporal-order function per condition series over the conditions'
  ``audio_offset_ms`` (``sync_window``), the series' means and their within-participant
  comparison (``sync_summary``, ``sync_tests``; :mod:`facelab.analysis.timing`);
* typed answers (a ``typed`` task): every answer beside what was said with its score
  (``typed_answers``) and the mean score per condition (``typed_summary``); a word matrix
  also each word position's share right per condition and its commonest confusion
  (``matrix_words``);
* speech in noise (an identify task with answers, or a typed task, on conditions with
  ``noise``): each
  participant's speech reception threshold per condition series, the audio-visual benefit
  against the audio-only series and Sumby-Pollack's visual enhancement (``srt``), the series'
  means and comparison (``srt_summary``, ``srt_tests``; :mod:`facelab.analysis.srt`);
* graded VAS designs (every condition of the item's block has a level): the linear trend
  contrast and the random-slope mixed model (:mod:`facelab.analysis.graded`).

:func:`analyze_tasks` returns :class:`TaskResults`: named tables (written as CSV) and
figure specifications the report draws.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

import facelab.analysis.graded as graded
import facelab.analysis.identification as identification
import facelab.analysis.psychometric as psychometric
import facelab.analysis.srt as srt
import facelab.analysis.stats as stats
import facelab.analysis.timing as timing
from facelab.analysis.pilot import below_chance
from facelab.errors import AnalysisError
from facelab.protocol import (
    ChoiceTask,
    IdentifyTask,
    MatrixTask,
    Protocol,
    Stimulus,
    TypedTask,
)
from facelab.staircase import (
    QuestPlusStaircase,
    Staircase,
    UpDownStaircase,
    convergence_probability,
    new_staircase,
)

__all__ = [
    "DesignCalibration",
    "DesignSampler",
    "TaskResults",
    "analyze_tasks",
    "calibrate_design",
    "choice_outcome",
    "compares_conditions",
    "graded_ratings",
    "in_protocol_order",
    "score_identification",
]


@dataclass
class TaskResults:
    tables: dict[str, pd.DataFrame] = field(default_factory=dict)
    # (task, pooled counts, fitted curves, gamma) per choice task
    psychometric: list[tuple[ChoiceTask, pd.DataFrame, pd.DataFrame, float]] = field(
        default_factory=list
    )
    # (task, confusion matrix) per identify task
    confusion: list[tuple[IdentifyTask, pd.DataFrame]] = field(default_factory=list)
    # (task, {condition: confusion matrix}) per identify task whose conditions are compared
    confusion_by_condition: list[tuple[IdentifyTask, dict[str, pd.DataFrame]]] = field(
        default_factory=list
    )
    # (task, trials per participant x series x SNR, SRT table) per speech-in-noise task
    srt: list[tuple[IdentifyTask | TypedTask, pd.DataFrame, pd.DataFrame]] = field(
        default_factory=list
    )
    # (task, counts per participant x series x offset, windows) per timing task
    timing: list[tuple[IdentifyTask, pd.DataFrame, pd.DataFrame]] = field(default_factory=list)
    # task id -> its scored identification answers (target and correct columns added)
    identification_trials: dict[str, pd.DataFrame] = field(default_factory=dict)
    # (task, block id, track, thresholds) per staircase block
    staircases: list[tuple[ChoiceTask | IdentifyTask, str, pd.DataFrame, pd.DataFrame]] = field(
        default_factory=list
    )
    notes: list[str] = field(default_factory=list)

    @property
    def empty(self) -> bool:
        return not self.tables


def choice_outcome(rows: pd.DataFrame, task: ChoiceTask) -> tuple[pd.Series, float]:
    """(y, gamma): 'correct' for a scored task (gamma 1/2), else 'chose the comparison'."""
    if task.correct == "comparison":
        return rows["correct"].astype(float), 0.5
    return (rows["response"] == rows["condition"]).astype(float), 0.0


def _curves(fits: pd.DataFrame, levels: np.ndarray) -> pd.DataFrame:
    grid = np.linspace(levels.min(), levels.max(), 121)
    parts = []
    for fit in fits.itertuples():
        if not fit.converged or not np.isfinite(fit.alpha):
            continue
        p = psychometric.predict(
            grid,
            sigmoid=fit.sigmoid,
            alpha=fit.alpha,
            beta=fit.slope,
            gamma=fit.gamma,
            lapse=fit.lapse,
        )
        parts.append(pd.DataFrame({"participant": fit.participant, "level": grid, "p": p}))
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()


def _staircase_tables(
    rows: pd.DataFrame, protocol: Protocol, block_id: str
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Each participant's staircase replayed from the log: (thresholds, one row per
    participant and session - a session runs its own staircase; track, one row per step:
    the level shown, the answer, reversals)."""
    out, track = [], []
    rule = next(b.staircase for b in protocol.blocks if b.id == block_id)
    keys = ["participant", "session"] if "session" in rows else ["participant"]
    for key, part in rows.sort_values("trial_index").groupby(keys, sort=True):
        pid, session = (key[0], key[1]) if len(keys) == 2 else (key[0], 1)
        state = new_staircase(protocol, block_id)
        try:
            steps = state.replay(
                zip(
                    part["trial_index"],
                    part["condition"],
                    part["correct"].astype(bool),
                    [None if pd.isna(v) else float(v) for v in part["score"]],
                    strict=True,
                )
            )
        except ValueError as exc:
            raise AnalysisError(
                f"participant {pid} session {session}, staircase of block {block_id!r}: {exc}"
            ) from None
        track += [
            {
                "participant": pid,
                "session": int(session),
                "block": block_id,
                "step": k,
                "trial_index": st["trial_index"],
                "level": st["level"],
                "correct": int(st["correct"]),
                "score": st["score"],
                "reversal": bool(st["reversal"]),
                "threshold": st["threshold"],
            }
            for k, st in enumerate(steps, start=1)
        ]
        estimate = state.estimate()
        threshold = estimate.pop("threshold")
        out.append(
            {
                "participant": pid,
                "session": int(session),
                "block": block_id,
                "rule": rule.rule if rule else None,
                "estimate": estimate.pop("estimate"),
                "trials": state.trials,
                "reversals": len(state.reversals),
                "threshold": threshold,
                "threshold_sd": float("nan"),
                **estimate,
                "last_level": float(part["level"].iloc[-1]),
                "note": _track_note(part["level"].to_numpy(dtype=float), state=state,
                                    threshold=threshold,
                                    correct=part["correct"].astype(bool).to_numpy()),
            }
        )
    return pd.DataFrame(out), pd.DataFrame(track)


def _track_note(
    shown: np.ndarray, *, state: Staircase, threshold: float, correct: np.ndarray
) -> str:
    """What a staircase's threshold cannot say - the participant's threshold lies beyond the
    levels rendered, so the estimate is a bound, whatever its rule's interval says: an end
    level answered right less often (easiest) or more often (hardest) than the rule aims at,
    by a one-sided binomial test at 0.05 (an up-down rule's convergence point; QUEST+'s
    midpoint, halfway from guessing to always right); for QUEST+, a posterior whose most
    likely threshold is an end of its grid with 30 % or more of it; for up-down, fewer right
    over the whole track than it converges on; for up-down and Brand-Kollmeier, a track that
    kept to an end of its grid in at least half of its second half (QUEST+ places trials
    for information, often at an end, so not that); or no estimate at all (no reversal).
    ``state``: the replayed staircase; ``shown``/``correct``: the trials' levels and answers
    in order."""
    from scipy import stats as sps

    levels = state.levels  # easiest first
    bound = ("the threshold lies at or beyond that end of the levels rendered - a bound, not "
             "an estimate (render levels beyond it)")  # fmt: skip
    target = None
    if isinstance(state, UpDownStaircase):
        target = convergence_probability(up=state.up, down=state.down)
    elif isinstance(state, QuestPlusStaircase):
        target = state.gamma + (1.0 - state.gamma) / 2
    if target is not None:
        for end, where in ((levels[0], "easiest"), (levels[-1], "hardest")):
            at = np.isclose(shown, end)
            n, k = int(at.sum()), int(correct[at].sum())
            if n < 5:
                continue
            p = sps.binom.cdf(k, n, target) if where == "easiest" else sps.binom.sf(k - 1, n,
                                                                                   target)
            if p < 0.05:
                fewer = "fewer" if where == "easiest" else "more"
                return (f"at the grid's {where} level ({end:g}) {k} of {n} right, {fewer} than "
                        f"the rule aims at ({target:.1%}) allows (binomial p = {p:.2g}): "
                        f"{bound}")  # fmt: skip
    if isinstance(state, QuestPlusStaircase):
        marginal = state.posterior.sum(axis=(1, 2))
        top = int(np.argmax(marginal))
        # 0.3: at the shipped gain_questplus grid, 0-3 of 150 simulated observers whose
        # threshold lies inside it, 86 / 138 of 150 beyond either end (stop 82)
        if top in (0, len(marginal) - 1) and marginal[top] >= 0.3:
            return (f"the posterior's most likely threshold is the end of its grid "
                    f"({state.thresholds[top]:g}, {marginal[top]:.0%} of it there): "
                    f"{bound}")  # fmt: skip
    if isinstance(state, UpDownStaircase):
        n, k = len(correct), int(correct.sum())
        p = sps.binom.cdf(k, n, target)
        if n >= 10 and p < 0.05:  # never near the target anywhere: the grid is too hard
            return (f"{k} of {n} right over the whole track, fewer than the rule converges on "
                    f"({target:.1%}; binomial p = {p:.2g}): no level rendered is easy "
                    "enough - the threshold lies at or beyond the grid's easiest end "
                    f"({levels[0]:g}), a bound, not an estimate (render easier "
                    "levels)")  # fmt: skip
    if not isinstance(state, QuestPlusStaircase):
        late = shown[len(shown) // 2:]
        for end, where in ((levels[-1], "hardest"), (levels[0], "easiest")):
            at = int(np.sum(np.isclose(late, end)))
            if len(late) >= 2 and at * 2 >= len(late):
                return (f"the track kept to the grid's {where} level ({end:g}) in {at} of its "
                        f"last {len(late)} trials: {bound}")  # fmt: skip
    if math.isnan(threshold):
        return f"no threshold: {len(state.reversals)} reversal(s) in {len(shown)} trials"
    return ""


#: (task id, observer midpoint, logistic slope, lapse, generator) -> the rows of one simulated
#: participant answering that task through the protocol's design (staircase or constant
#: stimuli) as that observer; ``facelab.experiment.simulate.design_sampler`` makes one
DesignSampler = Callable[[str, float, float, float, np.random.Generator], pd.DataFrame]

#: the columns of a :data:`DesignSampler`'s rows that the calibration reads (a sampler may
#: return only these: it runs hundreds of times per task)
SAMPLED_COLUMNS = ("item", "screen", "level", "correct", "response", "condition")

#: simulated participants per calibration
CALIBRATION_PARTICIPANTS = 200


@dataclass
class DesignCalibration:
    """Participants simulated through a task's design at a known truth (the pooled
    posterior mode), for calibrating profile intervals: ``samples`` the answer counts
    (``level, n, k``) of each."""

    gamma: float
    midpoint: float
    slope: float
    samples: list[pd.DataFrame]

    @property
    def full_trials(self) -> int:
        """Trials of a complete simulated session (the longest, for a variable design)."""
        return max(int(s["n"].sum()) for s in self.samples)

    def drops(self) -> tuple[float, float] | None:
        """The drops (midpoint, width) at which the profile intervals of these simulated
        participants hold the truth 95 % of the time
        (:func:`facelab.analysis.bayes_psychometric.calibrated_drops`); None when too few of
        them can be fitted. Complete sessions: calibrating a session stopped early on
        simulated sessions cut as early was tried and covered the slope less well (module
        doc)."""
        from facelab.analysis.bayes_psychometric import calibrated_drops

        try:
            return calibrated_drops(
                self.samples, gamma=self.gamma, midpoint=self.midpoint, slope=self.slope
            )
        except AnalysisError:
            return None


def calibrate_design(
    trials: pd.DataFrame,
    task: ChoiceTask,
    *,
    gamma: float,
    sampler: DesignSampler,
    rng: np.random.Generator,
    n: int = CALIBRATION_PARTICIPANTS,
) -> DesignCalibration | None:
    """``n`` participants simulated by ``sampler`` through ``task``'s design as an observer at
    the posterior mode of everyone's ``trials`` pooled (columns ``level, y``), for
    calibrating each participant's intervals (:meth:`DesignCalibration.drops`). None when
    the pooled answers cannot be fitted (one level only). ``gamma``: the guess rate."""
    from tqdm import tqdm

    from facelab.analysis.bayes_psychometric import posterior_fit

    pooled = psychometric.count_responses(trials, x="level", y="y")
    try:
        truth = posterior_fit(pooled, gamma=gamma)
    except AnalysisError:
        return None
    samples = []
    quiet = not sys.stderr.isatty()
    for child in tqdm(rng.spawn(n), desc="calibrating intervals", leave=False, disable=quiet):
        rows = sampler(task.id, truth.midpoint, truth.slope, truth.lapse, child)
        rows = rows[(rows["item"] == task.id) & (rows["screen"] == task.type)]
        if rows.empty:
            continue
        y, _ = choice_outcome(rows, task)
        # counted without count_responses' checks: the simulation answers every trial 0/1
        level = pd.to_numeric(rows["level"], errors="coerce").to_numpy(dtype=float)
        samples.append(psychometric.level_counts(level=level, y=y.to_numpy(dtype=float)))
    if not samples:
        return None
    return DesignCalibration(gamma, truth.midpoint, truth.slope, samples)


def _name_short_sessions(fits: pd.DataFrame, trials: pd.DataFrame, full: int) -> None:
    """Add to the ``note`` of each participant with fewer of the task's trials than a
    complete simulated session (``full``) that its intervals were calibrated on complete
    sessions."""
    done = trials.groupby("participant", sort=True).size()
    for pid, k in done[done < full].items():
        at = fits["participant"] == pid
        fits.loc[at, "note"] = fits.loc[at, "note"] + (
            f"; this session has {k} of the design's {full} trials (calibrated on complete "
            "sessions)"
        )


def analyze_tasks(
    data: pd.DataFrame,
    protocol: Protocol,
    *,
    rng: np.random.Generator,
    n_boot: int = 200,
    sampler: DesignSampler | None = None,
) -> TaskResults:
    """Every task and graded-design analysis the protocol calls for (see the module);
    ``sampler`` calibrates each participant's psychometric intervals on the design."""
    res = TaskResults()
    psy_tables, stair_tables, stair_tracks = [], [], []
    id_summary, id_recall, id_matrix = [], [], []
    id_by_condition, id_models = [], []
    for task in protocol.tasks:
        rows = data[(data["item"] == task.id) & (data["screen"] == task.type)]
        if rows.empty:
            res.notes.append(f"no answers for task {task.id!r}: not analysed")
            continue
        for block in protocol.blocks:  # forced choice or identification: scored answers
            if block.task == task.id and block.design == "staircase":
                part = rows[rows["block"] == block.id]
                if not part.empty:
                    thresholds, track = _staircase_tables(part, protocol, block.id)
                    stair_tables.append(thresholds)
                    stair_tracks.append(track)
                    res.staircases.append((task, block.id, track, thresholds))
        if isinstance(task, ChoiceTask):
            y, gamma = choice_outcome(rows, task)
            trials = rows.assign(y=y.to_numpy())
            res.notes.extend(below_chance(trials, task=task.id, chance=gamma))
            drops, calibration = None, None
            if sampler is not None:  # its own generator: the bootstrap's draws stay as they were
                calibration = calibrate_design(
                    trials, task, gamma=gamma, sampler=sampler, rng=rng.spawn(1)[0]
                )
                drops = calibration.drops() if calibration is not None else None
                if drops is None:
                    res.notes.append(
                        f"task {task.id!r}: the intervals were not calibrated (the pooled "
                        "answers or the simulated ones cannot be fitted)"
                    )
            fits = stats.psychometric(  # a participant's few trials: the posterior
                trials, level="level", correct="y", subject="participant", pooled=True,
                gamma=gamma, n_boot=n_boot, rng=rng, per_subject="posterior", drops=drops,
            ).rename(columns={"subject": "participant"})  # fmt: skip
            if drops is not None and calibration is not None:
                _name_short_sessions(fits, trials, calibration.full_trials)
            psy_tables.append(fits.assign(task=task.id, gamma=gamma))
            counts = psychometric.count_responses(trials, x="level", y="y")
            curves = _curves(fits, counts["level"].to_numpy(dtype=float))
            res.psychometric.append((task, counts, curves, gamma))
        elif isinstance(task, TypedTask):  # typed answers: scores, thresholds in noise
            _typed_tables(rows, protocol, task, res)
            if srt.is_noise_task(protocol, task):
                _srt_tables(rows, protocol, task, res)
        elif task.timing is not None:  # a synchrony task: windows over the audio offsets
            _timing_tables(rows, protocol, task, res)
        else:
            in_noise = srt.is_noise_task(protocol, task)
            if in_noise:  # words in noise: thresholds per series (not per-condition models)
                _srt_tables(rows, protocol, task, res)
            labels = [lb.id for lb in task.labels]
            if not task.answers:
                res.notes.append(
                    f"task {task.id!r} names no answers: only the answer counts are tabled"
                )
            scored = score_identification(rows, task)
            if not scored.empty:
                res.identification_trials[task.id] = scored
                summary, recall = identification.identification_summary(scored, labels=labels)
                matrix = identification.confusion_matrix(scored, labels=labels)
                id_summary.append(summary.assign(task=task.id))
                id_recall.append(recall.assign(task=task.id))
                long = matrix.stack().rename("count").reset_index()
                id_matrix.append(long.assign(task=task.id))
                res.confusion.append((task, matrix))
                if compares_conditions(scored) and not in_noise:
                    parts = in_protocol_order(scored, protocol)
                    by_cond, cond_model = _identification_by_condition(scored, parts, task, res)
                    id_by_condition.append(by_cond)
                    if cond_model is not None:
                        id_models.append(cond_model)
                    res.confusion_by_condition.append(
                        (
                            task,
                            {
                                c: identification.confusion_matrix(part, labels=labels)
                                for c, part in parts
                            },
                        )
                    )
    if psy_tables:
        res.tables["psychometric_fits"] = _first(pd.concat(psy_tables, ignore_index=True), "task")
    if stair_tables:
        res.tables["staircase_thresholds"] = pd.concat(stair_tables, ignore_index=True)
        res.tables["staircase_tracks"] = pd.concat(stair_tracks, ignore_index=True)
    if id_summary:
        res.tables["identification_summary"] = _first(pd.concat(id_summary), "task")
        res.tables["identification_recall"] = _first(pd.concat(id_recall), "task")
        res.tables["confusion_matrix"] = _first(pd.concat(id_matrix), "task")
    if id_by_condition:
        res.tables["identification_by_condition"] = pd.concat(id_by_condition, ignore_index=True)
    if id_models:
        res.tables["identification_condition_model"] = pd.concat(id_models, ignore_index=True)
    _graded(data, protocol, res)
    return res


def _timing_tables(
    rows: pd.DataFrame, protocol: Protocol, task: IdentifyTask, res: TaskResults
) -> None:
    """``sync_window`` (each participant's window per condition series), ``sync_summary``
    and ``sync_tests`` (:mod:`facelab.analysis.timing`)."""
    windows = timing.window_table(rows, protocol, task)
    if windows.empty:
        res.notes.append(f"task {task.id!r}: no participant answered at three offsets of a "
                         "series; no window fitted")  # fmt: skip
        return
    windows = windows.assign(task=task.id)
    summary, tests = timing.window_tests(windows)
    _add_estimates(res, task, ("sync_window", "sync_summary", "sync_tests"), windows, summary,
                   tests, what="windows",
                   partly=" (of the measure the note names: a note on the width alone keeps "
                   "the window's PSS in)")  # fmt: skip
    counts = timing.timing_counts(rows, protocol, task)
    res.timing.append((task, counts, windows))


def _add_estimates(
    res: TaskResults, task: IdentifyTask, names: tuple[str, str, str], estimates: pd.DataFrame,
    summary: pd.DataFrame, tests: pd.DataFrame, *, what: str, partly: str = "",
) -> None:  # fmt: skip
    """Append one task's per-participant ``estimates``, their ``summary`` and ``tests`` to the
    tables ``names``; a note names how many estimates the data leave undetermined."""
    main, _, tested = names
    for name, frame in zip(names, (estimates, summary.assign(task=task.id),
                                   tests.assign(task=task.id)), strict=True):  # fmt: skip
        if name in res.tables:
            frame = pd.concat([res.tables[name], frame], ignore_index=True)
        res.tables[name] = frame
    undetermined = estimates[estimates["note"].fillna("").astype(str).ne("")]
    if len(undetermined):
        res.notes.append(
            f"task {task.id!r}: {len(undetermined)} of {len(estimates)} {what} are not fully "
            f"determined ({main}.csv's note); they are left out of {tested}{partly}"
        )
    series = list(dict.fromkeys(estimates["condition"]))
    measures = [c.removesuffix("_mean") for c in summary.columns if c.endswith("_mean")]
    untested = [m for m in measures if m not in set(tests["measure"])]
    if len(series) >= 2 and untested:
        res.notes.append(
            f"task {task.id!r}: {tested}.csv holds no test of {', '.join(untested)} - a test "
            "needs two or more series each determined for three or more participants, "
            "compared within the participants who have all of them (see the summary's "
            "'determined')"
        )
    for measure, part in tests.groupby("measure", sort=False):
        valued = estimates.groupby("condition", sort=False)[measure].apply(
            lambda v: bool(np.isfinite(v.to_numpy(dtype=float)).any()))  # a reference: none
        left = [s for s in series if valued.get(s, False)
                and s not in set(part["a"]) | set(part["b"])]  # fmt: skip
        if left:
            res.notes.append(f"task {task.id!r}: {', '.join(left)} left out of {tested}'s "
                             f"{measure} (fewer than three participants with it determined "
                             f"and a value: the summary's {measure}_n)")  # fmt: skip


def _srt_tables(
    rows: pd.DataFrame, protocol: Protocol, task: IdentifyTask | TypedTask, res: TaskResults
) -> None:
    """``srt`` (each participant's SRT per condition series, the benefit against audio
    alone), ``srt_summary`` and ``srt_tests`` (:mod:`facelab.analysis.srt`)."""
    table = srt.srt_table(rows, protocol, task)
    if table.empty:
        res.notes.append(f"task {task.id!r}: no participant answered at two SNRs of a series; "
                         "no SRT fitted")  # fmt: skip
        return
    reference = srt.audio_only_series(protocol)
    if reference is None:
        res.notes.append(f"task {task.id!r}: no (single) audio-only series in noise: SRTs "
                         "without the audio-visual benefit")  # fmt: skip
    summary, tests = srt.srt_tests(table, reference=reference)
    _add_estimates(res, task, ("srt", "srt_summary", "srt_tests"), table.assign(task=task.id),
                   summary, tests, what="SRTs")  # fmt: skip
    res.srt.append((task, srt.noise_trials(rows, protocol, task), table))
    steep = table["benefit_db"].notna() & table["visual_enhancement"].isna()
    if steep.any():
        res.notes.append(
            f"task {task.id!r}: {int(steep.sum())} of {int(table['benefit_db'].notna().sum())} "
            "visual enhancements are not estimated: the series' fitted slope sits on its bound "
            f"({srt.SLOPE_BOUND[1]:g} per dB, steeper than the SNRs tested show), so P away "
            "from the SRT is not known (the SRT and the benefit stand)"
        )


def _typed_tables(
    rows: pd.DataFrame, protocol: Protocol, task: TypedTask, res: TaskResults
) -> None:
    """``typed_answers`` (every typed answer beside what was said, its score and whether
    all of it was right) and ``typed_summary`` (per condition: answers, participants, the
    mean score with a 95 % t interval over participants' means, the share all right)."""
    def said_in(st: Stimulus) -> str | None:  # a matrix: the words, as the answers give them
        words = task.words_said(st) if isinstance(task, MatrixTask) else None
        return " ".join(words) if words is not None else task.said(st)

    said = {(s.id, st.id): said_in(st) for s in protocol.stimulus_sets for st in s.stimuli}
    answers = pd.DataFrame({
        "task": task.id, "participant": rows["participant"].astype(str),
        "trial_index": rows["trial_index"], "condition": rows["condition"],
        "stimulus": rows["stimulus"],
        "said": [said.get((a, b)) for a, b in zip(rows["stimulus_set"], rows["stimulus"],
                                                  strict=True)],
        "response": rows["response"], "score": rows["score"].astype(float),
        "correct": rows["correct"],
    }).reset_index(drop=True)  # fmt: skip
    out = []
    for cond, part in in_protocol_order(answers, protocol):
        means = part.groupby("participant")["score"].mean()
        mean, low, high = stats.mean_t_interval(means.to_numpy(dtype=float), bounds=(0.0, 1.0))
        out.append({"task": task.id, "condition": cond, "answers": len(part),
                    "participants": len(means), "mean_score": mean, "ci_low": low,
                    "ci_high": high,
                    "all_right": float(part["correct"].astype(float).mean())})  # fmt: skip
    frames = {"typed_answers": answers, "typed_summary": pd.DataFrame(out)}
    if isinstance(task, MatrixTask):
        frames["matrix_words"] = matrix_word_table(answers, task=task, protocol=protocol)
    for name, frame in frames.items():
        if name in res.tables:
            frame = pd.concat([res.tables[name], frame], ignore_index=True)
        res.tables[name] = frame


def matrix_word_table(
    answers: pd.DataFrame, *, task: MatrixTask, protocol: Protocol
) -> pd.DataFrame:
    """Per condition series and word position (column) of a word matrix: how often the word
    said there was picked (``condition`` is the series, :attr:`Condition.series_id`: a
    series' SNRs pooled). ``answers``: :func:`_typed_tables`' rows (``said`` and ``response``,
    words separated by spaces). Columns: ``position`` (1 = the first column), ``answers``,
    ``participants``, ``mean_right`` (the participants' mean share right, 95 % t interval
    ``ci_low``/``ci_high``), ``pooled_right``, ``chance`` (1 / the column's length) and
    ``most_confused`` (the wrong pick made most often, ``said→picked (times)``; empty when
    none was). Compare positions within a series: an adaptive track shows each its own SNRs."""
    series = {c.id: c.series_id for c in protocol.conditions}
    rows = []
    for _, answer in answers.iterrows():
        said = str(answer["said"] or "").split()
        picked = str(answer["response"]).split() if pd.notna(answer["response"]) else []
        if len(said) != len(task.columns) or not picked or answer["condition"] not in series:
            continue  # nothing known was said, no answer, or a condition not in the protocol
        for i, word in enumerate(said):
            pick = picked[i] if i < len(picked) else ""
            rows.append((series[answer["condition"]], answer["participant"], i + 1, word, pick))
    words = pd.DataFrame(rows, columns=["condition", "participant", "position", "said", "picked"])
    words["right"] = (words["said"] == words["picked"]).astype(float)
    out = []
    for cond in dict.fromkeys(series.values()):
        part = words[words["condition"] == cond]
        for position, at in part.groupby("position", sort=True):
            means = at.groupby("participant")["right"].mean()
            mean, low, high = stats.mean_t_interval(means.to_numpy(dtype=float), bounds=(0.0, 1.0))
            wrong = at[at["right"] == 0]
            confused = (wrong["said"] + "→" + wrong["picked"]).value_counts()
            out.append({
                "task": task.id, "condition": cond, "position": int(position),
                "answers": len(at), "participants": len(means), "mean_right": mean,
                "ci_low": low, "ci_high": high, "pooled_right": float(at["right"].mean()),
                "chance": 1.0 / len(task.columns[int(position) - 1]),
                "most_confused": (f"{confused.index[0]} ({int(confused.iloc[0])})"
                                  if len(confused) else ""),
            })  # fmt: skip
    columns = ["task", "condition", "position", "answers", "participants", "mean_right",
               "ci_low", "ci_high", "pooled_right", "chance", "most_confused"]  # fmt: skip
    return pd.DataFrame(out, columns=columns)


def score_identification(rows: pd.DataFrame, task: IdentifyTask) -> pd.DataFrame:
    """An identify task's answer rows with ``target`` (the label the trial portrays) and
    ``correct`` (0/1); rows whose trial portrays no label of the task's answers are left out."""
    target = pd.Series(
        [
            task.target(condition=c, stimulus=st)
            for c, st in zip(rows["condition"], rows["stimulus"], strict=True)
        ],
        index=rows.index,
        dtype=object,
    )
    scored = rows.assign(target=target).dropna(subset=["target"])
    return scored.assign(correct=(scored["response"] == scored["target"]).astype(int))


def compares_conditions(scored: pd.DataFrame) -> bool:
    """True when an identification can be compared between conditions: two or more
    conditions, each with two or more portrayed labels (when the answer is the condition
    itself, per-condition accuracy is just the label's recall)."""
    per = scored.groupby("condition")["target"].nunique()
    return len(per) >= 2 and bool((per >= 2).all())


def in_protocol_order(scored: pd.DataFrame, protocol: Protocol) -> list[tuple[str, pd.DataFrame]]:
    """``(condition, its rows)`` for the conditions present, in the protocol's order."""
    order = [c.id for c in protocol.conditions]
    present = set(scored["condition"])
    return [(c, scored[scored["condition"] == c]) for c in order if c in present]


def _identification_by_condition(
    scored: pd.DataFrame,
    parts: list[tuple[str, pd.DataFrame]],
    task: IdentifyTask,
    res: TaskResults,
) -> tuple[pd.DataFrame, pd.DataFrame | None]:
    """Accuracy and kappa per condition (``parts``: :func:`in_protocol_order` of ``scored``,
    pooled over participants), and the logistic GEE of a right answer on the condition
    (:func:`identification.correct_model`; None, with a note, when it cannot be fitted)."""
    labels = [lb.id for lb in task.labels]
    rows = []
    for c, part in parts:
        summary, _ = identification.identification_summary(part, labels=labels, by=())
        rows.append(summary.assign(task=task.id, condition=c))
    table = pd.concat(rows, ignore_index=True)
    table = table[["task", "condition", *identification.SUMMARY_COLUMNS]]
    try:
        model = identification.correct_model(scored, conditions=[c for c, _ in parts])
    except AnalysisError as exc:
        res.notes.append(f"task {task.id!r}: {exc}")
        return table, None
    return table, _first(model.assign(task=task.id), "task")


def _first(frame: pd.DataFrame, column: str) -> pd.DataFrame:
    return frame[[column, *[c for c in frame.columns if c != column]]].reset_index(drop=True)


def graded_ratings(data: pd.DataFrame, protocol: Protocol) -> pd.DataFrame:
    """The VAS ratings of blocks whose conditions all have levels (graded designs), with a
    level; empty when there are none or only one level."""
    graded_blocks = [
        b.id
        for b in protocol.blocks
        if b.task is None
        and all(protocol.condition(c).level is not None for c in protocol.block_conditions(b))
    ]
    vas = data[(data["screen"].fillna("vas") == "vas") & data["block"].isin(graded_blocks)]
    vas = vas.dropna(subset=["level", "rating"])
    return vas.iloc[0:0] if vas["level"].nunique() < 2 else vas


def _graded(data: pd.DataFrame, protocol: Protocol, res: TaskResults) -> None:
    """Trend contrast and mixed model for VAS items of blocks whose conditions all have levels."""
    vas = graded_ratings(data, protocol)
    if vas.empty:
        return
    by = ("item", "stimulus_set")
    try:
        res.tables["trend_contrast"] = graded.trend_contrast(vas, by=by)
    except AnalysisError as exc:  # a pilot of one participant: the ratings are described
        res.notes.append(f"the trend contrast over the levels is not estimable: {exc} "
                         "(descriptive tables and figures only)")  # fmt: skip
        return
    if vas["participant"].nunique() >= 3:
        res.tables["graded_lmm"] = graded.graded_lmm(vas, by=by)
    else:
        res.notes.append("the random-slope model needs three or more participants: not fitted")


def answer_counts(rows: pd.DataFrame) -> pd.DataFrame:
    """The default table of an added screen's answers (``screen_<kind>.csv``) from its log
    rows: per condition the count and share of each answer, and mean, sd and n when the
    answers are numbers."""
    counts = (rows.groupby(["condition", "response"], observed=True).size()
              .rename("n").reset_index())  # fmt: skip
    counts["share"] = counts["n"] / counts.groupby("condition")["n"].transform("sum")
    numeric = pd.to_numeric(rows["response"], errors="coerce")
    if numeric.notna().all():
        means = rows.assign(value=numeric).groupby("condition", observed=True)["value"]
        summary = means.agg(mean="mean", sd="std", n="count").reset_index()
        counts = counts.merge(summary.rename(columns={"n": "n_condition"}), on="condition")
    return counts
