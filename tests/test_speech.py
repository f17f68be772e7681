"""Speech input: OpenJTalk TTS with timing, recorded audio, and every bad-audio case."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from facelab.stimuli.speech.audio import SpeechError, load_audio
from facelab.stimuli.speech.tts import parse_trace, synthesize


def test_tts_gives_audio_and_exact_phoneme_timeline() -> None:
    speech = synthesize("あいうえお", speed=1.0)
    assert speech.sample_rate == 48_000 and speech.samples.dtype == np.float32
    names = [p.phoneme for p in speech.phones]
    assert names == ["sil", "a", "i", "u", "e", "o", "sil"]
    assert speech.phones[-1].end == pytest.approx(speech.duration_s, abs=0.006)
    starts = [p.start for p in speech.phones]
    assert starts == sorted(starts) and all(p.end > p.start for p in speech.phones)
    # the audio is quiet in the leading silence and loud in the vowels
    a = speech.phones[1]
    sil = speech.samples[: int(speech.phones[0].end * 48_000)]
    vowel = speech.samples[int(a.start * 48_000) : int(a.end * 48_000)]
    assert np.sqrt(np.mean(vowel**2)) > 20 * np.sqrt(np.mean(sil**2) + 1e-12)


def test_openjtalks_output_is_kept_on_disk_and_read_as_a_fresh_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A text synthesised once is read back from the disk cache by a new process (here: the
    memo emptied and the program made unrunnable): the same samples, phones and words; other
    settings are other entries; a damaged entry is run again and replaced; ``off`` keeps
    nothing; a cache that cannot be written is no error."""
    import subprocess

    from facelab.stimuli.speech import tts

    monkeypatch.setenv("FACELAB_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(tts, "_memo", type(tts._memo)(max_items=64))
    first = synthesize("こんにちは、キャッシュ。")
    slower = synthesize("こんにちは、キャッシュ。", speed=0.8)
    entries = sorted((tmp_path / "cache" / "tts").glob("*.bin"))
    assert len(entries) == 2 and slower.duration_s != first.duration_s
    # the key holds the library that makes the waveform, a Debian package of its own
    import shutil

    assert any("libHTSEngine" in f[0] for f in tts._program_stamps(shutil.which("open_jtalk")))
    tts._memo.clear()
    real_run = subprocess.run

    def no_open_jtalk(cmd, *a, **k):
        assert "open_jtalk" not in str(cmd[0]), "OpenJTalk ran again"
        return real_run(cmd, *a, **k)

    monkeypatch.setattr(tts.subprocess, "run", no_open_jtalk)
    again = synthesize("こんにちは、キャッシュ。")
    assert np.array_equal(again.samples, first.samples)
    assert again.phones == first.phones and again.words == first.words
    assert again.accents == first.accents
    monkeypatch.setattr(tts.subprocess, "run", real_run)
    whole = {e: e.stat().st_size for e in entries}
    for cut in (100, -1000):  # damaged: cut short in the trace, then in the sound
        for entry in entries:
            entry.write_bytes(entry.read_bytes()[:cut])
        tts._memo.clear()
        assert np.array_equal(synthesize("こんにちは、キャッシュ。").samples, first.samples)
        assert any(e.stat().st_size == whole[e] for e in entries)  # its entry written whole
    monkeypatch.setenv("FACELAB_CACHE_DIR", "off")
    tts._memo.clear()
    assert np.array_equal(synthesize("オフ。").samples, synthesize("オフ。").samples)
    assert len(list((tmp_path / "cache" / "tts").glob("*.bin"))) == 2
    (tmp_path / "file").write_text("not a folder")
    monkeypatch.setenv("FACELAB_CACHE_DIR", str(tmp_path / "file"))
    tts._memo.clear()
    assert synthesize("書けない。").duration_s > 0


def test_tts_parameters_change_the_voice() -> None:
    base = synthesize("あいうえお")
    slow = synthesize("あいうえお", speed=0.6)
    assert slow.duration_s > 1.4 * base.duration_s
    high = synthesize("あいうえお", pitch_halftones=6)
    low = synthesize("あいうえお", pitch_halftones=-6)
    assert _f0(high) > 1.6 * _f0(low)  # 12 half tones apart = 2x
    other = synthesize("あいうえお", alpha=0.45)
    assert not np.allclose(other.samples[:2000], base.samples[:2000])
    assert synthesize("あいうえお", sample_rate=16_000).sample_rate == 16_000


def test_an_utterance_asked_again_is_the_first_ones_copy(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A render and its checks ask for the same speech: OpenJTalk runs once, and a caller
    changing its samples does not change what the next caller gets."""
    from facelab.stimuli.speech import tts

    first = synthesize("おはようございます", speed=1.05)
    expected = first.samples.copy()
    first.samples[:] = 0.0  # the caller's own copy
    class RanAgainError(Exception):
        pass

    def refuse() -> str:
        raise RanAgainError

    monkeypatch.setattr(tts, "_open_jtalk", refuse)
    again = synthesize("おはようございます", speed=1.05)
    assert np.array_equal(again.samples, expected) and again.phones == first.phones
    assert again.words == first.words and again.source == first.source
    with pytest.raises(RanAgainError):
        synthesize("おはようございます", speed=1.1)  # other parameters: another run


def _f0(speech) -> float:
    phone = speech.phones[1]
    seg = speech.samples[int(phone.start * 48_000) : int(phone.end * 48_000)].astype(float)
    seg -= seg.mean()
    ac = np.correlate(seg, seg, mode="full")[len(seg) - 1 :]
    lo, hi = 48_000 // 600, 48_000 // 60
    return 48_000 / (lo + int(np.argmax(ac[lo:hi])))


@pytest.mark.parametrize(
    ("text", "message"), [("", "empty text"), ("   ", "empty text"), ("。。。", "could not read")]
)
def test_text_openjtalk_cannot_read(text: str, message: str) -> None:
    with pytest.raises(SpeechError, match=message):
        synthesize(text)


def test_trace_parser_rejects_garbage() -> None:
    assert parse_trace("[Output label]\n0 100 xx^sil-a+b=c/A\n\n")[0].phoneme == "a"
    with pytest.raises(SpeechError, match="unexpected OpenJTalk label"):
        parse_trace("[Output label]\nnonsense\n")


def _tone(rate: int, seconds: float = 0.5, freq: float = 1000.0, amp: float = 0.3) -> np.ndarray:
    t = np.arange(int(rate * seconds)) / rate
    return (amp * np.sin(2 * np.pi * freq * t)).astype(np.float32)


def test_recordings_are_mixed_to_mono_and_resampled(tmp_path: Path) -> None:
    left = _tone(44_100)
    stereo = np.column_stack([left, 0.5 * left])
    sf.write(tmp_path / "s.wav", stereo, 44_100)
    speech = load_audio(tmp_path / "s.wav", sample_rate=48_000)
    assert speech.sample_rate == 48_000
    assert len(speech.samples) == pytest.approx(0.5 * 48_000, abs=2)
    spectrum = np.abs(np.fft.rfft(speech.samples))
    assert np.fft.rfftfreq(len(speech.samples), 1 / 48_000)[np.argmax(spectrum)] == pytest.approx(
        1000, abs=3
    )
    assert np.max(np.abs(speech.samples[1000:-1000])) == pytest.approx(0.75 * 0.3, rel=0.02)
    sf.write(tmp_path / "m.flac", _tone(16_000), 16_000)
    assert load_audio(tmp_path / "m.flac", sample_rate=48_000).duration_s == pytest.approx(
        0.5, abs=1e-3
    )


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda p: sf.write(p, np.zeros(0, dtype=np.float32), 48_000), "empty"),
        (lambda p: sf.write(p, np.zeros(48_000, dtype=np.float32), 48_000), "silent"),
        (lambda p: sf.write(p, 1e-5 * _tone(48_000), 48_000), "silent"),
        (lambda p: sf.write(p, np.clip(5 * _tone(48_000), -1, 1), 48_000), "clipped"),
        (lambda p: p.write_bytes(b"RIFF\x00\x00\x00\x00WAVEjunkjunk"), "not a readable"),
        (lambda p: p.write_text("hello"), "not a readable"),
        (lambda p: sf.write(p, _tone(48_000, seconds=0.01), 48_000), "shorter than 50 ms"),
        (lambda p: sf.write(p, _tone(4_000), 4_000), "recorded at 4000 Hz; facelab needs at least"),
    ],
    ids=[
        "empty",
        "zeros",
        "very quiet",
        "clipped",
        "corrupt header",
        "text file",
        "too short",
        "4 kHz (was upsampled silently)",
    ],
)
def test_bad_audio_gives_a_clear_error(tmp_path: Path, make, message: str) -> None:
    path = tmp_path / "bad.wav"
    make(path)
    with pytest.raises(SpeechError, match=message) as info:
        load_audio(path, sample_rate=48_000)
    assert str(path) in str(info.value)


def test_missing_audio_file(tmp_path: Path) -> None:
    with pytest.raises(SpeechError, match="not found"):
        load_audio(tmp_path / "nope.wav", sample_rate=48_000)
