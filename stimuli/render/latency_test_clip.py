"""A latency test clip: a white patch and a tone burst that start together, for measuring a
lab set-up's audio-video offset with a photodiode and a microphone.

A browser or PsychoPy can report when it asked for a frame or a sound, not when the screen lit
or the loudspeaker moved. The clip is played through the study's own player (``facelab
latency-test play``); a photodiode taped over the patch and a microphone at the participant's
head are recorded as two channels of one recording (a sound card's line input is enough:
both share its clock), and :mod:`facelab.analysis.latency_recording` measures, event by event,
how much later the sound arrived than the light.

The clip: ``events`` times, every ``period_s`` from ``first_s``, the patch (a square in the
lower-left corner, ``patch`` of the picture's height) turns from black to white for
``flash_frames`` frames, and a ``tone_hz`` burst of the same length (1 ms raised-cosine ramps)
starts at the first white frame's time. Between events the patch is black, outlined in dark
grey so that the sensor can be placed; the rest of the picture is a dim, still
checkerboard. Frame k is shown from
k / fps (:mod:`facelab.stimuli.render.clip`'s contract), so in the file light and sound start
at the same instant to the sample.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from facelab.errors import StageError
from facelab.stimuli.render.clip import ClipInfo, encode
from facelab.stimuli.speech.audio import Speech

__all__ = ["LatencyTestClip", "event_frames", "latency_test_audio", "latency_test_frames",
           "write_latency_test_clip"]  # fmt: skip

RAMP_S = 0.001  # the tone's raised-cosine on- and off-ramps (a sharp, measurable onset)


@dataclass(frozen=True)
class LatencyTestClip:
    """The schedule of a latency test clip (written beside it as JSON).

    ``onsets_s``: each event's start in the clip (s), light and sound together;
    ``patch_px``: the patch's (left, top, width, height) in the picture's pixels."""

    fps: int
    width: int
    height: int
    events: int
    period_s: float
    first_s: float
    flash_frames: int
    tone_hz: float
    sample_rate: int
    duration_s: float
    onsets_s: tuple[float, ...]
    patch_px: tuple[int, int, int, int]

    @classmethod
    def plan(
        cls,
        *,
        fps: int = 60,
        width: int = 1280,
        height: int = 720,
        events: int = 20,
        period_s: float = 1.0,
        first_s: float = 1.0,
        flash_frames: int = 3,
        tone_hz: float = 1000.0,
        sample_rate: int = 48000,
        patch: float = 0.2,
    ) -> LatencyTestClip:
        """The schedule for these settings; a StageError names a setting that cannot work."""
        if fps < 10:
            raise StageError(f"--fps {fps}: a latency test needs at least 10 frames per second")
        if events < 3:
            raise StageError(f"--events {events}: at least 3 events are needed for a spread")
        flash_s = flash_frames / fps
        if flash_frames < 1 or flash_s < 2 * RAMP_S + 0.01:
            raise StageError(
                f"--flash-frames {flash_frames}: a flash of {1000 * flash_s:.0f} ms is too short "
                f"at {fps} frames/s (at least {1000 * (2 * RAMP_S + 0.01):.0f} ms)"
            )
        if period_s < 4 * flash_s or period_s < 0.25:
            raise StageError(
                f"--period-ms {1000 * period_s:.0f}: events must be at least 250 ms and four "
                f"flashes ({4000 * flash_s:.0f} ms) apart, so that each light finds its sound"
            )
        if not 100 <= tone_hz <= sample_rate / 4:
            raise StageError(f"--tone-hz {tone_hz:g}: expected 100 to {sample_rate / 4:g} Hz")
        if not 0.05 <= patch <= 0.5:
            raise StageError(f"patch {patch:g}: expected 0.05 to 0.5 of the picture's height")
        # every onset on a frame boundary, so the first white frame starts with the sound
        first_frame = max(1, round(first_s * fps))
        step = max(1, round(period_s * fps))
        starts = [first_frame + i * step for i in range(events)]
        n_frames = starts[-1] + step
        side = max(4, round(patch * height))
        margin = max(2, round(0.04 * height))
        return cls(
            fps=fps, width=width, height=height, events=events, period_s=step / fps,
            first_s=first_frame / fps, flash_frames=flash_frames, tone_hz=float(tone_hz),
            sample_rate=sample_rate, duration_s=n_frames / fps,
            onsets_s=tuple(k / fps for k in starts),
            patch_px=(margin, height - margin - side, side, side),
        )  # fmt: skip

    @property
    def n_frames(self) -> int:
        return round(self.duration_s * self.fps)

    def to_json(self) -> str:
        return json.dumps({"kind": "facelab latency test", **asdict(self)}, indent=2)

    @classmethod
    def read(cls, path: Path) -> LatencyTestClip:
        """The schedule written beside a clip; a StageError says what is wrong with it."""
        try:
            data = json.loads(Path(path).read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise StageError(f"{path}: schedule file not found") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            raise StageError(
                f"{path}: not a latency test schedule (expected the JSON that facelab "
                "latency-test clip writes beside its clip)"
            ) from None
        if not isinstance(data, dict) or data.pop("kind", None) != "facelab latency test":
            raise StageError(f"{path}: not a latency test schedule (no kind: facelab latency "
                             "test)")  # fmt: skip
        try:
            data["onsets_s"] = tuple(float(t) for t in data["onsets_s"])
            data["patch_px"] = tuple(int(v) for v in data["patch_px"])
            return cls(**data)
        except (KeyError, TypeError, ValueError):
            raise StageError(
                f"{path}: the schedule's fields are missing or of the wrong type; write it "
                "again with facelab latency-test clip"
            ) from None


def event_frames(clip: LatencyTestClip) -> np.ndarray:
    """(n_frames,) bool: the frames on which the patch is white."""
    white = np.zeros(clip.n_frames, dtype=bool)
    for t in clip.onsets_s:
        k = round(t * clip.fps)
        white[k : k + clip.flash_frames] = True
    return white


def latency_test_frames(clip: LatencyTestClip):
    """The clip's RGB frames (height, width, 3) uint8, one per frame, as a generator."""
    left, top, side, _ = clip.patch_px
    # a dim, still checkerboard: a player that shows no frames is seen (the lab window's
    # uniform-picture check), and nothing but the patch changes
    cell = max(2, clip.height // 9)
    rows, cols = np.indices((clip.height, clip.width)) // cell
    board = np.where((rows + cols) % 2 == 0, 20, 44).astype(np.uint8)
    dark = np.repeat(board[:, :, None], 3, axis=2)
    edge = max(2, side // 20)
    dark[top - edge : top + side + edge, left - edge : left + side + edge] = 90  # the outline
    dark[top : top + side, left : left + side] = 0
    lit = dark.copy()
    lit[top : top + side, left : left + side] = 255
    for white in event_frames(clip):
        yield lit if white else dark


def latency_test_audio(clip: LatencyTestClip) -> np.ndarray:
    """(n,) float32 at ``clip.sample_rate``: a -6 dBFS tone burst at each onset, silence
    between; the bursts last as long as the flashes."""
    sr = clip.sample_rate
    out = np.zeros(round(clip.duration_s * sr), dtype=np.float32)
    n = round(clip.flash_frames / clip.fps * sr)
    t = np.arange(n) / sr
    burst = 0.5 * np.sin(2 * np.pi * clip.tone_hz * t)
    ramp = round(RAMP_S * sr)
    shape = np.ones(n)
    shape[:ramp] = 0.5 - 0.5 * np.cos(np.pi * np.arange(ramp) / ramp)
    shape[n - ramp :] = shape[:ramp][::-1]
    burst = (burst * shape).astype(np.float32)
    for onset in clip.onsets_s:
        k = round(onset * sr)
        out[k : k + n] = burst[: len(out) - k]
    return out


def write_latency_test_clip(clip: LatencyTestClip, *, out: Path) -> ClipInfo:
    """The clip as ``out`` (mp4, H.264 + AAC as the study's clips are) and its schedule as
    ``out`` with the suffix ``.json``."""
    info = encode(
        latency_test_frames(clip), audio=Speech(latency_test_audio(clip), clip.sample_rate),
        out=out, fps=clip.fps, width=clip.width, height=clip.height, n_frames=clip.n_frames,
    )  # fmt: skip
    out.with_suffix(".json").write_text(clip.to_json() + "\n", encoding="utf-8")
    return info
