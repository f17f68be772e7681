"""A condition's method driven from streaming audio (``facelab live``): audio chunks in, the
avatar's frames out, causally - each frame as soon as the audio it depends on has arrived.

The chain is the offline one (:func:`facelab.stimuli.speech.analyser.analyze`,
``compensated()``, the method's ``drive_on``) cut into chunks: the analyser streams
(:class:`~facelab.stimuli.speech.analyser.WarpAdaptingAnalyzer`: the mel-filter warp chosen
as offline, on the audio heard so far; or a fixed warp), the smoothing lag is removed by
interpolating between an analysis frame and the next one (so frame k waits for analysis frame
k + 1), and the method drives each new stretch of frames. Frame k is the avatar's face at
k / :data:`LIVE_FPS` s of the talker's audio, the same values the offline chain at the same
warp gives the recording (``tests/test_live_dialogue.py`` checks it).

A method runs live when it says so (:attr:`Method.live_problem` is None) and when driving a
track in pieces gives what driving it whole gives (:func:`live_problem`): a method whose frame
depends on later frames (an envelope timed against the clip's length) cannot run on a stream.
The condition's behaviour layer (blinks, head motion) is not run live; the turn's record says so.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from facelab.errors import FacelabError, StageError
from facelab.stimuli.avatar.mesh import Avatar
from facelab.stimuli.methods.registry import get
from facelab.stimuli.methods.types import DriveInput
from facelab.stimuli.speech.analyser import (
    StreamingAnalyzer,
    VisemeModel,
    WarpAdaptingAnalyzer,
    default_model,
)
from facelab.stimuli.speech.track import VISEMES, VisemeTrack

__all__ = ["LIVE_FPS", "LiveDriver", "LiveFrames", "live_problem"]

#: frames per second of a live track: one per analysis frame (10 ms)
LIVE_FPS = 100
_HOP_S = 1.0 / LIVE_FPS


@dataclass(frozen=True)
class LiveFrames:
    """Frames ``start`` .. ``start + len(weights) - 1`` of a live track: ``weights`` (n, K) in
    [0, 1], columns the driver's ``names``; frame k is the face at k / LIVE_FPS s of audio."""

    start: int
    weights: np.ndarray

    def __len__(self) -> int:
        return len(self.weights)


def _probe_track(n: int, *, seed: int = 7) -> VisemeTrack:
    rng = np.random.default_rng(seed)
    w = rng.dirichlet(np.full(len(VISEMES), 0.3), size=n)
    return VisemeTrack(times=np.arange(n) * _HOP_S, weights=w)


def live_problem(
    method_name: str, params: Any, *, avatar: Avatar, base_dir: Path = Path(".")
) -> str | None:
    """Why the method cannot drive ``avatar`` from streaming audio, None when it can: the
    method's own word (:attr:`Method.live_problem`), then a check that driving a random track
    in pieces of 7 frames gives what driving it whole gives."""
    method = get(method_name)
    if method.live_problem is not None:
        return f"method {method_name!r} cannot run live: {method.live_problem}"
    probe = _probe_track(64)
    try:
        drive = method.prepared(avatar, params, base_dir=base_dir)
        whole = method.drive_on(avatar, DriveInput(track=probe, base_dir=base_dir), params)
        parts = [
            drive(DriveInput(track=_slice(probe, k, k + 7), base_dir=base_dir))
            for k in range(0, 64, 7)
        ]
    except FacelabError as exc:
        return f"method {method_name!r} cannot run live: {exc}"
    pieces = np.vstack([_columns(p, whole.names) for p in parts])
    if pieces.shape != whole.weights.shape or not np.allclose(pieces, whole.weights, atol=1e-6):
        return (f"method {method_name!r} cannot run live: a frame's value depends on frames "
                "after it (driven in pieces it differs from the whole)")  # fmt: skip
    return None


def _slice(track: VisemeTrack, a: int, b: int) -> VisemeTrack:
    return VisemeTrack(times=track.times[a:b], weights=track.weights[a:b], warp=track.warp)


def _columns(track, names: tuple[str, ...]) -> np.ndarray:
    out = np.zeros((len(track.times), len(names)))
    index = {n: j for j, n in enumerate(track.names)}
    for j, n in enumerate(names):
        if n in index:
            out[:, j] = track.weights[:, index[n]]
    return out


class LiveDriver:
    """Streaming audio -> the condition's frames for ``avatar`` (see the module docstring).

    sample_rate : Hz, >= 16 kHz and a multiple of 100 (the analyser's framing; a browser's
    capture runs at 16 kHz). ``names``: the avatar targets the method moves, the columns of
    every :class:`LiveFrames`. The method is checked and prepared once; :meth:`restart` begins
    the next turn's stream. Not thread-safe: one talker per driver.
    """

    def __init__(
        self,
        *,
        method_name: str,
        params: Any,
        avatar: Avatar,
        sample_rate: int,
        base_dir: Path = Path("."),
        model: VisemeModel | None = None,
        warp: float | str = "auto",
        start_warp: float = 1.0,
    ) -> None:
        problem = live_problem(method_name, params, avatar=avatar, base_dir=base_dir)
        if problem is not None:
            raise StageError(problem)
        if sample_rate < 16_000 or sample_rate % 100:
            raise StageError(f"live audio at {sample_rate} Hz: expected a rate of at least "
                             "16000 Hz that is a multiple of 100")  # fmt: skip
        if isinstance(warp, str) and warp != "auto":
            raise StageError(f"warp {warp!r}: use 'auto' or a number")
        self.base_dir = Path(base_dir)
        self.sample_rate = sample_rate
        self.model = model or default_model()
        self.warp = warp
        self.lag_frames = self.model.lag_s / _HOP_S  # fraction of a frame
        if not 0 <= self.lag_frames < 1:
            raise StageError(f"the analyser's smoothing lag ({self.model.lag_s * 1000:.1f} "
                             "ms) must be under one 10 ms frame to run live")  # fmt: skip
        self._drive = get(method_name).prepared(avatar, params, base_dir=self.base_dir)
        whole = self._drive(DriveInput(track=_probe_track(64), base_dir=self.base_dir))
        # a channel the avatar lacks is left out when a random mix of every viseme leaves it
        # at 0 (as the offline render does: an ARKit export without tongueOut plays Z)
        missing = whole.moved_but_missing(avatar.targets)
        if missing:
            raise StageError(f"avatar {avatar.name!r} lacks targets the method moves: "
                             f"{', '.join(missing[:8])}")  # fmt: skip
        self.names: tuple[str, ...] = tuple(n for n in whole.names if n in avatar.targets)
        self.restart(start_warp=start_warp)

    def restart(self, *, start_warp: float = 1.0) -> None:
        """Begin a new stream (a new turn): frame 0 at its first sample; with ``warp="auto"``
        the analysis starts at ``start_warp`` (where the talker's last turn settled)."""
        if self.warp == "auto":  # the talker's vocal-tract length, judged as the audio comes
            self.stream: StreamingAnalyzer | WarpAdaptingAnalyzer = WarpAdaptingAnalyzer(
                sample_rate=self.sample_rate, model=self.model, warp=start_warp)  # fmt: skip
        else:
            self.stream = StreamingAnalyzer(sample_rate=self.sample_rate, model=self.model,
                                            warp=float(self.warp))  # fmt: skip
        self._last: np.ndarray | None = None  # the previous analysis frame's weights
        self._next = 0  # the next live frame's index
        self.samples_in = 0

    @property
    def latency_s(self) -> float:
        """Audio a frame waits for beyond its own time: the analysis window's half and the
        next analysis frame (the lag compensation), at most one chunk more."""
        return self.stream.latency_s - self.model.lag_s + 2 * _HOP_S

    def feed(self, chunk: np.ndarray) -> LiveFrames:
        """The frames the chunk (n,) float samples in [-1, 1] completes."""
        chunk = np.asarray(chunk, dtype=np.float64).ravel()
        self.samples_in += chunk.size
        return self._frames(self.stream.feed(chunk), final=False)

    def flush(self) -> LiveFrames:
        """The remaining frames up to the end of the audio (the talker stopped)."""
        return self._frames(self.stream.flush(), final=True)

    def _frames(self, analysed: VisemeTrack, *, final: bool) -> LiveFrames:
        w = analysed.weights
        if self._last is not None:
            w = np.vstack([self._last[None, :], w])
        if len(w) == 0:
            return LiveFrames(self._next, np.zeros((0, len(self.names))))
        f = self.lag_frames
        # compensated frame k = the analysis track at k + lag (linear between k and k + 1);
        # the last frame holds its value when the audio ends (as np.interp does offline)
        ready = w[:-1] + f * (w[1:] - w[:-1]) if len(w) > 1 else np.zeros((0, w.shape[1]))
        if final:
            ready = np.vstack([ready, w[-1:]])
            self._last = None
        else:
            self._last = w[-1]
        if not len(ready):
            return LiveFrames(self._next, np.zeros((0, len(self.names))))
        times = (self._next + np.arange(len(ready))) * _HOP_S
        track = VisemeTrack(times=times, weights=ready, warp=analysed.warp)
        out = self._drive(DriveInput(track=track, base_dir=self.base_dir))
        frames = LiveFrames(self._next, np.clip(_columns(out, self.names), 0.0, 1.0))
        self._next += len(ready)
        return frames
