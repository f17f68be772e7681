"""The scripted participant of ``facelab run --simulate``: real X input through xdotool.

It moves the pointer and clicks the VAS line at the rating its :class:`RatingModel` gives,
then the confirm button, and presses the space bar on text screens - the same events a
person's mouse and keyboard make, so the whole window path is exercised.

Before every answer it plans, it writes the answer to ``…_actions.jsonl``
(``{"t": unix seconds, "trial_index", "item", "value"}``, fsync'd), so a test can compare
what was done with what was logged. Its generator is seeded with the simulation seed, the
participant and the run number (1 for the first run, 2 after the first resume …), so a
resumed session does not replay the values of the run before.
"""

from __future__ import annotations

import shutil
import subprocess
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from facelab.errors import SessionError
from facelab.experiment.simulate import ChoiceModel, RatingModel
from facelab.experiment.vas import VasGeometry
from facelab.sessionlog import append_jsonl

__all__ = ["ScriptedParticipant"]


@dataclass
class ScriptedParticipant:
    """Real X events through xdotool; values from ``model``; every answer logged first."""

    model: RatingModel
    window_origin: tuple[int, int]
    window_size: tuple[int, int]
    actions: Path
    # events due: (time, xdotool arguments, the screen state they answer)
    pending: list[tuple[float, list[str], int | None]] = field(default_factory=list)
    planned: dict[int, float] = field(default_factory=dict)  # state id -> time planned
    # state id -> the answer chosen: a re-plan (events lost, or not yet seen by a window that
    # stalled) sends the same answer again, so a late click of the first plan agrees with it
    chosen: dict[int, Any] = field(default_factory=dict)
    chooser: ChoiceModel | None = None  # answers forced choices and identifications
    typing: list[subprocess.Popen] = field(default_factory=list)  # xdotool type, running
    # characters outside the keyboard map (kana, kanji) given keycodes of their own before
    # they are typed, least recently given first: see :meth:`_map_characters`
    keycodes: dict[str, int] = field(default_factory=dict)
    spare: list[int] | None = None

    def __post_init__(self) -> None:
        self.exe = shutil.which("xdotool")
        if self.exe is None:
            raise SessionError("--simulate drives the window with xdotool: apt-get install xdotool")
        self.xmodmap = shutil.which("xmodmap")
        if self.xmodmap is None:
            raise SessionError(
                "--simulate types answers with keys mapped by xmodmap: "
                "apt-get install x11-xserver-utils"
            )
        # the pointer inside the window gives it the keyboard focus (no window manager)
        self._run(["mousemove", *map(str, self.screen_xy(0, 0))])

    def screen_xy(self, x: float, y: float) -> tuple[int, int]:
        ox, oy = self.window_origin
        w, h = self.window_size
        return round(ox + w / 2 + x), round(oy + h / 2 - y)

    def _run(self, args: list[str]) -> None:
        if args[0] == "type":  # seconds long: typed while the window goes on drawing
            self._map_characters(args[-1])
            self.typing.append(subprocess.Popen([self.exe, *args], stdout=subprocess.DEVNULL,
                                                stderr=subprocess.DEVNULL))  # fmt: skip
            self.typing = [t for t in self.typing if t.poll() is None]
            return
        subprocess.run([self.exe, *args], check=False, capture_output=True)

    def _map_characters(self, text: str) -> None:
        """Give every character of ``text`` that the keyboard map lacks a keycode of its own,
        before xdotool types it. xdotool would otherwise bind each such character to one
        scratch keycode and unbind it right after the key press; a window that reads its
        events late (a loaded machine) then looks the press up in a keyboard map already
        changed again, and the character is lost (止まった typed, 止った logged). Keycodes
        come from those with no key or only media keys (XF86…) on the X server the test
        starts; the lowest empty one stays free as xdotool's scratch keycode."""
        if self.spare is None:
            table = subprocess.run([self.xmodmap, "-pke"], capture_output=True, text=True)
            free = []
            for line in table.stdout.splitlines():
                code, _, syms = line.removeprefix("keycode").partition("=")
                if all(s == "NoSymbol" or s.startswith("XF86") for s in syms.split()):
                    free.append(int(code))
            self.spare = free[1:]
        new = [c for c in dict.fromkeys(text) if ord(c) > 0x7E and c not in self.keycodes]
        keep = {self.keycodes[c] for c in text if c in self.keycodes}
        # keycodes already given to characters of this text stay; the others are reused
        # least recently given first
        taken = {code: char for char, code in self.keycodes.items()}
        edits = []
        for char in new:
            free = [code for code in self.spare if code not in keep]
            if not free:
                break  # more new characters than keycodes: xdotool binds the rest itself
            code = free[0]
            self.spare.remove(code)
            self.spare.append(code)
            self.keycodes.pop(taken.pop(code, ""), None)
            self.keycodes[char] = taken[code] = code
            keep.add(code)
            edits += ["-e", f"keycode {code} = U{ord(char):04X} U{ord(char):04X}"]
        if edits:
            subprocess.run([self.xmodmap, *edits], check=False, capture_output=True)

    def schedule(self, delay: float, args: list[str], *, state: int | None = None) -> None:
        self.pending.append((time.perf_counter() + delay, args, state))

    def _replan(self, state: int, answer: Any) -> Any:
        """The answer for ``state``: the one chosen before, if any (its events still waiting
        are dropped: the new plan sends them again)."""
        self.pending = [p for p in self.pending if p[2] != state]
        return self.chosen.setdefault(state, answer)

    def tick(self) -> None:
        """Send the events that are due (a key waits while an xdotool is still typing)."""
        now = time.perf_counter()
        typing = any(t.poll() is None for t in self.typing)
        due = [p for p in self.pending if p[0] <= now and not (typing and p[1][0] == "key")]
        self.pending = [p for p in self.pending if p not in due]
        for _, args, _state in sorted(due, key=lambda p: p[0]):
            self._run(args)

    def press_key(self, key: str, delay: float = 0.15) -> None:
        self.schedule(delay, ["key", key])

    def answer_key(
        self, key_id: int, key: str, value: float | str, *, trial_index: int | None, item: str
    ) -> None:
        """Press ``key`` for a choice screen (recorded first); re-planned if lost."""
        now = time.perf_counter()
        if key_id in self.planned and now - self.planned[key_id] < 4.0:
            return
        self.planned[key_id] = now
        value, key = self._replan(key_id, (value, key))
        self.record(trial_index=trial_index, item=item, value=value)
        self.schedule(0.4, ["key", key], state=key_id)

    def answer_text(
        self, field_id: int, text: str, *, trial_index: int | None, item: str
    ) -> None:
        """Type ``text`` into a typed screen's field, one character every 0.15 s (X key
        events; a character the keyboard map lacks, e.g. kana, gets a keycode mapped for it
        while one xdotool types the whole text), then press Return once the typing is done
        (recorded first, once per ``field_id``: a field is never typed into twice)."""
        if field_id in self.planned:
            return
        self.planned[field_id] = time.perf_counter()
        self.record(trial_index=trial_index, item=item, value=text)
        if text:
            self.schedule(0.4, ["type", "--delay", "150", "--", text], state=field_id)
        self.schedule(0.4 + 0.15 * len(text) + 0.8, ["key", "Return"], state=field_id)

    def record(self, *, trial_index: int | None, item: str, value: float | str) -> None:
        """Write the action about to be taken to the actions file (fsync'd)."""
        append_jsonl(
            self.actions,
            {"t": time.time(), "trial_index": trial_index, "item": item, "value": value},
        )

    def answer(
        self,
        state_id: int,
        geometry: VasGeometry,
        value: float,
        delay: float,
        *,
        trial_index: int | None,
        item: str,
    ) -> None:
        """Click the line at ``value``, release, then click confirm."""
        now = time.perf_counter()
        if state_id in self.planned and now - self.planned[state_id] < 4.0:
            return  # planned recently; re-planned if events were lost (e.g. before focus)
        self.planned[state_id] = now
        value = self._replan(state_id, value)
        self.record(trial_index=trial_index, item=item, value=value)
        points = [(geometry.x_of(value), geometry.y_line), geometry.confirm_centre]
        self._click(state_id, points, delay=delay)

    def answer_clicks(
        self,
        state_id: int,
        points: Sequence[tuple[float, float]],
        value: str,
        *,
        trial_index: int | None,
        item: str,
    ) -> None:
        """Click ``points`` (window pixels from its centre) in turn, e.g. a word in each
        column of a matrix and then confirm (recorded first). Called every frame the screen
        is up: the clicks are sent again when the screen is still there 4 s after they all
        went out (clicks lost, e.g. before the window took the pointer; picking a word
        twice is harmless)."""
        now = time.perf_counter()
        planned = self.planned.get(state_id)
        if planned is not None and now - planned < 4.0 + 0.3 * len(points):
            return
        self.planned[state_id] = now
        self.pending = [p for p in self.pending if p[2] != state_id]
        if planned is None:
            self.record(trial_index=trial_index, item=item, value=value)
        self._click(state_id, points, delay=0.4)

    def _click(
        self, state_id: int, points: Sequence[tuple[float, float]], *, delay: float
    ) -> None:
        """Move to each point, press and release there, 0.3 s apart."""
        for i, point in enumerate(points):
            x, y = self.screen_xy(*point)
            for at, args in ((0.0, ["mousemove", str(x), str(y)]), (0.06, ["mousedown", "1"]),
                             (0.14, ["mouseup", "1"])):  # fmt: skip
                self.schedule(delay + 0.3 * i + at, args, state=state_id)
