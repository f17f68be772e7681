"""Walking a timeline: each screen to its presenter, each response to the log at once.

A presenter is any object with one method per screen kind, named after the kind (each screen
finds its own: :meth:`~facelab.experiment.timeline.Screen.present`): the PsychoPy window
(:mod:`facelab.experiment.window`) or a simulated participant
(:mod:`facelab.experiment.simulate`). The walker is the only place that turns answers into
log rows, so every presenter writes the same rows the same way: appended and fsync'd as the
screen that collected them ends, before the next screen appears.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Protocol

from facelab.experiment.adaptive import Staircases
from facelab.experiment.timeline import (
    AdaptiveTrial,
    ChoiceAnswer,
    ChoiceScreen,
    ClipPairScreen,
    ClipScreen,
    IdentifyAnswer,
    IdentifyScreen,
    MatrixScreen,
    PairPlayback,
    Playback,
    ResponseScreen,
    Screen,
    TextScreen,
    TypedAnswer,
    TypedScreen,
    VasAnswer,
    VasScreen,
)
from facelab.sessionlog import SessionContext, SessionLog, append_jsonl

__all__ = ["Presenter", "walk"]


class Presenter(Protocol):
    """The built-in kinds' methods (a new kind adds its own, or overrides ``Screen.present``)."""

    def text(self, screen: TextScreen) -> None: ...
    def clip(self, screen: ClipScreen) -> Playback: ...
    def clip_pair(self, screen: ClipPairScreen) -> PairPlayback: ...
    def vas(self, screen: VasScreen) -> list[VasAnswer]: ...
    def choice_2afc(self, screen: ChoiceScreen) -> list[ChoiceAnswer]: ...
    def identify(self, screen: IdentifyScreen) -> list[IdentifyAnswer]: ...
    def typed(self, screen: TypedScreen) -> list[TypedAnswer]: ...
    def matrix(self, screen: MatrixScreen) -> list[TypedAnswer]: ...


def walk(
    screens: Sequence[Screen],
    *,
    presenter: Any,
    log: SessionLog,
    context: SessionContext,
    replayed: set[int] = frozenset(),  # type: ignore[assignment]
    record_playback: bool = True,
    on_row: Callable[[dict[str, Any]], None] | None = None,
    staircases: Staircases | None = None,
) -> int:
    """Present ``screens`` in order; returns the number of trials whose responses finished.

    ``replayed`` are trials whose clip was already shown in an earlier run (a resume): their
    playback records say ``"replay": true``. A staircase trial (:class:`AdaptiveTrial`) asks
    ``staircases`` for its condition, shows that trial's screens, and reports the answer back.
    """
    playbacks: dict[int | None, Playback] = {}
    queue = list(screens)
    trials_done = 0
    adaptive: set[int | None] = set()  # trials a staircase chose the condition of
    index = 0
    while index < len(queue):
        screen = queue[index]
        if isinstance(screen, AdaptiveTrial):
            if staircases is None:
                raise TypeError("a staircase trial needs the session's staircases")
            assert screen.trial is not None
            expanded = screen.expand(staircases.resolve(screen.trial))
            queue[index : index + 1] = expanded
            adaptive.add(screen.trial_index)
            continue
        index += 1
        result = screen.present(presenter)
        if isinstance(screen, ClipScreen):
            # one playback record per clip (a side-by-side pair has two, with their own frames)
            shown = (result.left, result.right) if isinstance(result, PairPlayback) else (result,)
            if record_playback and not screen.practice:
                for clip, playback in zip(screen.clips(), shown, strict=True):
                    append_jsonl(
                        log.paths.playback,
                        playback.record(
                            trial_index=screen.trial_index,
                            clip="__".join(clip),
                            replay=screen.trial_index in replayed,
                        ),
                    )
            if isinstance(result, PairPlayback):
                result = result.combined()
            first = playbacks.get(screen.trial_index)
            if screen.interval == 2 and first is not None:
                result = first.joined(result)
            playbacks[screen.trial_index] = result
        elif isinstance(screen, ResponseScreen):
            rows = screen.rows(result, context=context, playback=playbacks.get(screen.trial_index))
            for row in rows:
                log.append(row)
                if on_row is not None:
                    on_row(row)
            if screen.trial_index in adaptive and rows and staircases is not None:
                assert screen.trial is not None
                staircases.update(screen.trial, rows)
            nxt = queue[index] if index < len(queue) else None  # a trial's responses are adjacent
            last = not (isinstance(nxt, ResponseScreen) and nxt.trial_index == screen.trial_index)
            if rows and last:
                trials_done += 1
    return trials_done
