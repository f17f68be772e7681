"""Where a stimulus' viseme track comes from (issue 32.2): the words whenever they are known."""

from __future__ import annotations

from pathlib import Path

import pytest

from facelab.protocol import Stimulus
from facelab.resources import protocol_path


def test_the_words_drive_the_track_whenever_they_are_known() -> None:
    assert Stimulus(id="t", text="あ。").track_source == "words"
    assert Stimulus(id="r", audio="r.wav", transcript="あ").track_source == "words"
    assert Stimulus(id="r", audio="r.wav").track_source == "audio"
    assert Stimulus(id="t", text="あ。", track_from="audio").track_source == "audio"
    assert Stimulus(id="s", silence_s=1.0).track_source == "silence"
    with pytest.raises(ValueError, match="needs the words"):
        Stimulus(id="r", audio="r.wav", track_from="words")
    with pytest.raises(ValueError, match="no track"):
        Stimulus(id="s", silence_s=1.0, track_from="audio")


def test_a_tts_stimulus_is_driven_by_its_phoneme_timing() -> None:
    from facelab.stimuli.render.prepare import speech_for, track_source_text, tracks_for

    stim = Stimulus(id="t", text="あいうえお。")
    speech = speech_for(stim, base_dir=Path("."), sample_rate=48_000)
    track, _ = tracks_for(stim, speech)
    assert track.latency_s == 0  # phonemes: no analyser latency
    heard = track.vowels().argmax(axis=1)
    for p in speech.phones:  # every vowel's middle frame shows that vowel
        if p.phoneme in "aiueo":
            mid = round((p.start + p.end) / 2 * 100)
            assert "aiueo"[heard[mid]] == p.phoneme
    assert track_source_text(stim).startswith("words")
    analysed, _ = tracks_for(stim.model_copy(update={"track_from": "audio"}), speech)
    assert analysed.latency_s == 0 and track_source_text(
        stim.model_copy(update={"track_from": "audio"})
    ).startswith("audio analysis")


def test_validate_says_in_one_line_which_recordings_are_analysed_audio_only(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from facelab.experiment.cli import main
    from facelab.stimuli.speech.audio import Speech, write_wav
    from facelab.stimuli.speech.tts import synthesize

    tts = synthesize("あいうえお。", sample_rate=22_050)
    write_wav(tmp_path / "rec.wav", Speech(tts.samples * 0.5, tts.sample_rate))
    text = protocol_path("kato2021").read_text(encoding="utf-8")
    text = text.replace("text: あ。い。う。え。お。", "audio: rec.wav", 1)
    (tmp_path / "p.yaml").write_text(text, encoding="utf-8")
    assert main(["validate", str(tmp_path / "p.yaml")]) == 0
    out = capsys.readouterr().out
    notes = [line for line in out.splitlines() if "audio-only" in line]
    assert len(notes) == 1 and "aiueo (rec.wav)" in notes[0], out
