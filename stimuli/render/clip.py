"""Clips: blendshape track + audio -> mp4 (H.264 + AAC), picture and sound aligned.

Timing contract: the clip is ``pad_s`` of neutral face and silence, the speech, and ``pad_s``
again. Frame k is shown from t = k / fps and shows the face at speech time t - pad_s (weights
linearly interpolated); frames outside the speech - and always the first and last - are the
neutral face. The clip has round(duration * fps) frames; the audio is the speech padded with
exact silence, so picture and sound start together at t = 0 and end within one frame.
"""

from __future__ import annotations

import contextlib
import queue
import shutil
import subprocess
import tempfile
import threading
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import numpy as np

from facelab.errors import StageError
from facelab.hashing import sha256_file
from facelab.stimuli.avatar.mesh import Avatar
from facelab.stimuli.avatar.rig import HeadPose
from facelab.stimuli.methods.types import BlendshapeTrack
from facelab.stimuli.speech.audio import Speech, write_wav

__all__ = [
    "ClipInfo",
    "decode_audios",
    "encode",
    "ffmpeg_each",
    "frame_weights",
    "padded_audio",
    "remux",
    "remux_many",
    "sha256_file",
    "shifted_audio",
    "weights_at",
]


@dataclass(frozen=True)
class ClipInfo:
    path: Path
    duration_s: float
    fps: int
    width: int
    height: int
    frames: int
    sha256: str


def padded_audio(speech: Speech, *, pad_s: float) -> Speech:
    """The speech with ``pad_s`` of digital silence before and after."""
    pad = np.zeros(round(pad_s * speech.sample_rate), dtype=np.float32)
    return Speech(
        np.concatenate([pad, speech.samples, pad]), speech.sample_rate, speech.phones, speech.source
    )


def shifted_audio(audio: Speech, *, offset_ms: float) -> Speech:
    """``audio`` moved by ``offset_ms`` within its own length: negative earlier (the voice
    before the face), positive later; what leaves one end is silence entering the other
    (the caller keeps the shift within the padding: :func:`padded_audio`)."""
    n = round(abs(offset_ms) * audio.sample_rate / 1000.0)
    if n == 0:
        return audio
    x = audio.samples
    silence = np.zeros(min(n, len(x)), dtype=x.dtype)
    if offset_ms < 0:
        moved = np.concatenate([x[n:], silence])
    else:
        moved = np.concatenate([silence, x[: len(x) - n]])
    source = f"{audio.source} shifted {offset_ms:+g} ms"
    return Speech(moved, audio.sample_rate, audio.phones, source)


def frame_weights(
    track: BlendshapeTrack, avatar: Avatar, *, fps: int, n_frames: int, pad_s: float
) -> np.ndarray:
    """(n_frames, K) weights in ``avatar.target_names`` order for frames k / fps. A channel
    the avatar lacks is left out when the track holds it at 0 throughout (an ARKit export
    without ``tongueOut`` plays a Z matrix whose ``tongueOut`` row is all zero); one the
    track moves is refused, naming it."""
    index = {n: i for i, n in enumerate(avatar.target_names)}
    missing = track.moved_but_missing(index)
    if missing:
        raise StageError(
            f"avatar {avatar.name!r} lacks targets the track moves: {', '.join(missing[:8])}"
            " (add these shapes to the avatar, or drive it with a method or Z matrix that "
            "leaves them at 0)"
        )
    t = np.arange(n_frames) / fps - pad_s
    inside = (t >= track.times[0]) & (t <= track.times[-1])
    out = np.zeros((n_frames, len(index)), np.float32)
    for j, name in enumerate(track.names):
        if name not in index:  # held at 0 throughout (checked above)
            continue
        col = np.interp(t, track.times, track.weights[:, j], left=0.0, right=0.0)
        out[:, index[name]] = np.where(inside, col, 0.0)
    out[0] = 0.0
    out[-1] = 0.0
    return out


def frame_poses(
    track: BlendshapeTrack, *, fps: int, n_frames: int, pad_s: float
) -> list[HeadPose] | None:
    """The track's head and eye angles at frames k / fps (held at the ends; None without
    poses)."""
    if track.poses is None:
        return None
    t = np.arange(n_frames) / fps - pad_s
    cols = [np.interp(t, track.times, track.poses[:, j]) for j in range(5)]
    return [HeadPose(*(float(c[k]) for c in cols)) for k in range(n_frames)]


def weights_at(track: BlendshapeTrack, avatar: Avatar, *, t: float) -> np.ndarray:
    """(K,) weights in ``avatar.target_names`` order at speech time ``t`` (interpolated; a
    channel the avatar lacks is passed over - :func:`frame_weights` refuses one the track
    moves)."""
    index = {n: i for i, n in enumerate(avatar.target_names)}
    out = np.zeros(len(index), np.float32)
    for j, name in enumerate(track.names):
        if name in index:
            out[index[name]] = np.interp(t, track.times, track.weights[:, j])
    return out


#: x264's thread count, fixed: its output depends on it, and left to itself it follows the
#: CPUs this process may use - so a worker pinned to one core, or a machine with another
#: number of cores, would write different bytes for the same clip. 3 is what x264 chose on
#: the 2-core machine the shipped hashes were made on.
X264_THREADS = 3

#: the sound of every clip: ffmpeg's own AAC encoder at 192 kbit/s with its "fast" coder. Its
#: default, "twoloop", took 4.5x the CPU for the same quality here (an 8.4-s OpenJTalk
#: sentence: 0.28 against 0.06 CPU-s beyond ffmpeg's start; decoded back, 36.7 against
#: 36.9 dB SNR).
AAC_ARGS = ("-c:a", "aac", "-aac_coder", "fast", "-b:a", "192k")


def _ffmpeg() -> str:
    exe = shutil.which("ffmpeg")
    if exe is None:
        raise StageError(
            "ffmpeg is not installed: apt-get install ffmpeg (scripts/setup.sh does this)"
        )
    return exe


class _PipeWriter:
    """Writes frames to ffmpeg's stdin from a second thread, so the next frame is rendered
    while this one is written (and ffmpeg encodes on the other core). At most ``depth``
    frames wait; the pipe write releases the GIL."""

    def __init__(self, pipe: IO[bytes], *, depth: int = 3):
        self._pipe = pipe
        self._queue: queue.Queue[np.ndarray | None] = queue.Queue(maxsize=depth)
        self._broken = threading.Event()
        self._error: BaseException | None = None  # anything but a closed pipe
        self.written = 0
        self._thread = threading.Thread(target=self._run, name="facelab-ffmpeg-writer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while (frame := self._queue.get()) is not None:
            if self._broken.is_set():
                continue  # drain what the renderer already queued
            try:
                self._pipe.write(memoryview(frame).cast("B"))
                self.written += 1
            except (BrokenPipeError, ValueError, OSError):
                self._broken.set()  # ffmpeg stopped reading
            except Exception as exc:  # keep draining, or put() would wait for ever
                self._error = exc
                self._broken.set()

    def put(self, frame: np.ndarray) -> bool:
        """Queue a frame (waits while ``depth`` frames are queued); False once the pipe broke."""
        if self._broken.is_set():
            return False
        self._queue.put(frame)
        return True

    def close(self) -> int:
        """Write what is queued, close the pipe; returns the frames written."""
        self._queue.put(None)
        self._thread.join()
        with contextlib.suppress(BrokenPipeError, OSError):
            self._pipe.close()
        if self._error is not None:
            raise self._error
        return self.written


def encode(
    frames: Iterable[np.ndarray],
    *,
    audio: Speech,
    out: Path,
    fps: int,
    width: int,
    height: int,
    n_frames: int,
    crf: int = 18,
    preset: str = "veryfast",
    on_frame: Callable[[], None] | None = None,
) -> ClipInfo:
    """Pipe RGB frames and the audio into ffmpeg (libx264 yuv420p + AAC); atomic write."""
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="facelab-clip-", dir=out.parent) as tmp:
        wav = Path(tmp) / "audio.wav"
        write_wav(wav, audio)
        part = Path(tmp) / out.name
        duration = n_frames / fps
        cmd = [
            _ffmpeg(),
            "-hide_banner",
            "-loglevel",
            "error",
            "-y",
            "-f",
            "rawvideo",
            "-pix_fmt",
            "rgb24",
            "-s",
            f"{width}x{height}",
            "-framerate",
            str(fps),
            "-i",
            "-",
            "-i",
            str(wav),
            "-map",
            "0:v",
            "-map",
            "1:a",
            "-c:v",
            "libx264",
            "-preset",
            preset,
            "-crf",
            str(crf),
            "-pix_fmt",
            "yuv420p",
            "-r",
            str(fps),
            "-fps_mode",
            "cfr",
            *AAC_ARGS,
            "-ar",
            str(audio.sample_rate),
            "-t",
            f"{duration:.6f}",
            "-threads",
            str(X264_THREADS),
            "-movflags",
            "+faststart",
            str(part),
        ]
        proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stderr=subprocess.PIPE)
        assert proc.stdin is not None
        writer = _PipeWriter(proc.stdin)
        try:
            for frame in frames:
                if frame.shape != (height, width, 3):
                    raise StageError(
                        f"frame of shape {frame.shape}, expected ({height}, {width}, 3)"
                    )
                # a copy: the frame waits in the queue while the caller may reuse its buffer
                if not writer.put(np.array(frame, dtype=np.uint8, order="C", copy=True)):
                    break  # ffmpeg stopped reading: its exit code and message say why
                if on_frame:
                    on_frame()
        finally:
            written = writer.close()
            err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
            code = proc.wait()
        if code != 0 or written != n_frames:
            raise StageError(
                f"ffmpeg failed for {out.name} (exit {code}, {written}/{n_frames} frames): "
                f"{err.strip()[-400:]}"
            )
        part.replace(out)
    return ClipInfo(out, duration, fps, width, height, n_frames, sha256_file(out))


def remux(*, video: Path, audio: Speech, out: Path, fps: int, n_frames: int) -> ClipInfo:
    """A clip with ``video``'s picture - its stream copied, not decoded or encoded again -
    and ``audio`` encoded as :func:`encode` does (AAC); atomic write. Clips that differ only
    in their sound (an audio offset) share one rendering this way."""
    return remux_many(video=video, outputs=[(audio, out)], fps=fps, n_frames=n_frames)[0]


#: outputs one ffmpeg process writes in :func:`remux_many` (its start-up, ~70 ms, is most of
#: a short clip's re-mux; the open files stay few)
REMUX_BATCH = 16


def remux_many(
    *, video: Path, outputs: list[tuple[Speech, Path]], fps: int, n_frames: int
) -> list[ClipInfo]:
    """:func:`remux` for several sounds on one picture: each output ``(audio, out)`` gets
    ``video``'s stream copied and its own ``audio`` (AAC), written by one ffmpeg process per
    :data:`REMUX_BATCH` outputs - the bytes :func:`remux` writes for each; atomic writes."""
    if not outputs:
        return []
    info = probe(video, count_frames=False)
    stream = next((s for s in info.get("streams", []) if s.get("codec_type") == "video"), None)
    if stream is None:
        raise StageError(f"{video.name}: no video stream to reuse")
    width, height = int(stream["width"]), int(stream["height"])
    duration = n_frames / fps
    done: list[ClipInfo] = []
    for start in range(0, len(outputs), REMUX_BATCH):
        batch = outputs[start : start + REMUX_BATCH]
        folder = batch[0][1].parent
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix="facelab-remux-", dir=folder) as tmp:
            cmd = [_ffmpeg(), "-hide_banner", "-loglevel", "error", "-y", "-i", str(video)]
            parts = []
            for k, (audio, _out) in enumerate(batch):
                wav = Path(tmp) / f"audio{k}.wav"
                write_wav(wav, audio)
                cmd += ["-i", str(wav)]
            for k, (audio, out) in enumerate(batch):
                part = Path(tmp) / f"{k}-{out.name}"
                parts.append(part)
                cmd += [
                    "-map", "0:v:0", "-map", f"{k + 1}:a", "-c:v", "copy", *AAC_ARGS,
                    "-ar", str(audio.sample_rate), "-t", f"{duration:.6f}",
                    "-movflags", "+faststart", str(part),
                ]  # fmt: skip
            ran = subprocess.run(cmd, capture_output=True, check=False)
            if ran.returncode != 0:
                why = ran.stderr.decode(errors="replace").strip()[-300:]
                raise StageError(f"ffmpeg could not put the new sound on {video.name}: {why}")
            for part, (_audio, out) in zip(parts, batch, strict=True):
                out.parent.mkdir(parents=True, exist_ok=True)
                part.replace(out)
                done.append(ClipInfo(out, duration, fps, width, height, n_frames,
                                     sha256_file(out)))  # fmt: skip
    return done


def probe(path: Path, *, count_frames: bool = True) -> dict:
    """Stream facts of a clip from ffprobe: codecs, frames (``count_frames``: counted by
    decoding, ``nb_read_frames``), durations, sample rate."""
    exe = shutil.which("ffprobe")
    if exe is None:
        raise StageError("ffprobe is not installed (Debian ffmpeg)")
    import json

    out = subprocess.run(
        [
            exe,
            "-v",
            "error",
            *(["-count_frames"] if count_frames else []),
            "-show_streams",
            "-show_format",
            "-of",
            "json",
            str(path),
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    if out.returncode != 0:
        raise StageError(f"{path}: ffprobe failed: {out.stderr.strip()}")
    return json.loads(out.stdout)


def _decode(path: Path, output_args: list[str], what: str) -> bytes:
    """Raw bytes ffmpeg writes to stdout for ``path`` with ``output_args``."""
    out = subprocess.run(
        [_ffmpeg(), "-v", "error", "-i", str(path), *output_args, "-"],
        capture_output=True,
        check=False,
    )
    if out.returncode != 0:
        raise StageError(
            f"{path}: cannot decode {what}: {out.stderr.decode(errors='replace')[-300:]}"
        )
    return out.stdout


def decode_audio(path: Path, *, sample_rate: int) -> np.ndarray:
    """The clip's audio as mono float32 at ``sample_rate``."""
    raw = _decode(path, ["-f", "f32le", "-ac", "1", "-ar", str(sample_rate)], "audio")
    return np.frombuffer(raw, dtype=np.float32)


def ffmpeg_each(
    paths: Sequence[Path], *, stream: str, output_args: list[str], batch: int = 24
) -> list[bytes | None]:
    """What ffmpeg writes for each clip's ``stream`` (``"a:0"``, ``"v:0"``) with
    ``output_args`` (a format and its options), one process per ``batch`` clips - its
    start-up is most of a short clip's work. None for a clip it cannot read: a batch that
    fails is run clip by clip, so one broken file spoils nothing else."""
    exe = _ffmpeg()
    out: list[bytes | None] = []
    for start in range(0, len(paths), batch):
        group = list(paths[start : start + batch])
        with tempfile.TemporaryDirectory(prefix="facelab-ffmpeg-") as tmp:
            files = [Path(tmp) / f"{k}.out" for k in range(len(group))]

            def run(members: list[int], *, group=group, files=files) -> bool:
                cmd = [exe, "-v", "error", "-nostdin", "-y"]
                for k in members:
                    cmd += ["-i", str(group[k])]
                for j, k in enumerate(members):
                    cmd += ["-map", f"{j}:{stream}", *output_args, str(files[k])]
                return subprocess.run(cmd, capture_output=True, check=False).returncode == 0

            everyone = list(range(len(group)))
            read = dict.fromkeys(everyone, True) if run(everyone) else {
                k: run([k]) for k in everyone}  # fmt: skip
            out += [files[k].read_bytes() if read[k] and files[k].is_file() else None
                    for k in everyone]  # fmt: skip
    return out


def decode_audios(paths: list[Path], *, sample_rate: int, batch: int = 24) -> list[np.ndarray]:
    """Each clip's audio as mono float32 at ``sample_rate``, as :func:`decode_audio` gives
    it, decoded in batches (:func:`ffmpeg_each`); a clip without decodable sound gives an
    empty array."""
    raw = ffmpeg_each(paths, stream="a:0", batch=batch,
                      output_args=["-f", "f32le", "-ac", "1", "-ar", str(sample_rate)])  # fmt: skip
    return [np.frombuffer(r or b"", dtype="<f4").copy() for r in raw]


def decode_frames(path: Path, *, width: int, height: int) -> np.ndarray:
    """All frames as (N, height, width, 3) uint8 (scaled by ffmpeg if needed)."""
    raw = _decode(path, ["-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{width}x{height}"], "video")
    return np.frombuffer(raw, dtype=np.uint8).reshape(-1, height, width, 3)


def av_offset_ms(path: Path, *, fps: int, max_lag_frames: int = 8) -> dict[str, float]:
    """Audio/picture offset measured from the clip file itself.

    Picture: darkness of the mouth region per frame (the mouth region is where frames vary
    most). Sound: RMS of the decoded audio in 40 ms windows centred on the frame times.
    The offset is the lag maximising their cross-correlation (parabolic interpolation);
    positive = the picture is late relative to the sound.
    """
    frames = decode_frames(path, width=320, height=180).astype(np.float32)
    luma = frames @ np.array([0.299, 0.587, 0.114], np.float32)
    var = luma.std(axis=0)
    roi = var >= np.percentile(var, 99.5)
    mouth = (255.0 - luma[:, roi]).mean(axis=1)
    rate = 16_000
    audio = decode_audio(path, sample_rate=rate)
    # RMS in a 40 ms window centred on each frame time k / fps (as the frames are)
    half = int(0.020 * rate)
    power = np.concatenate([[0.0], np.cumsum(audio.astype(np.float64) ** 2)])
    n = min(len(mouth), int(len(audio) / rate * fps))
    centres = (np.arange(n) * rate / fps).astype(int)
    lo, hi = np.clip(centres - half, 0, len(audio)), np.clip(centres + half, 0, len(audio))
    env = np.sqrt((power[hi] - power[lo]) / np.maximum(hi - lo, 1))
    a, b = mouth[:n] - mouth[:n].mean(), env - env.mean()
    lags = np.arange(-max_lag_frames, max_lag_frames + 1)
    corr = np.array(
        [np.dot(a[max(0, k) : n + min(0, k)], b[max(0, -k) : n - max(0, k)]) for k in lags]
    )
    i = int(np.argmax(corr))
    frac = 0.0
    if 0 < i < len(lags) - 1:
        den = corr[i - 1] - 2 * corr[i] + corr[i + 1]
        frac = 0.5 * (corr[i - 1] - corr[i + 1]) / den if den else 0.0
    peak = float(corr[i] / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-12))
    return {
        "offset_ms": float((lags[i] + frac) * 1000 / fps),
        "frame_ms": 1000 / fps,
        "correlation": peak,
    }
