"""`facelab validate` reads every file a protocol names as `facelab render` will (issue 34.4):
a Z matrix, recorded audio, the avatar - so "valid" means "will render". Each refusal names
the protocol's line and key, and the file and its problem, in words."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from facelab.experiment.cli import main
from facelab.resources import package_file


def _protocol(tmp_path: Path, kato_path: Path, **swap: str) -> Path:
    text = kato_path.read_text(encoding="utf-8")
    for old, new in swap.values():
        assert old in text
        text = text.replace(old, new, 1)
    path = tmp_path / "study.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def _z_without_a_row(tmp_path: Path) -> None:
    rows = package_file("facelab.stimuli", "data", "z_standard.csv").read_text().splitlines()
    (tmp_path / "z51.csv").write_text("\n".join(rows[:-1]) + "\n", encoding="utf-8")


CASES = {
    "z with 51 rows": (
        {"z": ("params: {z: standard, gain: 1.0}", "params: {z: z51.csv, gain: 1.0}")},
        r"study\.yaml:28: conditions\[1\]\.params\.z: .*z51\.csv: missing ARKit rows",
    ),
    "empty wav": (
        {"audio": ("text: あ。い。う。え。お。", "audio: empty.wav")},
        r"study\.yaml:41: stimulus_sets\[0\]\.stimuli\[0\]\.audio: .*empty\.wav",
    ),
    "jpeg renamed glb": (
        {"avatar": ("avatar: default", "avatar: photo.glb")},
        r"study\.yaml:106: rendering\.avatar: .*photo\.glb",
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_validate_refuses_what_render_would_refuse(
    case: str, tmp_path: Path, kato_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    swap, expected = CASES[case]
    _z_without_a_row(tmp_path)
    (tmp_path / "empty.wav").write_bytes(b"")
    (tmp_path / "photo.glb").write_bytes(b"\xff\xd8\xff\xe0\x00\x10JFIF\x00" + bytes(500))
    path = _protocol(tmp_path, kato_path, **swap)
    assert main(["validate", str(path)]) == 2
    err = capsys.readouterr().err
    assert re.search(expected, err), err
    assert "Traceback" not in err and "Error:" not in err  # no exception class names


def test_validate_passes_the_shipped_protocols(capsys: pytest.CaptureFixture[str]) -> None:
    shipped = sorted((Path(__file__).parents[1] / "protocols").glob("*.yaml"))
    assert main(["validate", *map(str, shipped)]) == 0
    assert capsys.readouterr().out.count("ok: ") == len(shipped)


def test_a_missing_file_does_not_hide_an_unreadable_one(
    tmp_path: Path, kato_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One report holds every problem: a Z file that is not there (found while the protocol
    is read) and a recording that is a tone (found when the files are read), each at its
    line - validate and render alike, and render writes nothing."""
    import numpy as np
    import soundfile as sf

    t = np.arange(16_000) / 16_000
    sf.write(tmp_path / "tone.wav", 0.3 * np.sin(2 * np.pi * 440 * t), 16_000)
    path = _protocol(tmp_path, kato_path,
                     z=("params: {z: standard, gain: 1.0}", "params: {z: nothere.csv, gain: 1.0}"),
                     audio=("text: あ。い。う。え。お。", "audio: tone.wav"))  # fmt: skip
    for argv in (["validate", str(path)],
                 ["render", str(path), "--out", str(tmp_path / "clips"), "--quiet"]):  # fmt: skip
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "(2 problems)" in err, err
        assert re.search(r"study\.yaml:28: conditions\[1\]\.params\.z: .*nothere\.csv", err)
        assert re.search(r"study\.yaml:41: stimulus_sets\[0\]\.stimuli\[0\]\.audio: tone\.wav: "
                         r"this is not speech: a tone at 440 Hz", err), err  # fmt: skip
    assert not (tmp_path / "clips").exists()


def test_a_transcript_the_recording_does_not_say_is_refused_by_validate(
    tmp_path: Path, kato_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A short recording with a long transcript fails the alignment the render does: validate
    says so at the transcript's line (it passed, and the render failed after drawing clips);
    the render refuses before writing anything, and aligns each recording once."""
    import soundfile as sf

    from facelab.errors import VisemeError
    from facelab.stimuli.speech import align
    from facelab.stimuli.speech.tts import synthesize

    said = synthesize("はい", sample_rate=16_000)
    sf.write(tmp_path / "hai.wav", said.samples, 16_000)
    path = _protocol(tmp_path, kato_path, audio=(
        "text: あ。い。う。え。お。\n        tts: {speed: 0.6}",
        "audio: hai.wav\n        transcript: こんにちは、今日はいい天気ですね"),
        vowels=("expected_vowels: aiueo", "expected_vowels: ai"))  # fmt: skip
    assert main(["validate", str(path)]) == 2
    err = capsys.readouterr().err
    assert re.search(r"study\.yaml:42: stimulus_sets\[0\]\.stimuli\[0\]\.transcript: hai\.wav "
                     r"and its transcript: text and audio disagree: the text has words the "
                     r"recording does not say", err), err  # fmt: skip
    assert main(["render", str(path), "--out", str(tmp_path / "clips"), "--quiet"]) == 2
    assert "and its transcript" in capsys.readouterr().err
    assert not (tmp_path / "clips").exists()
    # a disagreement is kept too: asked again, the same error without aligning again
    calls = []
    real = align._align_phones
    align._align_phones = lambda *a, **k: calls.append(1) or real(*a, **k)  # type: ignore
    try:
        for _ in range(2):
            with pytest.raises(VisemeError, match="text and audio disagree"):
                align.align_phones(said.samples, sample_rate=16_000,
                                   text="こんにちは、今日はいい天気ですね")  # fmt: skip
        first = align.align_phones(said.samples, sample_rate=16_000, text="はい")
        assert align.align_phones(said.samples, sample_rate=16_000, text="はい") is first
    finally:
        align._align_phones = real  # type: ignore
    assert len(calls) == 2  # each recording and text once
