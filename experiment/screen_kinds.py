"""Screen kinds from outside facelab: a base a package subclasses, and the loading of the
installed ones (entry-point group ``facelab.screens``).

A protocol asks for an added screen in every trial with ``presentation.added_screens: [{kind:
NAME, options: {...}}]``. The kind (a :class:`ButtonScreen` subclass) declares everything
else, so adding one touches only its own package:

* where it goes in a trial (``placement``: ``after_responses`` - after the trial's last
  response screen - or ``after_clip``), its protocol options (``Options``, a pydantic model:
  unknown keys are errors reported with the protocol's line), the item its answers are logged
  under (``item``);
* its question and buttons (``question``, ``choices``): the lab window draws them as numbered
  buttons (keys 1..n or a click), the browser with facelab's generic buttons plugin (no
  JavaScript to write), a simulated participant answers with :meth:`ButtonScreen.simulate`;
* its log row: ``screen`` = the kind, ``item``, ``response`` = the chosen value; the
  integrity check expects one such row per trial, and ``facelab analyze`` tabulates the
  answers per condition (``screen_<kind>.csv``: counts per value, and the mean when the values
  are numbers).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict

from facelab.experiment.timeline import (
    SCREEN_KINDS,
    AnswerError,
    BrowserContext,
    ResponseScreen,
    screen_kind,
)
from facelab.sessionlog import SessionContext

__all__ = [
    "PLACEMENTS",
    "ButtonAnswer",
    "ButtonScreen",
    "NoOptions",
    "load_screen_plugins",
]

PLACEMENTS = ("after_responses", "after_clip")


class NoOptions(BaseModel):
    """A kind without protocol options (any key is an error)."""

    model_config = ConfigDict(extra="forbid", frozen=True)


@dataclass(frozen=True)
class ButtonAnswer:
    value: Any
    rt_s: float
    timestamp: str


@dataclass(frozen=True)
class ButtonScreen(ResponseScreen):
    """A screen of buttons after each trial (see the module docstring). Subclasses set
    ``kind`` (and optionally ``item``, ``placement``, ``Options``) and define
    :meth:`question` and :meth:`choices`; :meth:`simulate` may model a participant."""

    kind: ClassVar[str] = "buttons"
    item: ClassVar[str] = ""  # default: the kind
    placement: ClassVar[str] = "after_responses"
    Options: ClassVar[type[BaseModel]] = NoOptions
    options: Any = None  # an Options instance (from the protocol's added_screens entry)

    # ---------------------------------------------------------------- to define
    def question(self, lang: str) -> str:
        raise NotImplementedError

    def choices(self, lang: str) -> list[tuple[Any, str]]:
        """(value, label) per button, left to right."""
        raise NotImplementedError

    def simulate(self, rng: np.random.Generator) -> Any:
        """A simulated participant's answer (default: a button at random)."""
        values = [v for v, _ in self.choices("en")]
        return values[int(rng.integers(len(values)))]

    # ---------------------------------------------------------------- provided
    @classmethod
    def item_id(cls) -> str:
        return cls.item or cls.kind

    def response_keys(self) -> tuple[tuple[int, str], ...]:
        if self.practice or self.trial is None:
            return ()
        return ((self.trial.trial_index, self.item_id()),)

    def browser(self, ctx: BrowserContext) -> dict[str, Any]:
        return {
            "kind": self.kind, "widget": "buttons", "trial_index": self.trial_index,
            "item": self.item_id(), "practice": self.practice,
            "question": self.question(ctx.lang),
            "choices": [{"value": v, "label": label} for v, label in self.choices(ctx.lang)],
        }  # fmt: skip

    def answer(
        self, item: str, posted: Mapping[str, Any], *, rt_s: float, timestamp: str
    ) -> ButtonAnswer:
        value = posted.get("value")
        values = [v for v, _ in self.choices("en")]
        if isinstance(value, bool) or value not in values:
            raise AnswerError(f"value: expected one of {', '.join(map(str, values))}, "
                              f"got {value!r}")  # fmt: skip
        # the choice's own value (a browser's JSON may turn 2 into 2.0)
        return ButtonAnswer(values[values.index(value)], rt_s, timestamp)

    def posted(self, answer: ButtonAnswer) -> dict[str, Any]:
        return {"value": answer.value}

    def row(
        self, item: str, answer: ButtonAnswer, *, context: SessionContext, playback: Any
    ) -> dict[str, Any]:
        return self._row(context=context, playback=playback, item=item, rt_s=answer.rt_s,
                         timestamp=answer.timestamp, response=str(answer.value))  # fmt: skip

    def present(self, presenter: Any) -> list[ButtonAnswer]:
        """The lab window and the simulated participant both show buttons (``buttons``)."""
        return presenter.buttons(self)


def load_screen_plugins() -> list[str]:
    """Register the installed screen kinds (entry-point group ``facelab.screens``: a
    :class:`ButtonScreen` subclass whose ``kind`` is the entry point's name); problems are
    recorded in the entries (``facelab plugins``) and returned."""
    from facelab.plugins import GROUPS, plugin_entries

    problems = []
    for entry in plugin_entries(GROUPS["screens"]):
        if entry.problem is not None:
            problems.append(entry.problem)
            continue
        obj = entry.obj
        where = f"plugin {entry.name!r} from package {entry.package!r} ({entry.value})"
        if not (isinstance(obj, type) and issubclass(obj, ButtonScreen)):
            entry.problem = f"{where} is not a facelab ButtonScreen subclass"
        elif obj.kind != entry.name:
            entry.problem = (f"{where}: the entry point is named {entry.name!r} but its kind "
                             f"is {obj.kind!r}")  # fmt: skip
        elif obj.placement not in PLACEMENTS:
            entry.problem = (f"{where}: placement {obj.placement!r}; expected "
                             f"{', '.join(PLACEMENTS)}")  # fmt: skip
        elif SCREEN_KINDS.get(obj.kind, obj) is not obj:
            entry.problem = f"{where}: a screen kind named {obj.kind!r} exists already"
        else:
            screen_kind(obj)
        if entry.problem is not None:
            problems.append(entry.problem)
    return problems
