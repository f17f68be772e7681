"""Text-to-speech: Japanese text -> waveform + phoneme timeline with OpenJTalk.

Runs Debian's ``open_jtalk`` with the ``mei_normal`` HTS voice shipped inside the
``pyopenjtalk-plus`` wheel and the Debian naist-jdic dictionary, offline. One run writes both
the waveform and the label trace, so the phoneme times are exactly those the audio was
generated from (5 ms resolution for mei: 240-sample frames at 48 kHz).
"""

from __future__ import annotations

import dataclasses
import importlib.util
import shutil
import subprocess
import tempfile
import threading
from collections import OrderedDict
from pathlib import Path

from facelab.errors import SpeechError
from facelab.stimuli.speech.audio import Phone, Speech, _read_wav_pcm16, resample
from facelab.stimuli.speech.prosody import accent_phrases, label_rows, words_with_times

__all__ = ["DICTIONARY_DIR", "TTS_SAMPLE_RATE", "parse_trace", "synthesize", "voice_file"]

DICTIONARY_DIR = Path("/var/lib/mecab/dic/open-jtalk/naist-jdic")
TTS_SAMPLE_RATE = 48_000  # mei_normal's native rate

# OpenJTalk is deterministic, and one process often asks for the same utterance more than once
# (a render makes a clip's speech, its stimulus checks make it again to compare the clip with):
# the latest results are kept, up to this many bytes of samples, and handed out as copies
_MEMO_BYTES = 64 * 2**20
_memo: OrderedDict[tuple, Speech] = OrderedDict()
_memo_lock = threading.Lock()


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
    with _memo_lock:
        kept = _memo.get(key)
        if kept is not None:
            _memo.move_to_end(key)
    if kept is None:
        kept = _run_open_jtalk(clean, speed=speed, pitch_halftones=pitch_halftones,
                               alpha=alpha, sample_rate=sample_rate)  # fmt: skip
        with _memo_lock:
            _memo[key] = kept
            total = sum(v.samples.nbytes for v in _memo.values())
            while total > _MEMO_BYTES and len(_memo) > 1:
                total -= _memo.popitem(last=False)[1].samples.nbytes
    return dataclasses.replace(kept, samples=kept.samples.copy())


def _run_open_jtalk(
    clean: str, *, speed: float, pitch_halftones: float, alpha: float | None, sample_rate: int
) -> Speech:
    """One run of ``open_jtalk`` (see :func:`synthesize`)."""
    exe = _open_jtalk()
    with tempfile.TemporaryDirectory(prefix="facelab-tts-") as tmp:
        tmpdir = Path(tmp)
        (tmpdir / "in.txt").write_text(clean + "\n", encoding="utf-8")
        cmd = [
            exe,
            "-x",
            str(DICTIONARY_DIR),
            "-m",
            str(voice_file()),
            "-r",
            f"{speed:g}",
            "-fm",
            f"{pitch_halftones:g}",
            "-ow",
            str(tmpdir / "out.wav"),
            "-ot",
            str(tmpdir / "out.trace"),
        ]
        if alpha is not None:
            cmd += ["-a", f"{alpha:g}"]
        cmd.append(str(tmpdir / "in.txt"))
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        wav = tmpdir / "out.wav"
        if proc.returncode != 0 or not wav.exists() or wav.stat().st_size <= 44:
            why = ("it finds nothing it can pronounce in it" if "phoneme" in proc.stderr
                   else f"it made no audio (exit status {proc.returncode})")  # fmt: skip
            raise SpeechError(f"OpenJTalk could not read the text {clean[:30]!r}: {why}")
        trace = (tmpdir / "out.trace").read_text(encoding="utf-8", errors="replace")
        phones = parse_trace(trace)
        samples, rate = _read_wav_pcm16(wav)
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


