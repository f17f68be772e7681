"""``facelab run``: a participant session in a PsychoPy window. The only psychopy user.

Flow: checks (clips and hashes, display, audio, disk) -> session log created (or resumed)
-> participant screen -> instructions -> practice trial (not logged; skipped on resume)
-> trials from the design, from the first unanswered one: the clip with sound, then the VAS
items one after another (or together) -> a break after blocks that ask for one -> end screen.
Every confirmed rating is appended and fsync'd before the next screen. Escape asks before
quitting; quitting keeps every rating given, and ``--resume`` continues.

Playback path (chosen by measurement): ``visual.MovieStim`` (ffpyplayer) - it decodes in
its own thread and slaves the picture to the audio clock, so sound starts with the first
frame; under Xvfb it drew the clip's real frames (checked by pixel statistics) and kept real
time (5.75 s for a 5.7 s clip). Our own frame-by-frame presentation with PsychoPy sound was
the alternative, but PsychoPy's PTB sound could not open an output on a machine without a
sound card (channel-count mismatch on ALSA's null device), so it could not be tested
headless. Every flip time is recorded; a frame counts as dropped when the movie clock skips
it between two flips. The first frame's pixels are checked: a uniform (black) picture stops
the session with an error instead of collecting ratings of nothing.

``--simulate`` drives this same window with a scripted participant: real X mouse and key
events (xdotool) click the VAS line at the model's rating and then the confirm button.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
import shutil
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from facelab.design import Trial, build_trials, participant_seed
from facelab.errors import SessionAbortedError, StageError
from facelab.experiment.preflight import (
    ClipRef,
    check_audio,
    check_clips,
    check_disk,
    check_display,
)
from facelab.experiment.simulate import RatingModel
from facelab.experiment.vas import VasGeometry, VasState
from facelab.protocol import Protocol, VasItem, protocol_hash
from facelab.sessionlog import SessionLog, rating_row, session_paths

__all__ = ["RunOptions", "SessionAbortedError", "run_session"]




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


_UI = {
    "ja": {
        "participant": "参加者 {pid}（セッション {ses}）\n\nスペースキーで開始します。",
        "confirm": "決定",
        "practice": "練習試行です。",
        "quit": "実験を中断しますか？  y: 中断 / n: 続ける",
        "resume": "中断したところから再開します。\n\nスペースキーで続けます。",
        "next": "スペースキーで次へ",
        "break": "休憩です。準備ができたらスペースキーを押してください。",
        "end": "終了です。ありがとうございました。",
    },
    "en": {
        "participant": "Participant {pid} (session {ses})\n\nPress space to start.",
        "confirm": "Confirm",
        "practice": "Practice trial.",
        "quit": "Quit the session?  y: quit / n: continue",
        "resume": "Continuing where the session stopped.\n\nPress space.",
        "next": "Press space to continue",
        "break": "Take a break. Press space when you are ready.",
        "end": "This is the end. Thank you.",
    },
}


def _text(localized: dict[str, str] | None, lang: str, default: str = "") -> str:
    if not localized:
        return default
    return localized.get(lang) or next(iter(localized.values()))


@dataclass
class _Script:
    """A scripted participant: real X events through xdotool, ratings from the model."""

    model: RatingModel
    window_origin: tuple[int, int]
    window_size: tuple[int, int]
    pending: list[tuple[float, list[str]]] = field(default_factory=list)
    planned: dict[int, float] = field(default_factory=dict)  # state id -> time planned

    def __post_init__(self) -> None:
        self.exe = shutil.which("xdotool")
        if self.exe is None:
            raise StageError("--simulate drives the window with xdotool: apt-get install xdotool")
        # the pointer inside the window gives it the keyboard focus (no window manager)
        self._run(["mousemove", *map(str, self.screen_xy(0, 0))])

    def screen_xy(self, x: float, y: float) -> tuple[int, int]:
        ox, oy = self.window_origin
        w, h = self.window_size
        return round(ox + w / 2 + x), round(oy + h / 2 - y)

    def _run(self, args: list[str]) -> None:
        subprocess.run([self.exe, *args], check=False, capture_output=True)

    def schedule(self, delay: float, args: list[str]) -> None:
        self.pending.append((time.perf_counter() + delay, args))

    def tick(self) -> None:
        now = time.perf_counter()
        due = [p for p in self.pending if p[0] <= now]
        self.pending = [p for p in self.pending if p[0] > now]
        for _, args in sorted(due, key=lambda p: p[0]):
            self._run(args)

    def press_key(self, key: str, delay: float = 0.15) -> None:
        self.schedule(delay, ["key", key])

    def answer(self, state_id: int, geometry: VasGeometry, value: float, delay: float) -> None:
        """Click the line at ``value``, release, then click confirm."""
        now = time.perf_counter()
        if state_id in self.planned and now - self.planned[state_id] < 4.0:
            return  # planned recently; re-planned if events were lost (e.g. before focus)
        self.planned[state_id] = now
        x, y = self.screen_xy(geometry.x_of(value), geometry.y_line)
        cx, cy = self.screen_xy(*geometry.confirm_centre)
        self.schedule(delay, ["mousemove", str(x), str(y)])
        self.schedule(delay + 0.05, ["mousedown", "1"])
        self.schedule(delay + 0.12, ["mouseup", "1"])
        self.schedule(delay + 0.30, ["mousemove", str(cx), str(cy)])
        self.schedule(delay + 0.36, ["mousedown", "1"])
        self.schedule(delay + 0.44, ["mouseup", "1"])


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
    """Run (or resume) one session; returns a summary. Raises StageError before any window
    opens when a check fails, SessionAbortedError when the experimenter quits."""
    trials = build_trials(protocol, participant=options.participant)
    clips_dir = options.clips or options.results / protocol.study.id / "clips"
    clips = check_clips(protocol, trials, clips_dir, verify_hashes=options.verify_hashes)
    check_disk(options.results)
    check_display()
    audio = check_audio(allow_dummy=options.simulate)
    paths = session_paths(
        options.results,
        study=protocol.study.id,
        participant=options.participant,
        session=options.session,
    )
    if options.resume:
        log = SessionLog.resume(
            options.results,
            study=protocol.study.id,
            participant=options.participant,
            session=options.session,
        )
        saved = json.loads(log.paths.provenance.read_text(encoding="utf-8"))
        if saved.get("protocol_sha256") != protocol_hash(protocol_path):
            raise StageError(
                f"{protocol_path} changed since this session started (hash differs from "
                f"{log.paths.provenance}); resume with the original protocol file"
            )
        if saved.get("trial_order") != [
            [t.block, t.set_index, t.stimulus, t.condition, t.repetition] for t in trials
        ]:
            raise StageError("the trial order differs from the one this session started with")
    else:
        if paths.tsv.exists():
            raise StageError(
                f"session already exists: {paths.folder}; nothing was overwritten. "
                "Continue it with --resume, or choose another --session"
            )
        log = SessionLog.create(
            options.results,
            study=protocol.study.id,
            participant=options.participant,
            session=options.session,
            provenance={
                "study": protocol.study.id,
                "participant": options.participant,
                "session": options.session,
                "simulated": options.simulate,
                "protocol_file": str(protocol_path),
                "protocol_sha256": protocol_hash(protocol_path),
                "design_seed": participant_seed(protocol.seed, options.participant),
                "trial_order": [
                    [t.block, t.set_index, t.stimulus, t.condition, t.repetition] for t in trials
                ],
                "clips": {"/".join(k): v.sha256 for k, v in clips.items()},
                "software": _versions(),
                "audio_output": audio,
                "started": dt.datetime.now(dt.UTC).isoformat(),
                "resumes": [],
            },
        )
    answered = log.answered()
    todo = [
        t for t in trials if answered.get(t.trial_index, set()) != {i.id for i in protocol.items}
    ]
    if options.resume:
        log.update_provenance(
            resumes=[
                {
                    "at": dt.datetime.now(dt.UTC).isoformat(),
                    "first_trial": todo[0].trial_index if todo else None,
                    "repaired_lines": log.repaired,
                }
            ]
        )
    if not todo:
        return {
            "log": str(log.paths.tsv),
            "ratings": len(log.rows),
            "trials_run": 0,
            "complete": True,
        }
    window = _Window(protocol, options, clips, log, audio)
    try:
        return window.run(trials, todo)
    finally:
        window.close()


class _Window:
    def __init__(
        self,
        protocol: Protocol,
        options: RunOptions,
        clips: dict[tuple[str, str, str], ClipRef],
        log: SessionLog,
        audio: str,
    ):
        os.environ.setdefault("PYGLET_SHADOW_WINDOW", "0")
        from psychopy import core, event, logging, visual

        logging.console.setLevel(logging.ERROR)
        self.core, self.event, self.visual = core, event, visual
        self.protocol, self.options, self.clips, self.log = protocol, options, clips, log
        self.lang = protocol.presentation.language
        self.ui = _UI.get(self.lang, _UI["en"])
        fullscr = protocol.presentation.fullscreen and not options.windowed
        self.win = visual.Window(
            size=options.size,
            fullscr=fullscr,
            units="pix",
            color=(-0.2, -0.2, -0.2),
            allowGUI=not fullscr,
            checkTiming=False,
            screen=0,
            winType="pyglet",
            title="facelab",
        )
        self.size = tuple(int(v) for v in self.win.size)
        self.clock = core.Clock()
        self.mouse = event.Mouse(win=self.win, visible=True)
        self.font = "Noto Sans CJK JP"
        self.script: _Script | None = None
        if options.simulate:
            rng = np.random.default_rng(
                options.sim_seed + participant_seed(0, options.participant) % 1000
            )
            origin = (0, 0)
            if not fullscr:
                try:
                    origin = tuple(int(v) for v in self.win.winHandle.get_location())  # type: ignore[assignment]
                except Exception:
                    origin = (0, 0)
            self.script = _Script(RatingModel(protocol, rng=rng), origin, self.size)
        self.shots_taken: set[str] = set()
        self.audio = audio
        self.log.update_provenance(
            screen={"size": list(self.size), "fullscreen": fullscr, "refresh_hz": self._refresh()}
        )

    def _refresh(self) -> float | None:
        rate = self.win.getActualFrameRate(
            nIdentical=5, nMaxFrames=30, nWarmUpFrames=5, threshold=5
        )
        return None if rate is None else round(float(rate), 2)

    def close(self) -> None:
        self.win.close()

    # -------------------------------------------------------------------- helpers

    def _textstim(
        self,
        text: str,
        *,
        y: float = 0.0,
        height: float | None = None,
        width: float | None = None,
        color: str = "white",
    ):
        return self.visual.TextBox2(
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

    def _check_escape(self, keys: list) -> None:
        if any((k[0] if isinstance(k, tuple) else k) == "escape" for k in keys):
            prompt = self._textstim(self.ui["quit"])
            while True:
                prompt.draw()
                self.win.flip()
                answer = self.event.getKeys(keyList=["y", "n"])
                if "y" in answer:
                    raise SessionAbortedError(
                        f"session stopped by the experimenter; {len(self.log.rows)} ratings "
                        f"are saved in {self.log.paths.tsv}; continue with --resume"
                    )
                if "n" in answer:
                    return
                self.core.wait(0.01)

    def _clear_events(self) -> None:
        """Drop stale input before a new screen, but never an Escape press."""
        escape = self.event.getKeys(keyList=["escape"])
        self.event.clearEvents()
        if escape:
            self._check_escape(escape)

    def _screenshot(self, name: str) -> None:
        if self.options.screenshots and name not in self.shots_taken:
            self.options.screenshots.mkdir(parents=True, exist_ok=True)
            img = self.win.getMovieFrame(buffer="back")
            img.save(self.options.screenshots / f"{name}.png")
            self.win.movieFrames = []
            self.shots_taken.add(name)

    def text_screen(self, text: str, *, shot: str | None = None) -> None:
        stim = self._textstim(text)
        hint = self._textstim(
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
            if shot:
                self._screenshot(shot)
                shot = None
            self.win.flip()
            if self.script:
                self.script.tick()
            keys = self.event.getKeys()
            self._check_escape(keys)
            if "space" in keys:
                return

    # -------------------------------------------------------------------- playback

    def play(self, ref: ClipRef, *, shot: str | None = None) -> dict[str, Any]:
        """Play one clip with sound; returns onset, flips and dropped frames."""
        w, h = self.size
        scale = min(0.95 * w / 16, 0.80 * h / 9)
        movie = self.visual.MovieStim(
            self.win,
            str(ref.path),
            size=(16 * scale, 9 * scale),
            pos=(0, 0.05 * h),
            noAudio=False,
            autoStart=False,
            loop=False,
        )
        fps = ref.fps
        flips: list[float] = []
        shown: list[int] = []
        checked = False
        self._clear_events()
        movie.play()
        deadline = time.perf_counter() + ref.duration_s + 10.0
        try:
            while not movie.isFinished:
                movie.draw()
                if not checked and movie.movieTime > 0:
                    self._check_pixels(movie)
                    checked = True
                if shot and movie.movieTime >= ref.duration_s / 2:
                    self._screenshot(shot)
                    shot = None
                flips.append(self.win.flip())
                shown.append(round(movie.movieTime * fps))
                keys = self.event.getKeys(keyList=["escape"])
                if keys:
                    movie.pause()
                    self._check_escape(keys)
                    movie.play()
                if time.perf_counter() > deadline:
                    raise StageError(
                        f"playback of {ref.path.name} did not finish (stalled decoder?)"
                    )
        finally:
            movie.stop()
            movie.unload()
        distinct = sorted(set(shown))
        expected = max(1, round(ref.duration_s * fps))
        dropped = max(0, expected - len(distinct))
        return {
            "onset": flips[0] if flips else float("nan"),
            "flips": len(flips),
            "dropped": dropped,
            "frames_expected": expected,
            "flip_times": [round(f - flips[0], 5) for f in flips] if flips else [],
            "frames_shown": shown,
        }

    def _record_playback(self, trial: Trial, ref: ClipRef, playback: dict[str, Any]) -> None:
        """Append every flip of the clip (times from its first flip, and the movie frame shown)
        to ``..._playback.jsonl`` beside the log, one line per presentation."""
        path = self.log.paths.tsv.with_name(
            self.log.paths.tsv.name.replace("_beh.tsv", "_playback.jsonl")
        )
        line = json.dumps(
            {
                "trial_index": trial.trial_index,
                "clip": ref.path.name,
                "onset": playback["onset"],
                "frames_expected": playback["frames_expected"],
                "dropped": playback["dropped"],
                "flip_times": playback["flip_times"],
                "frames_shown": playback["frames_shown"],
            }
        )
        with open(path, "a", encoding="utf-8") as fh:
            fh.write(line + "\n")
            fh.flush()
            os.fsync(fh.fileno())

    def _check_pixels(self, movie) -> None:
        img = np.asarray(self.win.getMovieFrame(buffer="back"), dtype=np.float32)
        self.win.movieFrames = []
        h, w = img.shape[:2]
        mw, mh = movie.size
        cx, cy = w / 2 + movie.pos[0], h / 2 - movie.pos[1]
        roi = img[int(cy - mh / 4) : int(cy + mh / 4), int(cx - mw / 4) : int(cx + mw / 4)]
        if roi.size == 0 or roi.std() < 2.0 or roi.mean() < 5.0:
            raise StageError(
                f"the clip {movie.filename} is drawn as a uniform picture (mean "
                f"{roi.mean():.0f}, sd {roi.std():.1f}): the movie backend is not showing "
                "frames; check the psychopy/ffpyplayer installation before running people"
            )

    # -------------------------------------------------------------------- rating

    def ask(
        self, items: list[VasItem], trial: Trial | None, *, shot: str | None = None
    ) -> list[VasState]:
        """Show the items (one after another, or together) and return their confirmed states."""
        layout = self.protocol.presentation.items_layout
        groups = [items] if layout == "together" else [[i] for i in items]
        done: list[VasState] = []
        for group in groups:
            done += self._ask_group(group, trial, shot=shot)
            shot = None
        return done

    def _ask_group(
        self, items: list[VasItem], trial: Trial | None, *, shot: str | None
    ) -> list[VasState]:
        w, h = self.size
        n = len(items)
        rows = []
        for k, item in enumerate(items):
            offset = (0.25 * h * (n - 1) / 2 - 0.32 * h * k) if n > 1 else 0.0
            g = VasGeometry(
                width=w, height=h, low=item.range[0], high=item.range[1], y_line=-0.02 * h + offset
            )
            state = VasState(geometry=g, onset=self.clock.getTime())
            stims = {
                "question": self._textstim(_text(item.question, self.lang), y=g.y_line + 0.16 * h),
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
                "left": self._textstim(
                    _text(item.left_anchor, self.lang),
                    y=g.y_line - 0.06 * h,
                    height=0.026 * h,
                    width=0.3 * w,
                ),
                "right": self._textstim(
                    _text(item.right_anchor, self.lang),
                    y=g.y_line - 0.06 * h,
                    height=0.026 * h,
                    width=0.3 * w,
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
        confirm_label = self._textstim(
            self.ui["confirm"], y=g0.confirm_centre[1], height=0.03 * h, width=g0.confirm_size[0]
        )
        self._clear_events()
        self.mouse.clickReset()
        was_down = False
        targets: dict[int, float] = {}
        if self.script is not None:
            for item, g, state, _ in rows:
                if trial is None:  # practice: a mid-scale answer
                    targets[id(state)] = (g.low + g.high) / 2
                else:
                    targets[id(state)] = self.script.model.rate(
                        item=item.id, stimulus_set=trial.stimulus_set, condition=trial.condition
                    )[0]
        while True:
            if self.script is not None:
                delay = 0.3
                for _, g, state, _ in rows:
                    if state.confirmed_at is None:
                        self.script.answer(id(state), g, targets[id(state)], delay)
                        delay += 0.6
            now = self.clock.getTime()
            x, y = self.mouse.getPos()
            down = bool(self.mouse.getPressed()[0])
            all_rated = all(state.rating is not None for _, _, state, _ in rows)
            if down and not was_down:
                if rows[-1][1].on_confirm(x, y) and all_rated:
                    for _, _, state, _ in rows:
                        state.confirmed_at = now
                else:
                    for _, _, state, _ in rows:
                        state.press(x, y, now)
            elif down:
                for _, _, state, _ in rows:
                    state.move(x, y, now)
            elif was_down:
                for _, _, state, _ in rows:
                    state.release()
            was_down = down
            keys = self.event.getKeys(modifiers=True)
            self._check_escape(keys)
            active = next((s for _, _, s, _ in rows if s.confirmed_at is None), None)
            for key, mods in keys:
                if key in ("return", "space", "num_enter"):
                    if all_rated:
                        for _, _, state, _ in rows:
                            state.confirmed_at = now
                elif active is not None:
                    active.key(key, now, shift=bool(mods.get("shift")))
            if all(state.confirmed_at is not None for _, _, state, _ in rows):
                return [state for _, _, state, _ in rows]
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
            enabled = all_rated
            confirm_box.fillColor = (0.1, 0.45, 0.25) if enabled else (-0.5, -0.5, -0.5)
            confirm_label.color = "white" if enabled else "grey"
            confirm_box.draw()
            confirm_label.draw()
            if shot and not any(st.marker_visible for _, _, st, _ in rows):
                self._screenshot(shot.replace("vas_screen", "vas_before_click"))
            if shot and all_rated:
                self._screenshot(shot)
                shot = None
            self.win.flip()
            if self.script:
                self.script.tick()

    # -------------------------------------------------------------------- session

    def run(self, trials: list[Trial], todo: list[Trial]) -> dict[str, Any]:
        p = self.protocol.presentation
        opts = self.options
        self.text_screen(self.ui["participant"].format(pid=opts.participant, ses=opts.session))
        if opts.resume and len(self.log.rows):
            self.text_screen(self.ui["resume"])
        else:
            if p.instructions:
                self.text_screen(_text(p.instructions, self.lang))
            if p.practice is not None:
                self.text_screen(self.ui["practice"])
                key = (p.practice.stimulus_set, p.practice.stimulus, p.practice.condition)
                self.play(self.clips[key])
                self.ask(list(self.protocol.items), None)
        answered = self.log.answered()
        blocks = {b.id: b for b in self.protocol.blocks}
        ran = 0
        for i, trial in enumerate(todo):
            ref = self.clips[(trial.stimulus_set, trial.stimulus, trial.condition)]
            shot_clip = "clip_mid_playback" if opts.screenshots else None
            playback = self.play(ref, shot=shot_clip)
            self._record_playback(trial, ref, playback)
            remaining = [
                it
                for it in self.protocol.items
                if it.id not in answered.get(trial.trial_index, set())
            ]
            states = self.ask(remaining, trial, shot="vas_screen" if opts.screenshots else None)
            for item, state in zip(remaining, states, strict=True):
                self.log.append(
                    rating_row(
                        study=self.protocol.study.id,
                        participant=opts.participant,
                        session=opts.session,
                        trial=trial,
                        item=item.id,
                        rating=round(float(state.rating), 4),
                        rt_s=round(float(state.rt), 4),
                        clip_onset=round(float(playback["onset"]), 4),
                        clip_frames_dropped=int(playback["dropped"]),
                        timestamp=dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds"),
                    )
                )
                print(
                    f"trial {trial.trial_index}/{len(trials)} {trial.condition} {item.id} = "
                    f"{state.rating:.2f} (saved)",
                    flush=True,
                )
            ran += 1
            nxt = todo[i + 1] if i + 1 < len(todo) else None
            if nxt is not None and nxt.block != trial.block and blocks[trial.block].break_after:
                self.text_screen(_text(p.break_text, self.lang, self.ui["break"]))
        self.text_screen(_text(p.end_text, self.lang, self.ui["end"]))
        self.log.update_provenance(finished=dt.datetime.now(dt.UTC).isoformat())
        return {
            "log": str(self.log.paths.tsv),
            "ratings": len(self.log.rows),
            "trials_run": ran,
            "complete": len(self.log.rows) == len(trials) * len(self.protocol.items),
        }
