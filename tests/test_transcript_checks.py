"""Whether a recording says its transcript: the stimulus checks refuse a recording whose
transcript is other words (the mouth would say them), warn on doubtful ones, and pass right
ones - OpenJTalk at a voice setting the analyser was not trained on."""

from __future__ import annotations

import numpy as np
import pytest

from facelab.protocol_model import Stimulus
from facelab.stimuli.checks.run_checks import transcript_rows
from facelab.stimuli.render.prepare import speech_for
from facelab.stimuli.speech.audio import Speech, write_wav
from facelab.stimuli.speech.tts import synthesize

RATE = 48_000


def _rows(tmp_path, samples: np.ndarray, transcript: str) -> dict[str, object]:
    write_wav(tmp_path / "r.wav", Speech(samples, RATE))
    stim = Stimulus(id="r", audio="r.wav", transcript=transcript)
    speech = speech_for(stim, base_dir=tmp_path, sample_rate=RATE)
    rows = transcript_rows(stim, speech, kw={"clip": "c", "condition": "", "check": "track_source"})
    return {r.measure: r for r in rows}


def _said(text: str) -> np.ndarray:
    return synthesize(text, pitch_halftones=-5, alpha=0.5, speed=0.9, sample_rate=RATE).samples


@pytest.mark.parametrize(("said", "other"), [
    ("窓の外で子供たちが遊んでいます。", "明日の朝は早く起きてください。"),
    ("このりんごはとても甘いです。", "駅の前で待ち合わせしましょう。"),
])  # fmt: skip
def test_a_transcript_of_other_words_is_refused_and_the_right_one_passes(
    tmp_path, said: str, other: str
) -> None:
    samples = _said(said)
    right = _rows(tmp_path, samples, said)
    assert set(right) == {"transcript_vowels_heard", "transcript_order_fit"}
    assert all(r.passed for r in right.values()), right
    wrong = _rows(tmp_path, samples, other)
    refusal = wrong["transcript_matches_recording"]
    assert refusal.failed and refusal.severity == "error"
    assert not wrong["transcript_vowels_heard"].passed
    assert not wrong["transcript_order_fit"].passed
    assert "r.wav" in refusal.note and other in refusal.note and "hears clearly" in refusal.note
    assert "transcript_matches_recording" in wrong["transcript_vowels_heard"].note
    assert "leave the transcript out" in refusal.note and "accept" in refusal.note
    # the refusal is accepted by the check's name, as every stimulus check
    assert not refusal.accept().failed


def test_the_words_said_twice_are_doubted_but_not_refused(tmp_path) -> None:
    """Said twice, the transcript once: half its vowels heard, a warning (not a refusal:
    the order still fits better than reversed)."""
    once = _said("このりんごはとても甘いです。")
    twice = np.concatenate([once, np.zeros(RATE // 2, once.dtype), once])
    rows = _rows(tmp_path, twice, "このりんごはとても甘いです。")
    assert "transcript_matches_recording" not in rows
    heard = rows["transcript_vowels_heard"]
    assert heard.passed is False and heard.severity == "warning"
    assert "check that the transcript is what the recording says" in heard.note


def test_in_noise_other_words_are_doubted_but_not_refused(tmp_path) -> None:
    """At +10 dB of noise both measures fall for the right words too; the analyser's vowel
    confidence falls with them, and under 0.7 the check warns (naming why) instead of
    refusing."""
    from facelab.stimuli.checks.run_checks import TRANSCRIPT_CLEAR

    samples = _said("窓の外で子供たちが遊んでいます。")
    loud = samples[np.abs(samples) > 0.02 * np.abs(samples).max()]
    noise = np.random.default_rng(5).normal(size=len(samples))
    noisy = samples + noise * np.sqrt(np.mean(loud**2) / 10)  # +10 dB SNR, white
    rows = _rows(tmp_path, noisy.astype(np.float32), "明日の朝は早く起きてください。")
    assert "transcript_matches_recording" not in rows
    heard = rows["transcript_vowels_heard"]
    assert heard.passed is False and heard.severity == "warning"
    assert "hears this recording unclearly" in heard.note
    assert f"< {TRANSCRIPT_CLEAR:g}" in heard.note


def test_one_clips_failure_can_be_accepted_without_the_others() -> None:
    """--accept-check NAME:CLIP accepts one clip's failures (a recording listened to and
    found right), not every failure of the check (a wrong transcript elsewhere stays)."""
    import argparse

    from facelab.errors import StageError
    from facelab.experiment.cli.common import check_options
    from facelab.stimuli.checks.rows import CheckRow, accept_checks

    rows = [CheckRow(clip, "", "track_source", "transcript_matches_recording", 0.2, "", False)
            for clip in ("s__a__std", "s__b__std")]  # fmt: skip
    kept = accept_checks(rows, ["track_source:s__a__std"])
    assert [r.failed for r in kept] == [False, True]
    assert all(not r.failed for r in accept_checks(rows, ["track_source"]))
    with pytest.raises(StageError, match="nonsense:s__a__std: unknown check"):
        accept_checks(rows, ["nonsense:s__a__std"])
    # a mistyped clip would accept nothing, silently: it is named with the failing clips
    with pytest.raises(StageError, match=r"no clip 's__c__std'.*failed on: s__a__std, s__b__std"):
        accept_checks(rows, ["track_source:s__c__std"])
    parser = argparse.ArgumentParser()
    check_options(parser)
    assert parser.parse_args(["--accept-check", "track_source:s__a__std"]).accept_check == [
        "track_source:s__a__std"]  # fmt: skip
    for bad in ("nonsense", "track_source:"):
        with pytest.raises(SystemExit):
            parser.parse_args(["--accept-check", bad])


def test_a_refused_recording_fails_every_clip_of_its_stimulus(tmp_path) -> None:
    """The refusal is about the recording (filed under its first clip): every condition's
    clip of the stimulus is marked failed in clips.csv - preflight refuses a session by
    the clips it shows - and accepting the named clip accepts the stimulus."""
    import csv

    from facelab.stimuli.checks.rows import CheckRow, accept_checks
    from facelab.stimuli.checks.run_checks import CheckReport, record_in_manifest

    clips = [("s__r__std", "std", "r"), ("s__r__emph", "emph", "r"), ("s__q__std", "std", "q")]
    with open(tmp_path / "clips.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["clip_id", "condition", "stimulus_set", "stimulus"])
        w.writerows([(c, cond, "s", stim) for c, cond, stim in clips])
    row = CheckRow("s__r__std", "", "track_source", "transcript_matches_recording", 0.2, "", False)

    def marks(rows) -> dict[str, str]:
        record_in_manifest(tmp_path, CheckReport(rows=rows))
        with open(tmp_path / "clips.csv", newline="", encoding="utf-8") as fh:
            return {r["clip_id"]: r["stimulus_checks"] for r in csv.DictReader(fh)}

    assert marks([row]) == {"s__r__std": "failed: track_source",
                            "s__r__emph": "failed: track_source", "s__q__std": "passed"}
    accepted = accept_checks([row], ["track_source:s__r__std"])
    assert set(marks(accepted).values()) == {"accepted: track_source", "passed"}
