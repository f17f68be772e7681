"""``facelab run``: one participant session in a PsychoPy window, from the first screen or
from where an interrupted session stopped.

Order: the checks (every clip present, unchanged and rendered from the protocol as it is now;
display, audio, disk) -> the session's lock -> the session log created (or resumed: same
protocol, same trial order, same clips) -> the timeline walked in the window
(:mod:`facelab.experiment.window`), each response appended and fsync'd as its screen ends.
Escape asks before quitting (exit 4); SIGINT (exit 130) and SIGTERM (exit 143) end the
session the same way; every response given is on disk, and ``--resume`` continues. With
``presentation.ssq`` after, quitting with Escape first shows the sickness questionnaire's
symptoms not yet answered (Escape again skips them).

``--simulate`` drives this same window with a scripted participant
(:mod:`facelab.experiment.scripted`): real X mouse and key events.
"""

from __future__ import annotations

import datetime as dt
import functools
import platform
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from facelab.design import build_trials, participant_seed, trial_order
from facelab.errors import SessionAbortedError, SessionError
from facelab.experiment.adaptive import Staircases
from facelab.experiment.preflight import (
    check_audio,
    check_clips,
    check_disk,
    check_display,
    compare_with_session,
)
from facelab.experiment.presentation import DroppedFrames
from facelab.experiment.scripted import ScriptedParticipant
from facelab.experiment.simulate import ChoiceModel, RatingModel
from facelab.experiment.timeline import (
    ResponseScreen,
    SsqScreen,
    compile_timeline,
    needed_clips,
    remaining,
)
from facelab.experiment.walk import walk
from facelab.experiment.window import Window
from facelab.protocol import Protocol, protocol_hash
from facelab.sessionlog import SessionContext, SessionLock, SessionLog, session_paths

__all__ = ["RunOptions", "run_session"]


@dataclass
class RunOptions:
    participant: str
    session: int = 1
    resume: bool = False
    windowed: bool = False
    simulate: bool = False
    sim_seed: int = 1
    clips: Path | None = None
    results: Path = Path("results")
    screenshots: Path | None = None
    size: tuple[int, int] = (1280, 800)
    verify_hashes: bool = True
    accept_changed_clips: bool = False
    warn_dropped_frames: int = 3  # a clip that drops more frames is named at once
    #: hosts presentation.conversation in the window (facelab run gives a LabConversation):
    #: called (window, screen, participant=, session=, protocol_sha256=)
    conversation: Any = None


def _sickness_after_quitting(
    protocol: Protocol,
    screens: list[Any],
    log: SessionLog,
    *,
    window: Window,
    context: SessionContext,
    on_row: Any,
) -> None:
    """The experimenter quit a session whose protocol asks for the sickness questionnaire
    after the study: its symptoms not yet answered are shown before the window closes (a
    participant who stops because they feel sick is the one whose answers matter most);
    Escape and "y" skip it. Logged like any answer; the session stays resumable."""
    if "after" not in protocol.presentation.ssq:
        return
    todo = [s for s in remaining(screens, log.answered(), language=protocol.presentation.language)
            if isinstance(s, SsqScreen) and s.moment == "after"]  # fmt: skip
    if not todo:
        return
    print("quit: the sickness questionnaire (after) is shown before the window closes; "
          "Escape then y skips it", flush=True)  # fmt: skip
    walk(todo, presenter=window, log=log, context=context, replayed=set(), on_row=on_row,
         staircases=None)  # fmt: skip


def _versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {"python": platform.python_version(), "platform": platform.platform()}
    for pkg in ("facelab", "psychopy", "numpy", "ffpyplayer", "pyglet"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def run_session(protocol: Protocol, *, protocol_path: Path, options: RunOptions) -> dict[str, Any]:
    """Run (or resume) one session; returns a summary.

    Raises :class:`~facelab.errors.SessionError` before any window opens when a check fails,
    :class:`~facelab.errors.SessionAbortedError` when the experimenter quits.
    """
    pid = options.participant
    if protocol.presentation.conversation is not None and options.conversation is None:
        raise SessionError(
            f"{protocol_path}: presentation.conversation: this session has no host for the "
            "live conversation (facelab run gives one; a program calling run_session passes "
            "RunOptions.conversation)"
        )
    trials = build_trials(protocol, participant=pid)
    screens = compile_timeline(protocol, trials, participant=pid, session=options.session)
    needed = needed_clips(screens)
    clips_dir = options.clips or options.results / protocol.study.id / "clips"
    clips = check_clips(
        protocol,
        needed,
        clips_dir,
        base_dir=protocol_path.parent,
        verify_hashes=options.verify_hashes,
    )
    check_disk(options.results)
    check_display()
    audio = check_audio(allow_dummy=options.simulate)
    paths = session_paths(
        options.results, study=protocol.study.id, participant=pid, session=options.session
    )
    digest = protocol_hash(protocol_path)
    clip_hashes = {"/".join(k): v.sha256 for k, v in sorted(clips.items())}
    with SessionLock(paths):
        if options.resume:
            log = SessionLog.resume(
                options.results, study=protocol.study.id, participant=pid, session=options.session
            )
            saved = log.provenance()
            if saved.get("protocol_sha256") != digest:
                raise SessionError(
                    f"{protocol_path} changed since this session started (its SHA-256 differs "
                    f"from the one in {paths.provenance}); resume with the original protocol file"
                )
            if saved.get("trial_order") != trial_order(trials):
                raise SessionError("the trial order differs from the one this session started with")
            if bool(saved.get("simulated")) != options.simulate:
                raise SessionError(
                    f"this session was started {'with' if saved.get('simulated') else 'without'} "
                    "--simulate; resume it the same way, so that its rows are not mixed"
                )
            changed = compare_with_session(clips, saved.get("clips", {}))
            if changed and not options.accept_changed_clips:
                names = ", ".join(sorted(changed)[:5])
                raise SessionError(
                    f"{len(changed)} clip(s) differ from those this session started with "
                    f"({names}); the rest of the session would show other stimuli. Restore the "
                    "original clips, or pass --accept-changed-clips to continue with the new "
                    "ones (recorded in the session file)"
                )
            run_number = len(saved.get("resumes", [])) + 2
        else:
            if paths.tsv.exists():
                raise SessionError(
                    f"session already exists: {paths.folder}; nothing was overwritten. "
                    "Continue it with --resume, or choose another --session"
                )
            log = SessionLog.create(
                options.results,
                study=protocol.study.id,
                participant=pid,
                session=options.session,
                provenance={
                    "study": protocol.study.id,
                    "participant": pid,
                    "session": options.session,
                    "simulated": options.simulate,
                    "mode": "lab",
                    "protocol_file": str(protocol_path),
                    "protocol_sha256": digest,
                    "design_seed": participant_seed(protocol.seed, pid),
                    "trial_order": trial_order(trials),
                    "clips": clip_hashes,
                    "software": _versions(),
                    "audio_output": audio,
                    "started": dt.datetime.now(dt.UTC).isoformat(),
                    "resumes": [],
                },
            )
            changed = {}
            run_number = 1
        answered = log.answered()
        todo = remaining(screens, answered, language=protocol.presentation.language)
        if options.resume:
            first = next((s.trial_index for s in todo if isinstance(s, ResponseScreen)), None)
            log.update_provenance(
                resumes=[
                    {
                        "at": dt.datetime.now(dt.UTC).isoformat(),
                        "first_trial": first,
                        "repaired_lines": log.repaired,
                        "changed_clips": changed,
                    }
                ]
            )
        n_responses = sum(len(s.response_keys()) for s in screens)
        if not any(isinstance(s, ResponseScreen) for s in todo):
            return {
                "log": str(log.paths.tsv),
                "ratings": len(log.rows),
                "trials_run": 0,
                "complete": len(log.rows) == n_responses,
            }
        context = SessionContext(
            study=protocol.study.id,
            participant=pid,
            session=options.session,
            simulated=options.simulate,
            protocol_sha256=digest,
        )

        drops = DroppedFrames(warn_over=options.warn_dropped_frames)

        def saved_line(row: dict[str, Any]) -> None:
            drops.row(row)
            if row["rating"] is not None:
                value = format(row["rating"], ".2f")
            elif row.get("score") is not None:  # typed: the text and its score
                value = f"{row['response'] or ''!r} (score {row['score']:.2f})"
            else:
                value = str(row["response"])
            print(
                f"trial {row['trial_index']}/{len(trials)} {row['condition']} {row['item']} = "
                f"{value} (saved)",
                flush=True,
            )

        fullscreen = protocol.presentation.fullscreen and not options.windowed
        with Window(
            protocol,
            clips=clips,
            size=options.size,
            fullscreen=fullscreen,
            screenshots=options.screenshots,
        ) as window:
            if options.simulate:
                seed = [options.sim_seed, participant_seed(0, pid) % 2**32, run_number]
                rng = np.random.default_rng(seed)
                window.script = ScriptedParticipant(
                    RatingModel(protocol, rng=rng),
                    window.origin(),
                    window.size,
                    paths.actions,
                    chooser=ChoiceModel(protocol, rng=rng) if protocol.tasks else None,
                )
            if options.conversation is not None:
                window.conversation_host = functools.partial(
                    options.conversation, participant=pid, session=options.session,
                    protocol_sha256=digest,
                )  # fmt: skip
            log.update_provenance(
                screen={
                    "size": list(window.size),
                    "fullscreen": fullscreen,
                    "refresh_hz": window.refresh_hz(),
                    "gl_renderer": window.gl_renderer,
                    "paced_hz": window.paced_hz,
                }
            )
            try:
                ran = walk(
                    todo,
                    presenter=window,
                    log=log,
                    context=context,
                    replayed={t for t, _ in answered},
                    on_row=saved_line,
                    staircases=Staircases(protocol, logged=log.rows, record=paths.staircase),
                )
            except SessionAbortedError:
                _sickness_after_quitting(protocol, screens, log, window=window, context=context,
                                         on_row=saved_line)  # fmt: skip
                raise
        drops.end_block()
        log.update_provenance(
            finished=dt.datetime.now(dt.UTC).isoformat(), dropped_frames=drops.summary()
        )
        return {
            "log": str(log.paths.tsv),
            "ratings": len(log.rows),
            "trials_run": ran,
            "complete": len(log.rows) == n_responses,
            "dropped": drops.summary(),
        }
