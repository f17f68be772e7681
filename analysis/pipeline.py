"""The analysis pipeline, once: session logs -> checks -> every analysis the protocol calls for
-> tables, figures and a report. ``facelab analyze``, ``facelab demo`` and the benchmarks run
this one function (``facelab.analysis.run``), so what they report cannot drift apart.

Steps: load every session of the study (:mod:`.load`); drop excluded participants; check the
data against the protocol (:mod:`.integrity`: provenance, protocol hash, each row where the
design put it); the VAS analysis per item and stimulus set (:mod:`.study`, repeated-measures
or the paper's procedure) when there are VAS ratings; the task analyses (:mod:`.tasks`:
psychometric fits, staircases, identification, graded designs); the behaviour covariates for
protocols with a behaviour layer (:mod:`.behaviour`, from the clips' event logs); the report
(:mod:`.report`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from facelab.analysis.conversation import conversation_tables, is_conversation_row
from facelab.analysis.integrity import DataCheck, added_items, added_kinds, check_data
from facelab.analysis.load import load_results, sessions_without_responses
from facelab.analysis.objective import (
    objective_covariate,
    objective_distances,
    objective_vs_ratings,
)
from facelab.analysis.pilot import pilot_items, pilot_sessions, same_rating_everywhere
from facelab.analysis.presentation import (
    exclude_av_offset,
    exclude_dropped,
    exclude_trials,
    live_playback,
    live_quality,
    playback_records,
    playback_replays,
    presentation_quality,
    session_modes,
    session_records,
    with_live_playback,
)
from facelab.analysis.report import ReportFiles, write_report
from facelab.analysis.sickness import is_ssq_row, ssq_tables
from facelab.analysis.stimulus_checks import summarize_stimulus_checks
from facelab.analysis.study import StudyResults, analyze_study
from facelab.analysis.tasks import DesignSampler, TaskResults, analyze_tasks, answer_counts
from facelab.analysis.vr_screen_poses import screen_pose_summary, screen_pose_table
from facelab.blas_threads import on_one_blas_thread
from facelab.errors import AnalysisError
from facelab.formats import MANIFEST_NAME
from facelab.protocol import Protocol, protocol_hash

__all__ = ["AnalysisRun", "run", "study_root"]


@dataclass(frozen=True)
class AnalysisRun:
    """What one run of the pipeline produced.

    data : every response analysed (one row per rating or answer; tidy, DESIGN.md's columns).
    check : the data check (provenance, notes, incomplete participants).
    results : the VAS analysis (None when the study has no VAS ratings).
    tasks : the task and graded-design analyses, and the behaviour tables.
    files : the report's files.
    """

    data: pd.DataFrame
    check: DataCheck
    results: StudyResults | None
    tasks: TaskResults
    files: ReportFiles

    @property
    def notes(self) -> tuple[str, ...]:
        """Every note of the check and the analyses, in that order."""
        return (
            *self.check.notes,
            *(self.results.notes if self.results is not None else ()),
            *self.tasks.notes,
        )


def study_root(results: Path, protocol: Protocol) -> Path:
    """The study's folder: ``results`` itself when it is named after the study, else
    ``results/<study id>``."""
    return results if results.name == protocol.study.id else results / protocol.study.id


@on_one_blas_thread  # many small fits: see facelab.blas_threads
def run(
    results: Path,
    protocol: Protocol,
    *,
    protocol_path: Path,
    out: Path,
    method: str = "rm",
    exclude: Sequence[str] = (),
    accept_protocol_change: bool = False,
    clips: Path | None = None,
    boot_seed: int = 1,
    n_boot: int = 200,
    max_dropped_frames: int | None = None,
    max_av_offset_ms: float | None = None,
    sampler: DesignSampler | None = None,
    exclude_rules: Sequence[str] = (),
) -> AnalysisRun:
    """Analyse the study's sessions under ``results`` into ``out`` (created; files in it are
    replaced).

    method : the primary VAS procedure, ``rm`` (repeated measures) or ``paper``.
    exclude : participant ids left out (each must be in the logs).
    clips : the rendered clips: their behaviour logs and stimulus checks (default
        ``<study>/clips``).
    boot_seed, n_boot : the bootstrap of the psychometric intervals (seeded Generator).
    max_dropped_frames : leave out responses to trials whose clip dropped more frames (the
        report says how many, per condition); None keeps every response. Either way the
        dropped frames per condition are tabled (``presentation_quality``).
    max_av_offset_ms : leave out responses to trials drawn live (display live3d / webxr)
        whose picture and sound were further apart; the live measures per condition are
        tabled either way (``live_presentation``), and each response carries its trial's
        ``av_offset_ms``, head movement and viewing distance as covariates.
    sampler : simulates the protocol's design, to calibrate each participant's psychometric
        intervals (``facelab.experiment.simulate.design_sampler``; None: uncalibrated).
    exclude_rules : leave out responses to trials whose playback record meets a rule
        (``"frame_age_max_ms > 100"``: :func:`facelab.analysis.presentation.exclude_trials`);
        the report says how many per condition and rule.
    """
    data = load_results(results, study=protocol.study.id)
    empty_sessions = sessions_without_responses(results, study=protocol.study.id)
    if exclude:
        unknown = sorted(set(exclude) - set(data["participant"]))
        if unknown:
            raise AnalysisError(
                f"--exclude: no such participant(s) in the logs: {', '.join(unknown)}"
            )
        data = data[~data["participant"].isin(list(exclude))].reset_index(drop=True)
        if data.empty:
            raise AnalysisError(
                f"--exclude leaves no participant: all {len(set(exclude))} in the logs are "
                "excluded; nothing to analyse"
            )
    people_notes = _participant_notes(data, exclude=exclude)
    records = playback_records(data)  # each session's _playback.jsonl, read once
    modes = session_modes(data)  # where each session ran (before any exclusion)
    data = with_live_playback(data, live_playback(records))
    excluded, dropped_note, offset_note = data.iloc[:0], None, None
    if max_dropped_frames is not None:
        data, excluded, dropped_note = exclude_dropped(data, max_dropped=max_dropped_frames)
    if max_av_offset_ms is not None:
        data, late, offset_note = exclude_av_offset(data, max_ms=max_av_offset_ms)
        excluded = pd.concat([excluded, late], ignore_index=True) if not late.empty else excluded
    rule_notes: list[str] = []
    if exclude_rules:
        data, ruled, rule_notes = exclude_trials(data, records, rules=exclude_rules)
        excluded = pd.concat([excluded, ruled], ignore_index=True) if not ruled.empty else excluded
    check = check_data(
        pd.concat([data, excluded], ignore_index=True) if not excluded.empty else data,
        protocol,
        protocol_sha256=protocol_hash(protocol_path),
        accept_protocol_change=accept_protocol_change,
    )
    every_row = data  # the session table counts the questionnaire's answers too
    in_ssq, in_conversation = is_ssq_row(data), is_conversation_row(data, protocol)
    questionnaires = data[in_ssq]  # session-level: outside every trial analysis
    conversations = data[in_conversation]
    data = data[~in_ssq & ~in_conversation].reset_index(drop=True)
    vas = data[data["screen"].fillna("vas") == "vas"].reset_index(drop=True)
    study = analyze_study(vas, protocol, method=method) if not vas.empty else None
    tasks = analyze_tasks(
        data, protocol, rng=np.random.default_rng(boot_seed), n_boot=n_boot, sampler=sampler
    )
    clips = clips or study_root(results, protocol) / "clips"
    _behaviour_tables(protocol, clips, vas, tasks)
    _objective_tables(protocol, clips, vas, tasks)
    _added_screen_tables(protocol, data, tasks)
    _ssq_tables(protocol, questionnaires, tasks)
    tables, notes = conversation_tables(conversations, protocol)
    tasks.tables.update(tables)
    tasks.notes.extend(notes)
    tasks.tables["presentation_quality"] = presentation_quality(
        data, excluded=excluded, replays=playback_replays(records)
    )
    poses = screen_pose_table(session_records(every_row, suffix="_screen_poses.jsonl"))
    if not poses.empty:  # VR: how participants moved while screens waited for an answer
        tasks.tables["vr_screen_poses_summary"] = screen_pose_summary(poses)
        tasks.tables["vr_screen_poses"] = poses
    live = live_quality(pd.concat([data, excluded], ignore_index=True))  # every trial shown
    if not live.empty:  # clips drawn live (display live3d / webxr): A/V offset, head movement
        tasks.tables["live_presentation"] = live
    sessions = pilot_sessions(every_row, check)
    if not modes.empty and not sessions.empty:  # where each session ran
        sessions = sessions.merge(modes, on=["participant", "session"], how="left")
    tasks.tables["pilot_sessions"] = sessions
    if not modes.empty:
        tasks.notes.append(_mode_note(modes))
    items, item_notes = pilot_items(vas)
    if not items.empty:
        tasks.tables["pilot_items"] = items
    tasks.notes.extend(item_notes)
    tasks.notes.extend(same_rating_everywhere(vas))
    tasks.notes.extend(n for n in (dropped_note, offset_note, *rule_notes) if n)
    tasks.notes.extend(people_notes)
    if empty_sessions:
        tasks.notes.append(
            f"{len(empty_sessions)} session(s) hold no response and are in no table: "
            + "; ".join(empty_sessions)
        )
    files = write_report(
        results=study,
        data=data,
        protocol=protocol,
        out=out,
        protocol_path=protocol_path,
        check=check,
        tasks=tasks,
        stimulus_checks=summarize_stimulus_checks(clips),
    )
    return AnalysisRun(data=data, check=check, results=study, tasks=tasks, files=files)


def _participant_notes(data: pd.DataFrame, *, exclude: Sequence[str]) -> list[str]:
    """The report's notes on who is analysed: the participants ``--exclude`` left out, and
    participants with more than one session (their answers are pooled as one participant's:
    the repeated-measures tests average them, the paper procedure counts every answer)."""
    notes = []
    if exclude:
        notes.append(f"left out by --exclude: {', '.join(sorted(set(exclude)))} (every answer "
                     "of theirs; the tables and tests hold the other participants)")  # fmt: skip
    sessions = data.groupby("participant")["session"].unique()
    repeated = {str(p): sorted(int(v) for v in s) for p, s in sessions.items() if len(s) > 1}
    if repeated:
        listed = "; ".join(f"{p}: sessions {', '.join(map(str, s))}"
                           for p, s in sorted(repeated.items()))  # fmt: skip
        notes.append(
            f"{len(repeated)} participant(s) ran more than one session ({listed}): their "
            "answers are pooled as one participant's (the repeated-measures tests average "
            "them; the paper procedure counts every rating); analyse a session on its own by "
            "moving the others out of the results folder"
        )
    return notes


def _ssq_tables(protocol: Protocol, rows: pd.DataFrame, tasks) -> None:
    """``ssq`` and ``ssq_summary`` (presentation.ssq): every questionnaire scored, and the
    scores per moment and their change (:mod:`facelab.analysis.sickness`)."""
    if not protocol.presentation.ssq:
        return
    tables, notes = ssq_tables(rows, moments=protocol.presentation.ssq)
    if not tables:
        notes = ["the protocol asks for the sickness questionnaire (presentation.ssq), but "
                 "the logs have no answers to it"]  # fmt: skip
    tasks.tables.update(tables)
    tasks.notes.extend(notes)


def _added_screen_tables(protocol: Protocol, data: pd.DataFrame, tasks) -> None:
    """``screen_<kind>`` per added screen kind (presentation.added_screens): the kind's own
    table of its answers (``AddedScreen.summarise``; by default per condition the count of
    each answer and, for numeric answers, their mean)."""
    kinds = added_kinds()
    for item, kind in added_items(protocol).items():
        rows = data[(data["item"] == item) & (data["screen"] == kind)]
        if rows.empty:
            tasks.notes.append(f"added screen {kind!r}: no answers in the logs")
            continue
        summarise = getattr(kinds.get(kind), "summarise", answer_counts)
        try:
            table = summarise(rows.reset_index(drop=True))
        except Exception:  # a package's code: its failure is named, the analysis goes on
            tasks.notes.append(f"added screen {kind!r}: the kind's own summary (summarise) "
                               "failed; the default table is written instead")  # fmt: skip
            table = answer_counts(rows.reset_index(drop=True))
        tasks.tables[f"screen_{kind}"] = table.round(6)


def _objective_tables(protocol: Protocol, clips: Path, vas: pd.DataFrame, tasks) -> None:
    """``objective`` (every condition's motion against ``analysis.reference``),
    ``objective_vs_ratings`` (beside the ratings) and ``objective_covariate`` (the tracked
    measures as per-stimulus covariates of the ratings), with notes; nothing without a
    reference."""
    ref = protocol.analysis.reference
    if ref is None:
        return
    objective = objective_distances(protocol, clips_dir=clips)
    if objective.empty:
        tasks.notes.append(f"objective comparison with {ref!r}: no clips of it with tracks in "
                           f"{clips} (render and check them first)")  # fmt: skip
        return
    tasks.tables["objective"] = objective
    related = objective_vs_ratings(objective, vas)
    if not related.empty:
        tasks.tables["objective_vs_ratings"] = related
    tracked = objective[objective["measure"] == "aperture_correlation"]
    if tracked.empty:
        tasks.notes.append(f"objective comparison with {ref!r}: the clips have no face "
                           "tracking (run facelab check): track channels only")  # fmt: skip
        return
    per = tracked.groupby("condition")["value"].mean().sort_values(ascending=False)
    tasks.notes.append(
        f"objective comparison with {ref!r} (objective.csv): tracked lip aperture correlation, "
        "mean over stimuli: " + ", ".join(f"{c} {v:.2f}" for c, v in per.items())
    )
    covariate = objective_covariate(objective, vas)
    if covariate.empty:
        return
    tasks.tables["objective_covariate"] = covariate
    for row in covariate[covariate["measure"] == "aperture_correlation"].itertuples():
        if row.procedure == "not estimable":
            said = f"not estimable: {row.note}"
        else:
            said = (f"{row.estimate:+.2f} per unit (95% CI {row.ci_low:.2f} to "
                    f"{row.ci_high:.2f}, p = {row.p:.3g}, {row.n_cells} clips)")  # fmt: skip
        tasks.notes.append(
            f"objective_covariate.csv: {row.item} rating on the clip's tracked "
            f"aperture correlation with {ref!r}, within conditions: {said}"
        )


def _behaviour_tables(
    protocol: Protocol, clips: Path, vas: pd.DataFrame, tasks: TaskResults
) -> None:
    """Behaviour counts per clip and the covariate models, for protocols with a behaviour
    layer (seed 003), into ``tasks.tables``; what cannot be made becomes a note."""
    if all(c.behaviour == "none" for c in protocol.conditions):
        return
    from facelab.analysis.behaviour import (
        clip_behaviour,
        covariate_model,
        identification_covariates,
    )

    if not (clips / MANIFEST_NAME).is_file():
        tasks.notes.append(
            f"behaviour covariates: no clips in {clips} (render them there, or pass --clips)"
        )
        return
    counts = clip_behaviour(clips)
    if counts.empty:
        tasks.notes.append(f"behaviour covariates: no behaviour logs in {clips}")
        return
    tasks.tables["behaviour_counts"] = counts
    order = tuple(c.id for c in protocol.conditions)  # the models keep those present
    if not vas.empty:
        try:
            tasks.tables["behaviour_covariates"] = covariate_model(vas, counts, conditions=order)
        except AnalysisError as exc:  # a secondary table: the report goes on without it
            tasks.notes.append(f"behaviour covariates: {exc}")
    models = []
    for task_id, trials in tasks.identification_trials.items():
        if trials["condition"].nunique() >= 2 and trials["participant"].nunique() >= 2:
            try:
                model = identification_covariates(trials, counts, conditions=order)
            except AnalysisError as exc:
                tasks.notes.append(f"behaviour covariates of task {task_id!r}: {exc}")
                continue
            models.append(model.assign(task=task_id))
    if models:
        frame = pd.concat(models, ignore_index=True)
        tasks.tables["identification_covariates"] = frame[
            ["task", *[c for c in frame.columns if c != "task"]]
        ]


def _mode_note(modes: pd.DataFrame) -> str:
    """Where the sessions ran, e.g. "sessions: 2 online (webxr 1, live3d 1), 1 lab"."""
    parts = []
    for mode, g in modes.groupby("mode", sort=True):
        shown = g["display"].value_counts().sort_index()
        how = (
            ""
            if set(shown.index) <= {"video"} or mode != "online"
            else " (" + ", ".join(f"{d} {n}" for d, n in shown.items()) + ")"
        )
        simulated = int(g["simulated"].sum())
        of = (
            ""
            if mode == "simulated" or not simulated
            else (", all simulated" if simulated == len(g) else f", {simulated} of them simulated")
        )
        parts.append(f"{len(g)} {mode}{how}{of}")
    return "sessions: " + "; ".join(parts)
