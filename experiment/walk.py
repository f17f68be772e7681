"""Walking a timeline: each screen to its presenter, each response to the log at once.

A presenter is any object with one method per screen kind (:data:`PRESENTERS`): the PsychoPy
window (:mod:`facelab.experiment.window`) or a simulated participant
(:mod:`facelab.experiment.simulate`). The walker is the only place that turns answers into
log rows, so every presenter writes the same rows the same way: appended and fsync'd as the
screen that collected them ends, before the next screen appears.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Protocol

from facelab.experiment.timeline import (
    ClipScreen,
    Playback,
    ResponseScreen,
    Screen,
    TextScreen,
    VasAnswer,
    VasScreen,
)
from facelab.sessionlog import SessionContext, SessionLog, append_jsonl

__all__ = ["PRESENTERS", "Presenter", "walk"]


class Presenter(Protocol):
    def text(self, screen: TextScreen) -> None: ...
    def clip(self, screen: ClipScreen) -> Playback: ...
    def vas(self, screen: VasScreen) -> list[VasAnswer]: ...


#: screen class -> the presenter method that shows it (a new screen type adds one line)
PRESENTERS: dict[type[Screen], str] = {
    TextScreen: "text",
    ClipScreen: "clip",
    VasScreen: "vas",
}


def walk(
    screens: Sequence[Screen],
    *,
    presenter: Any,
    log: SessionLog,
    context: SessionContext,
    replayed: set[int] = frozenset(),  # type: ignore[assignment]
    record_playback: bool = True,
    on_row: Callable[[dict[str, Any]], None] | None = None,
) -> int:
    """Present ``screens`` in order; returns the number of trials whose responses finished.

    ``replayed`` are trials whose clip was already shown in an earlier run (a resume): their
    playback records say ``"replay": true``.
    """
    playbacks: dict[int | None, Playback] = {}
    last_response = {
        s.trial_index: i for i, s in enumerate(screens) if isinstance(s, ResponseScreen)
    }
    trials_done = 0
    for index, screen in enumerate(screens):
        method = PRESENTERS.get(type(screen))
        if method is None:
            raise TypeError(f"no presenter for screen type {type(screen).__name__}")
        result = getattr(presenter, method)(screen)
        if isinstance(screen, ClipScreen):
            playbacks[screen.trial_index] = result
            if record_playback and not screen.practice:
                append_jsonl(
                    log.paths.playback,
                    result.record(
                        trial_index=screen.trial_index,
                        clip="__".join(screen.clip),
                        replay=screen.trial_index in replayed,
                    ),
                )
        elif isinstance(screen, ResponseScreen):
            rows = screen.rows(result, context=context, playback=playbacks.get(screen.trial_index))
            for row in rows:
                log.append(row)
                if on_row is not None:
                    on_row(row)
            if rows and last_response[screen.trial_index] == index:
                trials_done += 1
    return trials_done
