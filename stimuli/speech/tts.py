"""Text-to-speech: Japanese text -> waveform + phoneme timeline with OpenJTalk.

Runs Debian's ``open_jtalk`` with the ``mei_normal`` HTS voice shipped inside the
``pyopenjtalk-plus`` wheel and the Debian naist-jdic dictionary, offline. One run writes both
the waveform and the label trace, so the phoneme times are exactly those the audio was
generated from (5 ms resolution for mei: 240-sample frames at 48 kHz).

What ``open_jtalk`` writes for a text and its settings is kept on disk (:func:`cache_dir`:
``$FACELAB_CACHE_DIR``, else ``$XDG_CACHE_HOME/facelab``, else ``~/.cache/facelab``;
``FACELAB_CACHE_DIR=off`` keeps nothing), so ``facelab validate`` and ``render`` do not run it
again for texts they read before. The key holds the program and the libraries it loads (HTS
Engine), the dictionary and the voice files (path, size, modification time): a new OpenJTalk,
HTS Engine or voice makes new entries. The files
kept are the program's own output, read as a fresh run's are.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import importlib.util
import json
import os
import shutil
import subprocess
import tempfile
import threading
import time
import zlib
from pathlib import Path

import numpy as np

from facelab.bounded_memo import BoundedMemo
from facelab.errors import SpeechError
from facelab.stimuli.speech.audio import Phone, Speech, _read_wav_pcm16, resample
from facelab.stimuli.speech.prosody import accent_phrases, label_rows, words_with_times

__all__ = [
    "DICTIONARY_DIR",
    "TTS_SAMPLE_RATE",
    "cache_dir",
    "parse_trace",
    "synthesize",
    "voice_file",
]

DICTIONARY_DIR = Path("/var/lib/mecab/dic/open-jtalk/naist-jdic")
TTS_SAMPLE_RATE = 48_000  # mei_normal's native rate

# OpenJTalk is deterministic, and one process often asks for the same utterance more than once
# (a render makes a clip's speech, its stimulus checks make it again to compare the clip with):
# the latest results are kept, up to 64 MB of samples, and handed out as copies
_memo: BoundedMemo[Speech] = BoundedMemo(
    max_bytes=64 * 2**20, size_of=lambda speech: speech.samples.nbytes
)


#: bytes the disk cache may hold (an entry: the WAV, ~100 kB a second, and the compressed
#: trace); the oldest entries go first
CACHE_BYTES = 256 * 2**20
PRUNE_EVERY = 64  # writes between two looks at the folder's size
_CACHE_FORMAT = "open_jtalk-output-1"
_writes = 0


def cache_dir() -> Path | None:
    """Where OpenJTalk's outputs are kept (see the module), or None (``off``)."""
    chosen = os.environ.get("FACELAB_CACHE_DIR")
    if chosen is not None:
        return None if chosen.strip().lower() in ("", "off", "0", "none") else (
            Path(chosen) / "tts")
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "facelab" / "tts"


def _stamp(path: Path) -> list:
    st = path.stat()
    return [str(path), st.st_size, st.st_mtime_ns]


@functools.cache
def _program_stamps(exe: str) -> tuple:
    """The program and the shared libraries it loads (``ldd``: HTS Engine, which makes the
    waveform, is a Debian package of its own), each as path, size and modification time."""
    files = [Path(exe).resolve()]
    try:
        listed = subprocess.run(["ldd", exe], capture_output=True, text=True, timeout=30,
                                check=False).stdout  # fmt: skip
    except (OSError, subprocess.TimeoutExpired):
        listed = ""
    for line in listed.splitlines():
        where = line.split("=>")[-1].strip().split(" (")[0].strip()
        if where.startswith("/") and Path(where).is_file():
            files.append(Path(where).resolve())
    return tuple(tuple(_stamp(f)) for f in sorted(set(files)))


def _cache_key(exe: str, args: list[str], text: str) -> str:
    """What one run's output depends on: the program and its libraries, the dictionary and
    voice files, the options and the text."""
    dictionary = sorted(_stamp(f) for f in DICTIONARY_DIR.iterdir() if f.is_file())
    material = [_CACHE_FORMAT, _program_stamps(exe), dictionary, _stamp(voice_file()), args,
                text]  # fmt: skip
    return hashlib.sha256(json.dumps(material, ensure_ascii=False).encode()).hexdigest()


def _cached_output(key: str) -> tuple[np.ndarray, int, str] | None:
    """(samples, sample rate, trace) of the output kept for ``key``, or None (none kept, or
    unreadable: OpenJTalk runs again and replaces it)."""
    folder = cache_dir()
    if folder is None:
        return None
    try:
        entry = folder / f"{key}.bin"
        data = entry.read_bytes()
        os.utime(entry)  # used: the last to be dropped
        n = int.from_bytes(data[:8], "little")
        trace = zlib.decompress(data[8 : 8 + n]).decode("utf-8")
        samples, rate = _read_wav_pcm16(entry, data=data[8 + n :])
    except (OSError, UnicodeDecodeError, ValueError, zlib.error, SpeechError):
        return None
    return (samples, rate, trace) if len(samples) else None


def _keep_output(key: str, wav: bytes, trace: str) -> None:
    """Keep one run's output (written whole or not at all; a cache that cannot be written
    is no error), then drop the oldest entries beyond :data:`CACHE_BYTES`."""
    folder = cache_dir()
    if folder is None:
        return
    global _writes
    part = folder / f".{key}.{os.getpid()}.{threading.get_ident()}.part"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        encoded = zlib.compress(trace.encode("utf-8"), 6)
        part.write_bytes(len(encoded).to_bytes(8, "little") + encoded + wav)
        os.replace(part, folder / f"{key}.bin")
        _writes += 1
        if _writes % PRUNE_EVERY == 1:  # the folder is listed now and then, not every time
            _prune(folder)
    except OSError:
        return
    finally:
        with contextlib.suppress(OSError):  # left by a write that failed (a full disk)
            part.unlink(missing_ok=True)


def _prune(folder: Path) -> None:
    """Drop the least recently used entries beyond :data:`CACHE_BYTES` (and parts a killed
    process left, an hour old)."""
    entries = []
    for e in os.scandir(folder):
        st = e.stat()
        if e.name.endswith(".part") and time.time() - st.st_mtime > 3600:
            Path(e.path).unlink(missing_ok=True)
        elif e.name.endswith(".bin"):
            entries.append((st, e.path))
    total = sum(st.st_size for st, _ in entries)
    for st, path in sorted(entries, key=lambda e: e[0].st_mtime_ns):
        if total <= CACHE_BYTES:
            break
        Path(path).unlink(missing_ok=True)
        total -= st.st_size


def voice_file() -> Path:
    """The mei_normal HTS voice inside the installed pyopenjtalk-plus package."""
    spec = importlib.util.find_spec("pyopenjtalk")  # not imported: it prints warnings
    if spec is None or spec.origin is None:
        raise SpeechError("pyopenjtalk-plus is not installed (pip install 'facelab[stimuli]')")
    path = Path(spec.origin).parent / "htsvoice" / "mei_normal.htsvoice"
    if not path.is_file():
        raise SpeechError(f"the mei_normal voice was not found at {path}")
    return path


def _open_jtalk() -> str:
    exe = shutil.which("open_jtalk")
    if exe is None or not DICTIONARY_DIR.is_dir():
        raise SpeechError(
            "OpenJTalk is not installed: apt-get install open-jtalk open-jtalk-mecab-naist-jdic "
            "(scripts/setup.sh does this)"
        )
    return exe


def parse_trace(text: str) -> tuple[Phone, ...]:
    """Phones from the ``[Output label]`` section of an ``open_jtalk -ot`` trace.

    Label times are in 100 ns units; the phoneme sits between ``-`` and ``+``.
    """
    return tuple(Phone(ph, t0, t1) for t0, t1, ph, _ in label_rows(text))


def synthesize(
    text: str,
    *,
    speed: float = 1.0,
    pitch_halftones: float = 0.0,
    alpha: float | None = None,
    sample_rate: int = TTS_SAMPLE_RATE,
) -> Speech:
    """Japanese text -> :class:`Speech` with the phoneme timeline, via ``open_jtalk``.

    Parameters
    ----------
    speed : speaking-rate factor (``-r``), 0.5..2.
    pitch_halftones : pitch shift in half tones (``-fm``).
    alpha : all-pass constant (``-a``), a vocal-tract-length-like timbre change; None keeps
        the voice's own (0.55 for mei at 48 kHz).
    sample_rate : output rate; the voice runs at 48 kHz and is resampled if different
        (phone times are unaffected).
    """
    clean = text.strip()
    if not clean:
        raise SpeechError("empty text: nothing to synthesise")
    if not 0.5 <= speed <= 2.0:
        raise SpeechError(f"speed {speed} is outside 0.5..2")
    sample_rate = int(sample_rate)
    key = (clean, float(speed), float(pitch_halftones), alpha, sample_rate)
    kept = _memo.get(key)
    if kept is None:
        kept = _run_open_jtalk(clean, speed=speed, pitch_halftones=pitch_halftones,
                               alpha=alpha, sample_rate=sample_rate)  # fmt: skip
        _memo.put(key, kept)
    return dataclasses.replace(kept, samples=kept.samples.copy())


def _run_open_jtalk(
    clean: str, *, speed: float, pitch_halftones: float, alpha: float | None, sample_rate: int
) -> Speech:
    """One run of ``open_jtalk`` (see :func:`synthesize`)."""
    exe = _open_jtalk()
    options = ["-r", f"{speed:g}", "-fm", f"{pitch_halftones:g}"]
    if alpha is not None:
        options += ["-a", f"{alpha:g}"]
    key = _cache_key(exe, options, clean) if cache_dir() is not None else None
    kept = _cached_output(key) if key is not None else None
    if kept is not None:
        samples, rate, trace = kept
    else:
        with tempfile.TemporaryDirectory(prefix="facelab-tts-") as tmp:
            tmpdir = Path(tmp)
            wav = tmpdir / "out.wav"
            (tmpdir / "in.txt").write_text(clean + "\n", encoding="utf-8")
            cmd = [exe, "-x", str(DICTIONARY_DIR), "-m", str(voice_file()), *options,
                   "-ow", str(wav), "-ot", str(tmpdir / "out.trace"),
                   str(tmpdir / "in.txt")]  # fmt: skip
            proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
            if proc.returncode != 0 or not wav.exists() or wav.stat().st_size <= 44:
                why = ("it finds nothing it can pronounce in it" if "phoneme" in proc.stderr
                       else f"it made no audio (exit status {proc.returncode})")  # fmt: skip
                raise SpeechError(f"OpenJTalk could not read the text {clean[:30]!r}: {why}")
            trace = (tmpdir / "out.trace").read_text(encoding="utf-8", errors="replace")
            wav_bytes = wav.read_bytes()
            samples, rate = _read_wav_pcm16(wav, data=wav_bytes)
            if key is not None:
                _keep_output(key, wav_bytes, trace)
    phones = parse_trace(trace)
    speaking = [p for p in phones if p.phoneme not in ("sil", "pau")]
    if not speaking:
        raise SpeechError(f"OpenJTalk found nothing to pronounce in {clean[:30]!r}")
    if rate != sample_rate:
        samples = resample(samples, rate_in=rate, rate_out=sample_rate)
    return Speech(
        samples=samples,
        sample_rate=sample_rate,
        phones=phones,
        source=f"tts:{clean}",
        words=tuple(words_with_times(trace)),
        accents=tuple(accent_phrases(trace)),
    )


