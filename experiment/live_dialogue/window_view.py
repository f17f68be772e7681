"""``facelab live --display window``: the lab machine's PsychoPy window as a viewer of the live
hub, its speakers playing the talker.

The window is one more viewer of :class:`~facelab.experiment.live_dialogue.app.LiveHub`: a
:class:`LocalSocket` takes the messages a browser viewer's socket would (the talker's audio
chunks, the analysed frames, a turn's start and end) and the window's loop does what the
browser viewer does (``followTurns`` in conversation.js): the sound is played ``playout_ms``
after its first chunk arrived, and at each flip the frame of the audio heard then is shown -
or the newest there is, counted late. Its log goes back to the hub at the end of a turn, so the
turn's latency figures are computed the same way for a window and a browser.

The avatar is drawn by the offline renderer (the same pictures as the protocol's clips) in a
worker process of its own (EGL there, the window's GLX context here; and a core of its own):
each frame is asked for the flip it will be shown on - the time now plus the running render
time - so a frame shown was chosen for the sound heard at that flip. The sound goes out
through PortAudio (``sounddevice``): each 10 ms chunk is written when its time comes minus the
output latency the device reports, so what the speakers play and what the window shows keep
to one clock. A machine without a sound output is refused - the participant must hear the
talker. What this cannot measure: when light leaves the screen and sound leaves the speakers
(see the README's photodiode and microphone procedure).
"""

from __future__ import annotations

import asyncio
import contextlib
import heapq
import json
import math
import multiprocessing
import queue
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from facelab.errors import FacelabError, SessionAbortedError, SessionError, StageError
from facelab.experiment.live_dialogue.app import AUDIO, FRAMES, LiveHub
from facelab.stimuli.methods.live_drive import LIVE_FPS

__all__ = ["LEAD_MAX_S", "LocalSocket", "SoundOut", "WindowViewer", "render_size"]

RENDER_START_S = 120.0  # how long the render worker may take to load the avatar
LOG_AFTER_END_S = 0.2  # the log goes back this long after the turn's last sound was heard
#: the furthest ahead a frame is asked for (s): a frame is never shown more than this before
#: its sound (the live budget's 45 ms, however quick the flip; a slower render shows it late)
LEAD_MAX_S = 0.045
#: a chunk of sound this far past its time (s) is dropped, not played: the sound keeps to the
#: clock the frames follow (after the window was held, e.g. by the quit question)
DROP_LATE_S = 0.1


class LocalSocket:
    """What the hub's ``broadcast`` needs of a viewer's socket, for a viewer in this process:
    every message is queued for the window's thread."""

    def __init__(self) -> None:
        self.inbox: queue.SimpleQueue = queue.SimpleQueue()

    async def send_bytes(self, data: bytes) -> None:
        self.inbox.put(data)

    async def send_text(self, text: str) -> None:
        self.inbox.put(text)


class SoundOut:
    """The talker's voice on this machine's default sound output: :meth:`play` schedules
    ``samples`` (float, mono) to be heard at ``at`` (``time.perf_counter()`` s); a writer
    thread hands each chunk to PortAudio its reported output latency ahead of that time."""

    def __init__(self, *, sample_rate: int) -> None:
        device, self.stream = self.open(sample_rate=sample_rate)
        self.stream.start()
        self.device = str(device.get("name", "?")) if isinstance(device, dict) else "?"
        self.latency_s = float(self.stream.latency)
        self.late = 0  # chunks that arrived after their time (played at once)
        self._queue: list[tuple[float, int, np.ndarray]] = []
        self._n = 0
        self._cv = threading.Condition()
        self._closed = False
        self._thread = threading.Thread(target=self._write, daemon=True)
        self._thread.start()

    @staticmethod
    def open(*, sample_rate: int) -> tuple[Any, Any]:
        """The default output device and a mono float32 stream on it, not started;
        FacelabError in words when there is none (checked before a session starts)."""
        try:
            import sounddevice as sd

            device = sd.query_devices(kind="output")
            stream = sd.OutputStream(samplerate=sample_rate, channels=1, dtype="float32",
                                     latency="low")  # fmt: skip
        except Exception:  # no PortAudio library, no output device, a device that refuses
            raise FacelabError(
                "--display window: this machine has no usable sound output (PortAudio finds "
                "no output device, or it refuses 16 kHz mono): the participant must hear the "
                "talker - connect speakers or headphones, or use --display live3d"
            ) from None
        return device, stream

    @classmethod
    def check(cls, *, sample_rate: int) -> None:
        """FacelabError when :meth:`open` would fail."""
        _, stream = cls.open(sample_rate=sample_rate)
        stream.close()

    def play(self, samples: np.ndarray, *, at: float) -> None:
        if at - self.latency_s < time.perf_counter():
            self.late += 1
        with self._cv:
            heapq.heappush(self._queue, (at, self._n, np.asarray(samples, np.float32)))
            self._n += 1
            self._cv.notify()

    def _write(self) -> None:
        while True:
            with self._cv:
                while not self._closed and not self._queue:
                    self._cv.wait()
                if self._closed:
                    return
                at, _, samples = self._queue[0]
                wait = at - self.latency_s - time.perf_counter()
                if wait > 0:
                    self._cv.wait(min(wait, 0.005))
                    continue
                heapq.heappop(self._queue)
            with contextlib.suppress(Exception):  # a device gone mid-turn: the picture
                self.stream.write(samples.reshape(-1, 1))  # goes on, silent

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._cv.notify()
        self._thread.join(timeout=2)
        with contextlib.suppress(Exception):
            self.stream.stop()
            self.stream.close()


def render_size(*, width: int, height: int, window: tuple[int, int]) -> tuple[int, int]:
    """The protocol's frame (``width`` x ``height`` px) scaled down, if need be, to fit the
    window, its aspect kept (even sizes)."""
    scale = min(1.0, window[0] / width, window[1] / height)
    return max(2, int(width * scale) // 2 * 2), max(2, int(height * scale) // 2 * 2)


def _render_worker(conn, protocol_path: str, names: tuple[str, ...], size: tuple[int, int]):
    """A process of its own: the protocol's avatar drawn by the offline renderer; each
    request ``(K,)`` weights of ``names`` is answered with the frame's RGB bytes."""
    from facelab.blas_threads import one_blas_thread
    from facelab.protocol import load_protocol
    from facelab.stimuli.render.renderer import Renderer
    from facelab.stimuli.render.scene import load_avatar, settings_for

    try:
        path = Path(protocol_path)
        protocol = load_protocol(path)
        avatar = load_avatar(protocol, base_dir=path.parent)
        lacking = [n for n in names if n not in avatar.target_names]
        if lacking:  # the driver was made for another avatar than the protocol's
            raise StageError(f"avatar {avatar.name!r} lacks the targets the live method "
                             f"drives: {', '.join(lacking[:8])}")  # fmt: skip
        columns = np.array([avatar.target_names.index(n) for n in names], dtype=int)
        settings = replace(settings_for(protocol), width=size[0], height=size[1])
        # one BLAS thread: OpenBLAS's idle workers spin, taking the core the window needs
        with one_blas_thread(), Renderer(avatar, settings) as renderer:
            full = np.zeros(len(avatar.target_names))
            conn.send(("ready", None))
            while True:
                weights = conn.recv()
                if weights is None:
                    return
                full[:] = 0.0
                full[columns] = weights
                conn.send_bytes(np.ascontiguousarray(renderer.frame(full)).tobytes())
    except (EOFError, BrokenPipeError, KeyboardInterrupt):
        return
    except FacelabError as exc:
        conn.send(("error", str(exc)))
    except Exception:  # a driver or a model the renderer cannot draw: said, not a traceback
        with contextlib.suppress(OSError, ValueError):
            conn.send(("error", "the offline renderer failed on this avatar (facelab render "
                                "shows the same problem with its details)"))


class FrameRenderer:
    """The render worker, from the window's side: :meth:`ask` for the frame of weights (K,),
    :meth:`take` it, (H, W, 3) uint8, when :meth:`ready` - the window flips meanwhile."""

    def __init__(self, *, protocol_path: Path, names: tuple[str, ...], size: tuple[int, int]):
        ctx = multiprocessing.get_context("spawn")
        self.conn, child = ctx.Pipe()
        self.size = size
        self.proc = ctx.Process(target=_render_worker, daemon=True,
                                args=(child, str(protocol_path), names, size))  # fmt: skip
        self.proc.start()
        child.close()
        if not self.conn.poll(RENDER_START_S):
            self.close()
            raise SessionError(f"the live window: the avatar renderer did not start within "
                               f"{RENDER_START_S:.0f} s")  # fmt: skip
        try:
            kind, detail = self.conn.recv()
        except EOFError:
            kind, detail = "error", "the renderer process ended"
        if kind != "ready":
            self.close()
            raise SessionError(f"the live window: the avatar cannot be drawn: {detail}")

    def ask(self, weights: np.ndarray) -> None:
        """Start drawing weights (K,); :meth:`take` gets the frame (one asked at a time)."""
        self.conn.send(np.asarray(weights, np.float64))

    def ready(self, timeout_s: float = 0.0) -> bool:
        return self.conn.poll(timeout_s)

    def take(self) -> np.ndarray:
        """The asked frame, (H, W, 3) uint8 (waits for it)."""
        try:
            data = self.conn.recv_bytes()
        except (EOFError, OSError):
            raise SessionError("the live window: the avatar renderer stopped") from None
        if len(data) != self.size[0] * self.size[1] * 3:  # its last word, an error
            raise SessionError("the live window: the avatar renderer stopped")
        return np.frombuffer(data, np.uint8).reshape(self.size[1], self.size[0], 3)

    def draw(self, weights: np.ndarray) -> np.ndarray:
        self.ask(weights)
        return self.take()

    def close(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            self.conn.send(None)
        self.proc.join(timeout=5)
        if self.proc.is_alive():
            self.proc.kill()


@dataclass
class _TurnView:
    """One turn as the window follows it (the browser viewer's followTurns state)."""

    names: int
    t0: float | None = None  # perf_counter time at which the turn's sample 0 is heard
    end_s: float | None = None
    have: int = -1
    values: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    log: list[list[float]] = field(default_factory=list)
    arrivals: list[list[float]] = field(default_factory=list)
    sent: bool = False

    def __post_init__(self) -> None:
        self.values = np.zeros((1024, self.names), np.float32)

    def frames(self, start: int, weights: np.ndarray) -> None:
        need = start + len(weights)
        if need > len(self.values):
            grown = np.zeros((max(need, 2 * len(self.values)), self.names), np.float32)
            grown[: len(self.values)] = self.values
            self.values = grown
        self.values[start:need] = weights
        self.have = max(self.have, need - 1)
        if self.t0 is not None:
            self.arrivals.append([start, time.perf_counter() - self.t0])


class WindowViewer:
    """The lab window following the hub's turns (see the module docstring). Use as a context
    manager; :meth:`run` shows turns until Escape (confirmed), ``stop`` is set, or the window
    closes; it returns what it showed."""

    def __init__(
        self,
        hub: LiveHub,
        *,
        loop: asyncio.AbstractEventLoop,
        size: tuple[int, int] = (1280, 800),
        fullscreen: bool = False,
        window: Any = None,
    ) -> None:
        """A window of ``size`` (or full screen) of its own, or the lab session's ``window``
        (a :class:`~facelab.experiment.window.Window`, left open at the end)."""
        from facelab.experiment.window import Window

        self.hub, self.loop = hub, loop
        config = hub.config
        self.sound = SoundOut(sample_rate=hub.driver.sample_rate)
        self.own_window = window is None
        try:
            self.window = window or Window(config.protocol, clips={}, size=size,
                                           fullscreen=fullscreen)  # fmt: skip
        except Exception:
            self.sound.close()
            raise
        r = config.protocol.rendering
        self.frame_size = render_size(width=r.width, height=r.height, window=self.window.size)
        try:
            self.renderer = FrameRenderer(protocol_path=config.protocol_path,
                                          names=hub.driver.names, size=self.frame_size)  # fmt: skip
        except Exception:
            if self.own_window:
                self.window.__exit__()
            self.sound.close()
            raise
        self.socket = LocalSocket()
        self._picture: Any = None
        self.vid: int | None = None
        self.snap: dict[str, float] | None = None  # a requested still: {after_s, peak}
        self.snapshot: Any = None  # PIL image of the window when the still was taken
        self.snapped: dict[str, float] | None = None
        self.best: dict[str, float] | None = None
        self.best_shot: Any = None

    def __enter__(self) -> WindowViewer:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.vid is not None:
            with contextlib.suppress(RuntimeError):  # the loop owns the hub (if it still runs)
                self.loop.call_soon_threadsafe(self.hub.viewers.pop, self.vid, None)
        self.renderer.close()
        self.sound.close()
        if self.own_window:
            self.window.__exit__()

    async def _join(self) -> int:
        vid = self.hub.add_viewer(self.socket)  # type: ignore[arg-type]
        await self.hub.join_turn(vid)
        self.hub.start_file_talker()
        return vid

    def _image(self, frame: np.ndarray) -> Any:
        """The picture stimulus showing ``frame`` (H, W, 3) uint8 (made once, then updated)."""
        # bottom row first; values 0-1 (this PsychoPy draws a float RGB texture as 0-1, not
        # the -1..1 of its docs: measured, and the test compares the window with the frame)
        image = np.flipud(frame).astype(np.float32) / 255.0
        if self._picture is None:
            self._picture = self.window.visual.ImageStim(
                self.window.win, image=image, size=self.frame_size, units="pix",
                colorSpace="rgb", interpolate=True,
            )  # fmt: skip
        else:
            self._picture.image = image
        return self._picture

    def run(
        self, *, stop: threading.Event | None = None, seconds: float | None = None,
        quit_raises: bool = False, caption: str = "",
    ) -> dict[str, Any]:  # fmt: skip
        """Follow turns until Escape (confirmed; with ``quit_raises`` the SessionAbortedError
        goes on to the caller), ``stop`` is set, or ``seconds`` have passed since the window
        joined the hub (the avatar drawn, the talker's sound expected); ``caption`` is shown
        above the avatar throughout. Returns what it showed, with ``seconds_shown``."""
        win, event = self.window.win, self.window.event
        words = _WORDS.get(self.hub.config.protocol.presentation.language, _WORDS["en"])
        status = self.window.text_stim(words["waiting"], y=-0.42 * self.window.size[1],
                                       height=0.028 * self.window.size[1])  # fmt: skip
        k_names = len(self.hub.driver.names)
        top = self.window.text_stim(caption, y=0.44 * self.window.size[1],
                                    height=0.026 * self.window.size[1]) if caption else None
        picture = self._image(self.renderer.draw(np.zeros(k_names)))
        try:
            self.vid = asyncio.run_coroutine_threadsafe(self._join(), self.loop).result(30)
        except TimeoutError:
            raise SessionError("the live window could not join the live server") from None
        until = None if seconds is None else time.perf_counter() + seconds
        turn: _TurnView | None = None
        shown_k: int | None = None  # the frame the window shows
        asked: tuple[int, float] | None = None  # the frame being drawn, and when it was asked
        leads: deque[float] = deque(maxlen=8)  # from asking for a frame to the flip showing it
        began = time.perf_counter()
        flips = turns = 0
        changed = True
        while not (stop is not None and stop.is_set()) and not (
            until is not None and time.perf_counter() >= until
        ):
            turn = self._messages(turn, k_names)
            fresh = None
            if asked is not None and self.renderer.ready(0.002):
                picture = self._image(self.renderer.take())
                shown_k, fresh = asked
                asked, changed = None, True
            if turn is not None and turn.t0 is not None and turn.have >= 0 and asked is None:
                # the frame of the sound heard at the flip that will show it, judged by the
                # quickest recent ask-to-flip time: a frame shown later is late, one shown
                # sooner ahead of the sound - by less than LEAD_MAX_S, however fast the flip
                lead = min(min(leads) if leads else 0.0, LEAD_MAX_S)
                target = time.perf_counter() + lead - turn.t0
                k = max(0, min(math.floor(target * LIVE_FPS + 1e-9), turn.have))
                if k != shown_k:
                    self.renderer.ask(turn.values[k])
                    asked = (k, time.perf_counter())
            if changed:  # else the screen keeps its picture
                picture.draw()
                if top is not None:
                    top.draw()
                if turn is None or turn.t0 is None:
                    status.draw()
                win.flip()
                flips += 1
            elif asked is None:
                time.sleep(0.002)
            now = time.perf_counter()
            if fresh is not None:
                leads.append(now - fresh)
            if changed and turn is not None and turn.t0 is not None and shown_k is not None:
                heard = now - turn.t0
                if heard >= 0 and not turn.sent:
                    wanted = math.floor(heard * LIVE_FPS + 1e-9)
                    turn.log.append([round((now - began) * 1000, 3), heard, shown_k, wanted])
                    self._still(heard, shown_k, turn)
            changed = False
            if turn is not None and turn.t0 is not None:
                ended = turn.end_s is not None and now - turn.t0 > turn.end_s + LOG_AFTER_END_S
                if not turn.sent and ended:
                    self._send_log(turn)
                    turns += 1
                    turn, shown_k = None, None
                    if asked is not None:  # the frame being drawn is not shown now
                        self.renderer.take()
                        asked = None
                    picture = self._image(self.renderer.draw(np.zeros(k_names)))
                    changed = True
            keys = event.getKeys(keyList=["escape"])
            if keys:
                try:
                    self.window._check_escape(keys)
                    changed = True  # the quit question declined: the picture again
                except SessionAbortedError:
                    if quit_raises:
                        raise
                    break
        if turn is not None and not turn.sent and turn.log:
            self._send_log(turn)  # the window closes mid-turn: what it showed is kept
        return {"flips": flips, "turns_shown": turns, "frame_size": list(self.frame_size),
                "seconds_shown": round(time.perf_counter() - began, 3),
                "sound_device": self.sound.device,
                "sound_latency_ms": round(self.sound.latency_s * 1000, 1)}  # fmt: skip

    def _messages(self, turn: _TurnView | None, k_names: int) -> _TurnView | None:
        rate, playout = self.hub.driver.sample_rate, self.hub.config.playout_ms / 1000
        while True:
            try:
                msg = self.socket.inbox.get_nowait()
            except queue.Empty:
                return turn
            if isinstance(msg, str):
                control = json.loads(msg)
                if "turn" in control:  # a new turn: the last one's frames and clock forgotten
                    if turn is not None and not turn.sent and turn.log:
                        self._send_log(turn)
                    turn = _TurnView(names=k_names)
                    self.sound.late = 0
                if "end" in control and turn is not None:
                    turn.end_s = control["end"] / rate
                continue
            kind, start, count, width = struct.unpack_from("<4I", msg)
            data = np.frombuffer(msg, "<f4", count * width, 16).reshape(count, width)
            if turn is None:
                continue
            if kind == AUDIO:
                if turn.t0 is None:
                    turn.t0 = time.perf_counter() + playout - start / rate
                at = turn.t0 + start / rate
                if at < time.perf_counter() - DROP_LATE_S:
                    self.sound.late += 1
                    continue
                self.sound.play(data[:, 0], at=at)
            elif kind == FRAMES:
                turn.frames(start, data)

    def _still(self, heard: float, k: int, turn: _TurnView) -> None:
        """A requested still (``snap = {after_s, peak}``): the window once it showed a frame
        past ``after_s`` whose largest weight reached ``peak``; meanwhile the most moved."""
        if self.snap is None or self.snapshot is not None:
            return
        peak = float(turn.values[k].max()) if turn.values.shape[1] else 0.0
        shown = {"frame": k, "heard": round(heard, 4), "peak": round(peak, 4)}
        if heard > self.snap["after_s"] and peak >= self.snap["peak"]:
            self.snapshot, self.snapped = self._grab(), shown
        elif self.best is None or peak > self.best["peak"]:
            self.best_shot, self.best = self._grab(), shown

    def _grab(self) -> Any:
        """The window as just flipped: its picture drawn again into the back buffer, read
        there (reading the front buffer gives black under some X servers)."""
        self._picture.draw()
        image = self.window.win.getMovieFrame(buffer="back")
        self.window.win.movieFrames = []
        self.window.win.clearBuffer()
        return image

    def _send_log(self, turn: _TurnView) -> None:
        turn.sent = True
        message = {"log": turn.log, "arrivals": turn.arrivals, "poses": [],
                   "late_audio": self.sound.late, "display": "window"}  # fmt: skip
        # handed to the server's loop, which owns the hub's state (as a socket's message is)
        with contextlib.suppress(RuntimeError):  # the server already stopped
            self.loop.call_soon_threadsafe(self.hub.viewer_log, self.vid, message)


_WORDS = {
    "ja": {"waiting": "相手を待っています…"},
    "en": {"waiting": "Waiting for your partner…"},
}
