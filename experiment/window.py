"""The PsychoPy window: one presenter method per screen type. With the runner, the only
psychopy user.

Playback path (chosen by measurement): ``visual.MovieStim`` (ffpyplayer) - it decodes in
its own thread and slaves the picture to the audio clock, so sound starts with the first
frame; under Xvfb it drew the clip's real frames (checked by pixel statistics) and kept real
time (5.75 s for a 5.7 s clip). Our own frame-by-frame presentation with PsychoPy sound was
the alternative, but PsychoPy's PTB sound could not open an output on a machine without a
sound card (channel-count mismatch on ALSA's null device), so it could not be tested
headless. Every flip time is recorded; a frame counts as dropped when the movie clock skips
it between two flips. The first frame's pixels are checked: a uniform (black) picture stops
the session with an error instead of collecting ratings of nothing.

**Flips held to a display's pace.** A flip waits for the display's next refresh, which is
what paces every drawing loop here. Software OpenGL (Mesa's llvmpipe, as under Xvfb) does
not wait: a flip returned after ~1.7 ms, so each loop drew ~600 frames a second and took a
whole core from the clip's decoder and everything else. On a software renderer
(:data:`SOFTWARE_RENDERERS`) a buffer swap returns no sooner than 1 / :data:`PACED_HZ`
after the one before (a swap that waited for a display already took that long, and waits no
more); the session's ``screen`` records ``paced_hz``.

Escape, on any screen, asks before quitting; quitting raises
:class:`~facelab.errors.SessionAbortedError` (every response given is already on disk).
"""

from __future__ import annotations

import functools
import os
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from facelab.errors import SessionAbortedError, SessionError
from facelab.experiment.preflight import ClipRef
from facelab.experiment.scripted import ScriptedParticipant
from facelab.experiment.timeline import (
    ChoiceAnswer,
    ChoiceScreen,
    ClipKey,
    ClipPairScreen,
    ClipScreen,
    ConversationAnswer,
    ConversationScreen,
    IdentifyAnswer,
    IdentifyScreen,
    MatrixScreen,
    PairPlayback,
    Playback,
    TextScreen,
    TypedAnswer,
    TypedScreen,
    VasAnswer,
    VasScreen,
    localized,
    typed_text,
    ui,
)
from facelab.experiment.vas import VasGeometry, VasState
from facelab.protocol import Protocol
from facelab.sessionlog import NA, utc_now

__all__ = ["PACED_HZ", "Window"]

#: refreshes a second the window keeps when its OpenGL does not wait for a display's refresh
PACED_HZ = 60.0
#: OpenGL renderers that draw on the CPU (in their lower-case names): Mesa's llvmpipe,
#: softpipe and classic "Software Rasterizer", SwiftShader, Windows' and macOS's own
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "software rasterizer", "swiftshader",
                      "gdi generic", "apple software renderer")  # fmt: skip


def _paced(swap: Callable[..., Any], *, hz: float) -> Callable[..., Any]:
    """``swap`` (a window's buffer swap) made to return no sooner than ``1 / hz`` s after it
    last returned, as a swap that waits for a display's vertical blank does; the flip that
    called it takes its timestamp after it."""
    period = 1.0 / hz
    last: float | None = None

    def paced_swap(*args: Any, **kwargs: Any) -> Any:
        nonlocal last
        done = swap(*args, **kwargs)
        if last is not None:
            time.sleep(max(0.0, last + period - time.perf_counter()))
        last = time.perf_counter()
        return done

    return paced_swap


def _colour_key(colour: Any) -> tuple[float, ...] | None:
    rgba = getattr(colour, "rgba", None)
    return None if rgba is None else tuple(np.asarray(rgba, float).ravel().tolist())


@functools.cache
def _text_box_class(base: type) -> type:
    """PsychoPy's ``TextBox2`` (``base``) with its palette - the box's border and fill
    colours, with and without focus - worked out again only when one of them changes, not
    three times in every draw: that colour arithmetic took three quarters of a draw (3.1
    against 0.69 ms a draw here, the same pixels), and a screen draws several texts 60 times
    a second."""

    class TextBox(base):  # type: ignore[misc, valid-type]
        @property
        def palette(self) -> Any:
            key = (self.hasFocus, self.borderWidth, _colour_key(self._borderColor),
                   _colour_key(self._fillColor))  # fmt: skip
            if getattr(self, "_facelab_palette_key", None) != key:
                self._facelab_palette = base.palette.fget(self)
                self._facelab_palette_key = key
            return self._facelab_palette

        @palette.setter
        def palette(self, value: Any) -> None:
            base.palette.fset(self, value)
            self._facelab_palette_key = None

    return TextBox


class _Pointer:
    """The left button's presses and releases as the window's events report them, where
    each was made, in the stimuli's pixels (origin at the centre). A polled button state
    misses a click made between two polls - pressed and released while a frame is drawn (a
    quick click, a slow frame, a busy machine) - and by the next poll the pointer may have
    moved on. Use as a context manager around a screen's loop; events arrive when the window
    handles its events (``flip``, ``event.getKeys``)."""

    def __init__(self, win: Any, size: tuple[int, int]):
        self._handle = win.winHandle
        self._size = size
        self.events: list[tuple[str, float, float]] = []  # ("press" | "release", x, y)
        self.held = False  # the button is down (as the events last said)

    def _place(self, x: float, y: float) -> tuple[float, float]:
        # pyglet's event coordinates are in window points from the bottom-left; the stimuli
        # are placed in framebuffer pixels (twice as many on a Retina or scaled display)
        w, h = self._size
        scale = w / max(1, self._handle.width)
        return x * scale - w / 2, y * scale - h / 2

    def _press(self, x: float, y: float, button: int, _modifiers: int) -> None:
        if button == 1:  # the left button
            self.events.append(("press", *self._place(x, y)))

    def _release(self, x: float, y: float, button: int, _modifiers: int) -> None:
        if button == 1:
            self.events.append(("release", *self._place(x, y)))

    def __enter__(self) -> _Pointer:
        self._handle.push_handlers(on_mouse_press=self._press, on_mouse_release=self._release)
        return self

    def __exit__(self, *exc: object) -> None:
        self._handle.remove_handlers(on_mouse_press=self._press, on_mouse_release=self._release)

    def take(self) -> list[tuple[str, float, float]]:
        """The events since the last call, oldest first; :attr:`held` follows them."""
        events, self.events = self.events, []
        for kind, _x, _y in events:
            self.held = kind == "press"
        return events

    def presses(self) -> list[tuple[float, float]]:
        """Where the button was pressed since the last call, oldest first."""
        return [(x, y) for kind, x, y in self.take() if kind == "press"]


class Window:
    """A PsychoPy window that presents timeline screens. Use as a context manager."""

    def __init__(
        self,
        protocol: Protocol,
        *,
        clips: dict[ClipKey, ClipRef],
        size: tuple[int, int],
        fullscreen: bool,
        screenshots: Path | None = None,
    ):
        os.environ.setdefault("PYGLET_SHADOW_WINDOW", "0")
        from psychopy import core, event, logging, visual

        logging.console.setLevel(logging.ERROR)
        self.core, self.event, self.visual = core, event, visual
        self.protocol, self.clips = protocol, clips
        self.lang = protocol.presentation.language
        self.ui = ui(self.lang)
        self.fullscreen = fullscreen
        self.win = visual.Window(
            size=size,
            fullscr=fullscreen,
            units="pix",
            color=(-0.2, -0.2, -0.2),
            allowGUI=not fullscreen,
            checkTiming=False,
            screen=0,
            winType="pyglet",
            title="facelab",
        )
        self.size = tuple(int(v) for v in self.win.size)
        from psychopy.tools.gltools import getOpenGLInfo

        #: the OpenGL renderer's name
        self.gl_renderer = str(getOpenGLInfo().renderer or "")
        software = any(name in self.gl_renderer.lower() for name in SOFTWARE_RENDERERS)
        #: the pace the flips are held to (None: the display's own)
        self.paced_hz = PACED_HZ if software else None
        if self.paced_hz:
            handle = self.win.winHandle  # pyglet's window: its flip() swaps the buffers
            handle.flip = _paced(handle.flip, hz=self.paced_hz)
        self.clock = core.Clock()
        self.mouse = event.Mouse(win=self.win, visible=True)
        self.font = "Noto Sans CJK JP"
        self.script: ScriptedParticipant | None = None
        self.screenshots = screenshots
        self.shots_taken: set[str] = set()
        self.typed_fields = 0  # typed screens shown (the scripted participant's field keys)
        #: hosts a live conversation screen (the runner's RunOptions.conversation, bound to
        #: the session): called with (window, screen), returns a ConversationAnswer
        self.conversation_host: Any = None

    def __enter__(self) -> Window:
        return self

    def __exit__(self, *exc: object) -> None:
        self.win.close()

    def origin(self) -> tuple[int, int]:
        """The window's top-left corner on the X screen (0, 0 when full screen)."""
        if self.fullscreen:
            return (0, 0)
        try:
            x, y = self.win.winHandle.get_location()
            return int(x), int(y)
        except Exception:  # not every backend reports it
            return (0, 0)

    def refresh_hz(self) -> float | None:
        """The display's refresh rate as PsychoPy measures it; None when the flips are paced
        by facelab (:attr:`paced_hz`: there is no display refresh to measure)."""
        if self.paced_hz:
            return None
        rate = self.win.getActualFrameRate(
            nIdentical=5, nMaxFrames=30, nWarmUpFrames=5, threshold=5
        )
        return None if rate is None else round(float(rate), 2)

    # -------------------------------------------------------------------- helpers

    def text_stim(
        self,
        text: str,
        *,
        y: float = 0.0,
        height: float | None = None,
        width: float | None = None,
        color: str = "white",
    ) -> Any:
        """A centred text stimulus in the study's font (``y``, ``height``, ``width`` in pixels
        from the window's centre; lines broken for Japanese too): for screen kinds' ``lab``
        drawings as for facelab's own screens."""
        return _text_box_class(self.visual.TextBox2)(
            self.win,
            text=text,
            font=self.font,
            letterHeight=height or 0.032 * self.size[1],
            pos=(0, y),
            size=(width or 0.85 * self.size[0], None),
            color=color,
            alignment="center",
            lineBreaking="uax14",
        )

    def _check_escape(self, keys: list, pointer: _Pointer | None = None) -> None:
        """Escape asks whether to quit: y stops the session, n goes back to the screen; the
        clicks made while the question was up are dropped from ``pointer`` (no answers to the
        screen)."""
        if any((k[0] if isinstance(k, tuple) else k) == "escape" for k in keys):
            prompt = self.text_stim(self.ui["quit"])
            while True:
                prompt.draw()
                self.win.flip()
                answer = self.event.getKeys(keyList=["y", "n"])
                if "y" in answer:
                    raise SessionAbortedError(
                        "session stopped by the experimenter; every response given is saved; "
                        "continue with --resume"
                    )
                if "n" in answer:
                    if pointer is not None:
                        pointer.take()
                    return
                self.core.wait(0.01)

    def _clear_events(self) -> None:
        """Drop stale input before a new screen, but never an Escape press."""
        escape = self.event.getKeys(keyList=["escape"])
        self.event.clearEvents()
        if escape:
            self._check_escape(escape)

    def _screenshot(self, name: str) -> None:
        if self.screenshots and name not in self.shots_taken:
            self.screenshots.mkdir(parents=True, exist_ok=True)
            img = self.win.getMovieFrame(buffer="back")
            img.save(self.screenshots / f"{name}.png")
            self.win.movieFrames = []
            self.shots_taken.add(name)

    # -------------------------------------------------------------------- text

    def text(self, screen: TextScreen) -> None:
        stim = self.text_stim(screen.text)
        hint = self.text_stim(
            self.ui["next"], y=-0.4 * self.size[1], height=0.022 * self.size[1], color="grey"
        )
        self._clear_events()
        next_press = time.perf_counter() + 0.2
        while True:
            if self.script and time.perf_counter() >= next_press:
                self.script.press_key("space", delay=0.0)
                next_press = time.perf_counter() + 1.5  # again, should a key press get lost
            stim.draw()
            hint.draw()
            self.win.flip()
            if self.script:
                self.script.tick()
            keys = self.event.getKeys()
            self._check_escape(keys)
            if "space" in keys:
                return

    # -------------------------------------------------------------------- playback

    def _announce(self, screen: ClipScreen) -> None:
        """Before a forced choice's clip: a blank gap, then "Clip 1" / "Clip 2" for 0.8 s."""
        if screen.gap_s > 0:
            end = time.perf_counter() + screen.gap_s
            while time.perf_counter() < end:
                self.win.flip()
        label = self.text_stim(
            self.ui["interval"].format(n=screen.interval), height=0.06 * self.size[1]
        )
        end = time.perf_counter() + 0.8
        while time.perf_counter() < end:
            label.draw()
            self.win.flip()
            self._check_escape(self.event.getKeys(keyList=["escape"]))

    def clip(self, screen: ClipScreen) -> Playback:
        """Play one clip with sound; returns onset, flips and dropped frames."""
        if screen.interval is not None:
            self._announce(screen)
        shot = None if screen.practice else "clip_mid_playback"
        return self.play_file(self.clips[screen.clip], shot=shot)

    def play_file(self, ref: ClipRef, *, shot: str | None = None) -> Playback:
        """Play one clip where and as the study's clips play (also a file that is not one of
        the study's: a latency test clip)."""
        w, h = self.size
        scale = min(0.95 * w / 16, 0.80 * h / 9)
        (playback,) = self._play([ref], sizes=[(16 * scale, 9 * scale)],
                                 positions=[(0, 0.05 * h)], sound=0, shot=shot)  # fmt: skip
        return playback

    def clip_pair(self, screen: ClipPairScreen) -> PairPlayback:
        """Play two clips at once, left and right, with the sound of side ``screen.sound``."""
        w, h = self.size
        scale = min(0.47 * w / 16, 0.80 * h / 9)
        left, right = self._play(
            [self.clips[k] for k in screen.clips()],
            sizes=[(16 * scale, 9 * scale)] * 2,
            positions=[(-0.245 * w, 0.05 * h), (0.245 * w, 0.05 * h)],
            sound=screen.sound - 1,
            shot=None if screen.practice else "clip_pair_mid_playback",
        )
        return PairPlayback(left=left, right=right)

    def _play(
        self,
        refs: list[ClipRef],
        *,
        sizes: list[tuple[float, float]],
        positions: list[tuple[float, float]],
        sound: int,
        shot: str | None,
    ) -> list[Playback]:
        """Play the clips ``refs`` together (started on the same flip), only clip ``sound``
        with its sound; one :class:`Playback` per clip, timed on the shared flips."""
        movies = [
            self.visual.MovieStim(
                self.win,
                str(ref.path),
                size=size,
                pos=pos,
                noAudio=i != sound,
                autoStart=False,
                loop=False,
            )
            for i, (ref, size, pos) in enumerate(zip(refs, sizes, positions, strict=True))
        ]
        longest = max(ref.duration_s for ref in refs)
        flips: list[float] = []
        shown: list[list[int]] = [[] for _ in movies]
        checked = False
        self._clear_events()
        for movie in movies:
            movie.play()
        deadline = time.perf_counter() + longest + 10.0
        try:
            while not all(movie.isFinished for movie in movies):
                for movie in movies:
                    movie.draw()
                if not checked and all(movie.movieTime > 0 for movie in movies):
                    for movie in movies:
                        self._check_pixels(movie)
                    checked = True
                if shot and max(movie.movieTime for movie in movies) >= longest / 2:
                    self._screenshot(shot)
                    shot = None
                flips.append(self.win.flip())
                for frames, movie, ref in zip(shown, movies, refs, strict=True):
                    frames.append(round(movie.movieTime * ref.fps))
                keys_down = self.event.getKeys(keyList=["escape"])
                if keys_down:
                    for movie in movies:
                        movie.pause()
                    self._check_escape(keys_down)
                    for movie in movies:
                        movie.play()
                if time.perf_counter() > deadline:
                    raise SessionError(
                        f"playback of {', '.join(r.path.name for r in refs)} did not finish "
                        "(stalled decoder?)"
                    )
        finally:
            for movie in movies:
                movie.stop()
                movie.unload()
        out = []
        for ref, frames in zip(refs, shown, strict=True):
            expected = max(1, round(ref.duration_s * ref.fps))
            out.append(
                Playback(
                    onset=round(float(flips[0]), 4) if flips else float("nan"),
                    dropped=max(0, expected - len(set(frames))),
                    frames_expected=expected,
                    flip_times=tuple(round(f - flips[0], 5) for f in flips) if flips else (),
                    frames_shown=tuple(frames),
                )
            )
        return out

    def _check_pixels(self, movie: Any) -> None:
        img = np.asarray(self.win.getMovieFrame(buffer="back"), dtype=np.float32)
        self.win.movieFrames = []
        h, w = img.shape[:2]
        mw, mh = movie.size
        cx, cy = w / 2 + movie.pos[0], h / 2 - movie.pos[1]
        roi = img[int(cy - mh / 4) : int(cy + mh / 4), int(cx - mw / 4) : int(cx + mw / 4)]
        if roi.size == 0 or roi.std() < 2.0 or roi.mean() < 5.0:
            raise SessionError(
                f"the clip {movie.filename} is drawn as a uniform picture (mean "
                f"{roi.mean():.0f}, sd {roi.std():.1f}): the movie backend is not showing "
                "frames; check the psychopy/ffpyplayer installation before running people"
            )

    # -------------------------------------------------------------------- choices

    def _choose(
        self,
        *,
        question: str,
        options: list[str],
        hint: str,
        shot: str | None,
        scripted: tuple[int, float | str, int | None, str] | None,
    ) -> tuple[int, float]:
        """Show ``options`` as numbered buttons under ``question``; returns (index, rt in s).

        Keys 1..n (top row or keypad) or a click choose. ``scripted``: (index, logged value,
        trial index, item) for the scripted participant."""
        w, h = self.size
        n = len(options)
        width = min(0.8 * w / n, 0.3 * w)
        xs = [(i - (n - 1) / 2) * (width + 0.02 * w) for i in range(n)]
        box_h = 0.14 * h if n <= 3 else 0.18 * h
        boxes = [
            self.visual.Rect(
                self.win,
                width=width,
                height=box_h,
                pos=(x, -0.05 * h),
                lineColor="white",
                lineWidth=2,
                fillColor=(-0.45, -0.45, -0.45),
            )
            for x in xs
        ]
        labels = [
            self.text_stim(
                f"{i + 1}\n{text}" if text != str(i + 1) else text,
                y=-0.05 * h,
                height=0.028 * h if n > 2 else 0.05 * h,
                width=0.95 * width,
            )
            for i, text in enumerate(options)
        ]
        for stim, x in zip(labels, xs, strict=True):
            stim.pos = (x, -0.05 * h)
        prompt = self.text_stim(question, y=0.2 * h)
        hint_stim = self.text_stim(hint, y=-0.35 * h, height=0.022 * h, color="lightgrey")
        keys = {str(i + 1): i for i in range(n)} | {f"num_{i + 1}": i for i in range(n)}
        script = None
        if scripted is not None:
            index, value, trial_index, item = scripted
            script = (str(index + 1), value, trial_index, item)
        return self.show(
            stims=[prompt, *(x for pair in zip(boxes, labels, strict=True) for x in pair),
                   hint_stim],
            keys=keys, clickable=list(zip(boxes, range(n), strict=True)), shot=shot,
            scripted=script,
        )  # fmt: skip

    def show(
        self,
        *,
        stims: Sequence[Any],
        keys: Mapping[str, Any],
        clickable: Sequence[tuple[Any, Any]] = (),
        shot: str | None = None,
        scripted: tuple[str, Any, int | None, str] | None = None,
    ) -> tuple[Any, float]:
        """Draw ``stims`` (PsychoPy stimuli, in order) each frame until a key of ``keys`` is
        pressed or a ``clickable`` stimulus clicked; returns (its value, response time in s).

        For screen kinds from packages (``AddedScreen.lab``) as for facelab's own button
        screens. ``shot``: the screenshot's name (the first frame). ``scripted``: (key, logged
        value, trial index, item) the scripted participant presses (see
        :meth:`scripted_value`); Escape quits as everywhere."""
        self._clear_events()
        self.mouse.clickReset()
        onset = time.perf_counter()
        with _Pointer(self.win, self.size) as pointer:
            while True:
                if self.script is not None and scripted is not None:
                    key, value, trial_index, item = scripted
                    self.script.answer_key(id(stims), key, value, trial_index=trial_index,
                                           item=item)  # fmt: skip
                for stim in stims:
                    stim.draw()
                if shot:
                    self._screenshot(shot)
                    shot = None
                self.win.flip()
                if self.script:
                    self.script.tick()
                pressed = self.event.getKeys()
                self._check_escape(pressed, pointer)
                for key in pressed:
                    if key in keys:
                        return keys[key], time.perf_counter() - onset
                for x, y in pointer.presses():
                    for stim, value in clickable:
                        if stim.contains(x, y, units="pix"):  # a plugin's stim: any units
                            return value, time.perf_counter() - onset

    def choice_2afc(self, screen: ChoiceScreen) -> list[ChoiceAnswer]:
        """Which of the two clips? Keys 1/2 or a click on a button."""
        assert screen.task is not None
        scripted = None
        if self.script is not None and self.script.chooser is not None:
            if screen.trial is None or screen.practice:
                scripted = (0, 1, None, screen.task.id)
            else:
                pick = self.script.chooser.choose(screen)
                scripted = (pick - 1, pick, screen.trial_index, screen.task.id)
        index, rt = self._choose(
            question=localized(screen.task.question, self.lang),
            options=["1", "2"] if screen.task.layout == "sequential" else screen.options(self.lang),
            hint=self.ui["choice_keys"],
            shot=None if screen.practice else "choice_2afc_screen",
            scripted=scripted,
        )
        return [ChoiceAnswer(choice=index + 1, rt_s=round(rt, 4), timestamp=utc_now())]

    def identify(self, screen: IdentifyScreen) -> list[IdentifyAnswer]:
        """Which label? Number keys or a click on a label."""
        assert screen.task is not None
        ids = [lb.id for lb in screen.task.labels]
        scripted = None
        if self.script is not None and self.script.chooser is not None:
            if screen.trial is None or screen.practice:
                scripted = (0, ids[0], None, screen.task.id)
            else:
                label = self.script.chooser.identify(screen)
                scripted = (ids.index(label), label, screen.trial_index, screen.task.id)
        index, rt = self._choose(
            question=localized(screen.task.question, self.lang),
            options=[localized(lb.text, self.lang) for lb in screen.task.labels],
            hint=self.ui["label_keys"],
            shot=None if screen.practice else "identify_screen",
            scripted=scripted,
        )
        return [IdentifyAnswer(label=ids[index], rt_s=round(rt, 4), timestamp=utc_now())]

    def typed(self, screen: TypedScreen) -> list[TypedAnswer]:
        """Type what was said: a text field (the system's input method, e.g. a Japanese IME,
        composes into it), confirmed by Return or a click on the confirm button."""
        assert screen.task is not None
        w, h = self.size
        limit = screen.task.max_length
        prompt = self.text_stim(localized(screen.task.question, self.lang), y=0.2 * h)
        field = _text_box_class(self.visual.TextBox2)(
            self.win, text="", font=self.font, letterHeight=0.045 * h, pos=(0, 0),
            size=(0.7 * w, 0.1 * h), editable=True, color="white", borderColor="white",
            fillColor=(-0.45, -0.45, -0.45), alignment="left", lineBreaking="uax14",
        )  # fmt: skip
        field.hasFocus = True  # the window sends typed text to its current editable only
        confirm_box = self.visual.Rect(
            self.win, width=0.2 * w, height=0.08 * h, pos=(0, -0.18 * h), lineColor="white",
            lineWidth=2, fillColor=(0.1, 0.45, 0.25),
        )  # fmt: skip
        confirm_label = self.text_stim(self.ui["confirm"], y=-0.18 * h, height=0.03 * h,
                                       width=0.2 * w)  # fmt: skip
        hint = self.text_stim(self.ui["typed_keys"], y=-0.35 * h, height=0.022 * h,
                              color="lightgrey")  # fmt: skip
        if self.script is not None:
            chooser = self.script.chooser
            practice = screen.trial is None or screen.practice or chooser is None
            text = screen.said if practice else chooser.typed(screen)  # type: ignore[union-attr]
            trial_index = None if practice else screen.trial_index
            self.typed_fields += 1  # a key of its own (an id() may come back for a new field)
            self.script.answer_text(-self.typed_fields, text, item=screen.task.id,
                                    trial_index=trial_index)  # fmt: skip
        self._clear_events()
        self.mouse.clickReset()
        onset = time.perf_counter()
        shot = None if screen.practice else "typed_screen"
        with _Pointer(self.win, self.size) as pointer:
            while True:
                if len(field.text) > limit:
                    field.text = field.text[:limit]
                for stim in (prompt, field, confirm_box, confirm_label, hint):
                    stim.draw()
                self.win.flip()
                if self.script:
                    self.script.tick()
                keys = self.event.getKeys()
                self._check_escape(keys, pointer)
                clicked = any(confirm_box.contains(x, y, units="pix")
                              for x, y in pointer.presses())  # fmt: skip
                if (clicked or any(k in ("return", "num_enter") for k in keys)) and typed_text(
                        str(field.text)) != NA:  # fmt: skip # the log's missing mark: no answer
                    rt = time.perf_counter() - onset
                    if shot:  # the answer as confirmed
                        for stim in (prompt, field, confirm_box, confirm_label, hint):
                            stim.draw()
                        self._screenshot(shot)
                        self.win.clearBuffer()
                    text = typed_text(str(field.text))[:limit]
                    self.win.removeEditable(field)  # the next screen's field gets the keys
                    return [TypedAnswer(text=text, rt_s=round(rt, 4), timestamp=utc_now())]

    def matrix(self, screen: MatrixScreen) -> list[TypedAnswer]:
        """Pick the word heard in each column of the matrix (a click; a second click in a
        column moves the pick), then confirm: the confirm button takes a click once every
        column has a pick."""
        assert screen.task is not None
        w, h = self.size
        columns = screen.task.columns
        n, rows = len(columns), max(len(c) for c in columns)
        col_w = min(0.9 * w / n, 0.3 * w)
        row_h = min(0.065 * h, 0.58 * h / rows)
        top = 0.30 * h - row_h / 2
        xs = [(i - (n - 1) / 2) * col_w for i in range(n)]
        cells: list[tuple[Any, Any, int, str]] = []  # (box, label, column, word)
        for ci, (x, column) in enumerate(zip(xs, columns, strict=True)):
            for ri, word in enumerate(column):
                y = top - ri * row_h
                box = self.visual.Rect(self.win, width=0.94 * col_w, height=0.9 * row_h,
                                       pos=(x, y), lineColor="grey", lineWidth=1,
                                       fillColor=(-0.45, -0.45, -0.45))  # fmt: skip
                label = self.text_stim(word, y=y, height=min(0.028 * h, 0.6 * row_h),
                                       width=0.9 * col_w)  # fmt: skip
                label.pos = (x, y)
                cells.append((box, label, ci, word))
        prompt = self.text_stim(localized(screen.task.question, self.lang), y=0.38 * h,
                                height=0.03 * h)  # fmt: skip
        confirm_y = top - (rows - 0.5) * row_h - 0.06 * h
        confirm_box = self.visual.Rect(
            self.win, width=0.2 * w, height=0.07 * h, pos=(0, confirm_y), lineColor="white",
            lineWidth=2, fillColor=(0.1, 0.45, 0.25),
        )  # fmt: skip
        confirm_label = self.text_stim(self.ui["confirm"], y=confirm_y, height=0.03 * h,
                                       width=0.2 * w)  # fmt: skip
        hint = self.text_stim(self.ui["matrix_keys"], y=confirm_y - 0.075 * h,
                              height=0.022 * h, color="lightgrey")  # fmt: skip
        script = None
        if self.script is not None:  # the scripted participant's clicks, planned once
            chooser = self.script.chooser
            practice = screen.trial is None or screen.practice or chooser is None
            text = screen.said if practice else chooser.matrix(screen)  # type: ignore[union-attr]
            centres = {(ci, word): box.pos for box, _label, ci, word in cells}
            points = [tuple(centres[(ci, word)]) for ci, word in enumerate(text.split(" "))]
            self.typed_fields += 1
            script = (-self.typed_fields, [*points, (0.0, confirm_y)], text,
                      None if practice else screen.trial_index)  # fmt: skip
        picked: dict[int, str] = {}
        self._clear_events()
        self.mouse.clickReset()
        onset = time.perf_counter()
        shot = None if screen.practice else "matrix_screen"

        shown: dict[int, bool] = {}  # cell -> drawn as picked (colours set on a change only:
        # PsychoPy validates a colour on every set, ~0.1 ms, for 50 words a frame)

        def draw() -> None:
            for k, (box, label, ci, word) in enumerate(cells):
                on = picked.get(ci) == word
                if shown.get(k) is not on:
                    box.fillColor = (-0.75, 0.0, -0.5) if on else (-0.45,) * 3
                    box.lineColor = "white" if on else "grey"
                    shown[k] = on
                box.draw()
                label.draw()
            confirm_box.opacity = 1.0 if len(picked) == n else 0.35
            for stim in (prompt, confirm_box, confirm_label, hint):
                stim.draw()

        # every press where it was made (a frame of 50 words is slow enough to miss a click)
        with _Pointer(self.win, self.size) as pointer:
            while True:
                draw()
                self.win.flip()
                if self.script is not None and script is not None:
                    state, clicks, text, trial_index = script
                    self.script.answer_clicks(state, clicks, text, trial_index=trial_index,
                                              item=screen.task.id)  # fmt: skip
                if self.script:
                    self.script.tick()
                self._check_escape(self.event.getKeys(), pointer)  # takes the window's events
                for x, y in pointer.presses():
                    for box, _label, ci, word in cells:
                        if box.contains(x, y, units="pix"):
                            picked[ci] = word
                    if len(picked) == n and confirm_box.contains(x, y, units="pix"):
                        rt = time.perf_counter() - onset
                        if shot:  # the answer as confirmed
                            draw()
                            self._screenshot(shot)
                            self.win.clearBuffer()
                        text = " ".join(picked[i] for i in range(n))
                        return [TypedAnswer(text=text, rt_s=round(rt, 4), timestamp=utc_now())]

    def conversation(self, screen: ConversationScreen) -> list[ConversationAnswer]:
        """A live conversation (presentation.conversation) in this window: the partner's
        avatar drawn from the talker's streamed voice, for the conversation's minutes."""
        if self.conversation_host is None:
            raise SessionError("presentation.conversation: this window has no live server "
                               "for the talker (facelab run starts one)")  # fmt: skip
        self._clear_events()
        return [self.conversation_host(self, screen)]

    def added_screen(self, screen: Any) -> list[Any]:
        """A screen kind from a package (``AddedScreen``): drawn by the kind's ``lab``."""
        from facelab.experiment.screen_kinds import AddedAnswer

        value, rt = screen.lab(self)
        return [AddedAnswer(value, round(rt, 4), utc_now())]

    def scripted_value(self, screen: Any) -> Any:
        """The answer the scripted participant gives to an added screen (its kind's
        ``simulate``), None without a script."""
        if self.script is None:
            return None
        chooser = self.script.chooser
        return screen.simulate(chooser.rng if chooser is not None else self.script.model.rng)

    def buttons(self, screen: Any) -> tuple[Any, float]:
        """A ``ButtonScreen``: its question and buttons, number keys or a click; returns
        (value, response time in s)."""
        choices = screen.choices(self.lang)
        scripted = None
        value = self.scripted_value(screen)
        if value is not None:
            index = [v for v, _ in choices].index(value)
            scripted = (index, value, screen.trial_index, screen.item_id())
        index, rt = self._choose(
            question=screen.question(self.lang),
            options=[label for _, label in choices],
            hint=self.ui["label_keys"],
            shot=None if screen.practice else f"{screen.kind}_screen",
            scripted=scripted,
        )
        return choices[index][0], rt

    # -------------------------------------------------------------------- VAS

    def vas(self, screen: VasScreen) -> list[VasAnswer]:
        """Show the screen's items and return their confirmed answers."""
        w, h = self.size
        items = screen.items
        n = len(items)
        shot = None if screen.practice else "vas_screen"
        rows = []
        for k, item in enumerate(items):
            offset = (0.25 * h * (n - 1) / 2 - 0.32 * h * k) if n > 1 else 0.0
            g = VasGeometry(
                width=w, height=h, low=item.range[0], high=item.range[1], y_line=-0.02 * h + offset
            )
            state = VasState(geometry=g, onset=self.clock.getTime())
            stims = {
                "question": self.text_stim(
                    localized(item.question, self.lang), y=g.y_line + 0.16 * h
                ),
                "line": self.visual.Line(
                    self.win,
                    start=(g.x_left, g.y_line),
                    end=(g.x_right, g.y_line),
                    lineColor="white",
                    lineWidth=4,
                ),
                "ticks": [
                    self.visual.Line(
                        self.win,
                        start=(x, g.y_line - 12),
                        end=(x, g.y_line + 12),
                        lineColor="white",
                        lineWidth=4,
                    )
                    for x in (g.x_left, g.x_right)
                ],
                "left": self.text_stim(
                    localized(item.left_anchor, self.lang), height=0.026 * h, width=0.3 * w
                ),
                "right": self.text_stim(
                    localized(item.right_anchor, self.lang), height=0.026 * h, width=0.3 * w
                ),
                "marker": self.visual.Rect(
                    self.win, width=10, height=44, fillColor=(0.9, 0.3, 0.2), lineColor=None
                ),
            }
            stims["left"].pos = (g.x_left, g.y_line - 0.06 * h)
            stims["right"].pos = (g.x_right, g.y_line - 0.06 * h)
            rows.append((item, g, state, stims))
        g0 = rows[-1][1]
        confirm_box = self.visual.Rect(
            self.win,
            width=g0.confirm_size[0],
            height=g0.confirm_size[1],
            pos=g0.confirm_centre,
            lineColor="white",
            lineWidth=2,
        )
        confirm_label = self.text_stim(
            self.ui["confirm"], y=g0.confirm_centre[1], height=0.03 * h, width=g0.confirm_size[0]
        )
        self._clear_events()
        self.mouse.clickReset()
        targets: dict[int, float] = {}
        trial = screen.trial
        if self.script is not None:
            for item, g, state, _ in rows:
                if trial is None or screen.practice:  # practice: a mid-scale answer
                    targets[id(state)] = (g.low + g.high) / 2
                else:
                    targets[id(state)] = self.script.model.rate(
                        item=item.id, stimulus_set=trial.stimulus_set, condition=trial.condition
                    )[0]
        enabled: bool | None = None  # the confirm button as drawn: enabled or not
        with _Pointer(self.win, self.size) as pointer:
            while True:
                if self.script is not None:
                    delay = 0.3
                    for item, g, state, _ in rows:
                        if state.confirmed_at is None:
                            self.script.answer(
                                id(state),
                                g,
                                targets[id(state)],
                                delay,
                                trial_index=None if screen.practice else screen.trial_index,
                                item=item.id,
                            )
                            delay += 0.6
                now = self.clock.getTime()
                for kind, x, y in pointer.take():  # every press and release, where it was made
                    rated = all(state.rating is not None for _, _, state, _ in rows)
                    for _, _, state, _ in rows:
                        if kind == "release":  # the drag ends where the button was let go
                            state.move(x, y, now)
                            state.release()
                        elif rows[-1][1].on_confirm(x, y) and rated:
                            state.confirmed_at = now
                        else:
                            state.press(x, y, now)
                if pointer.held:  # a drag along the line follows the pointer
                    x, y = self.mouse.getPos()
                    for _, _, state, _ in rows:
                        state.move(x, y, now)
                all_rated = all(state.rating is not None for _, _, state, _ in rows)
                keys = self.event.getKeys(modifiers=True)
                self._check_escape(keys, pointer)
                active = next((s for _, _, s, _ in rows if s.confirmed_at is None), None)
                for key, mods in keys:
                    if key in ("return", "space", "num_enter"):
                        if all_rated:
                            for _, _, state, _ in rows:
                                state.confirmed_at = now
                    elif active is not None:
                        active.key(key, now, shift=bool(mods.get("shift")))
                if all(state.confirmed_at is not None for _, _, state, _ in rows):
                    stamp = utc_now()
                    return [
                        VasAnswer(
                            item=item.id,
                            rating=round(float(state.rating), 4),
                            rt_s=round(float(state.rt), 4),
                            timestamp=stamp,
                        )
                        for item, _, state, _ in rows
                    ]
                for _, g, state, stims in rows:
                    stims["question"].draw()
                    stims["line"].draw()
                    for t in stims["ticks"]:
                        t.draw()
                    stims["left"].draw()
                    stims["right"].draw()
                    if state.marker_visible:  # hidden until the first click or arrow key
                        stims["marker"].pos = (g.x_of(state.rating), g.y_line)
                        stims["marker"].draw()
                if enabled is not all_rated:  # set on a change only (a TextBox2 lays its
                    # text out again whenever its colour is set)
                    confirm_box.fillColor = (0.1, 0.45, 0.25) if all_rated else (-0.5,) * 3
                    confirm_label.color = "white" if all_rated else "grey"
                    enabled = all_rated
                confirm_box.draw()
                confirm_label.draw()
                if shot and not any(st.marker_visible for _, _, st, _ in rows):
                    self._screenshot("vas_before_click")
                if shot and all_rated:
                    self._screenshot(shot)
                    shot = None
                self.win.flip()
                if self.script:
                    self.script.tick()
