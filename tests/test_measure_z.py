"""measure-z on generated captures with a known Z, in both CSV formats, and its errors."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from facelab.errors import StageError
from facelab.experiment.cli import main
from facelab.stimuli.arkit import ARKIT_NAMES
from facelab.stimuli.capture.measure_z import measure_z, read_capture, read_onsets
from facelab.stimuli.capture.zmatrix import load_z
from facelab.stimuli.speech.track import VOWELS

FPS = 60.0


def _capture(rng: np.random.Generator, z: np.ndarray, order: str, speaker_bias: float):
    """Frames at 60 fps: each vowel ramps in over 50 ms *before* its onset (the mouth leads),
    holds Z's column (+ speaker bias + noise) for 0.3 s, then relaxes; 0.4 s between."""
    times, frames, onsets = [], [], []
    t = 0.3
    for vowel in order:
        onsets.append((vowel, t))
        t += 0.7
    n = int((t + 0.3) * FPS)
    coeffs = np.zeros((n, 52))
    for vowel, onset in onsets:
        j = VOWELS.index(vowel)
        a, b = int(np.ceil((onset - 0.05) * FPS)), int((onset + 0.3) * FPS)
        coeffs[a:b] = z[:, j] + speaker_bias
    coeffs = np.clip(coeffs + rng.normal(0, 0.01, coeffs.shape), 0, 1)
    times = np.arange(n) / FPS
    return times, coeffs, onsets, frames


def _write_generic(path: Path, times: np.ndarray, coeffs: np.ndarray) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time_s", *ARKIT_NAMES])
        for t, row in zip(times, coeffs, strict=True):
            w.writerow([f"{t:.5f}", *[f"{v:.5f}" for v in row]])


def _write_live_link(path: Path, times: np.ndarray, coeffs: np.ndarray) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(
            [
                "Timecode",
                "BlendShapeCount",
                *[n[0].upper() + n[1:] for n in ARKIT_NAMES],
                "HeadYaw",
                "HeadPitch",
            ]
        )
        for k, row in enumerate(coeffs):
            frame = k % 60
            secs = 10 + k // 60
            w.writerow([f"14:03:{secs:02d}:{frame:02d}.000", 61, *[f"{v:.5f}" for v in row], 0, 0])


def test_measure_z_recovers_a_known_z(tmp_path: Path, rng: np.random.Generator) -> None:
    z_true = load_z("standard")
    onset_rows = []
    for s, (bias, writer) in enumerate(
        [(0.02, _write_generic), (-0.02, _write_live_link), (0.0, _write_generic)]
    ):
        times, coeffs, onsets, _ = _capture(
            rng, z_true, "aiueo" * 3, bias * (z_true.max(axis=1) > 0)
        )
        path = tmp_path / f"spk{s}.csv"
        writer(path, times, coeffs)
        onset_rows += [
            {"capture": path.name, "vowel": v, "onset_s": round(t, 4), "speaker": f"S{s}"}
            for v, t in onsets
        ]
    with open(tmp_path / "onsets.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["capture", "vowel", "onset_s", "speaker"])
        w.writeheader()
        w.writerows(onset_rows)
    captures = [read_capture(tmp_path / f"spk{s}.csv") for s in range(3)]
    assert captures[1].times[1] == pytest.approx(1 / 60)  # Live Link Face timecode parsed
    result = measure_z(captures, read_onsets(tmp_path / "onsets.csv"))
    np.testing.assert_allclose(result.z, z_true, atol=0.015)  # biases cancel across speakers
    assert result.spread["a"]["repetitions"] == 9 and result.spread["a"]["speakers"] == 3
    assert "jawOpen" in result.spread["a"]["main_rows"]
    # and through the command line, writing a Z the protocol can use
    out = tmp_path / "z.csv"
    argv = [
        "measure-z",
        *map(str, (tmp_path / f"spk{s}.csv" for s in range(3))),
        "--onsets",
        str(tmp_path / "onsets.csv"),
        "--out",
        str(out),
    ]
    assert main(argv) == 0
    np.testing.assert_allclose(load_z("z.csv", base_dir=tmp_path), z_true, atol=0.015)
    assert main(argv) == 2  # never overwrites without --force


def test_window_matters_when_the_shape_changes_after_onset(tmp_path: Path) -> None:
    times = np.arange(120) / FPS
    coeffs = np.zeros((120, 52))
    coeffs[30:36, ARKIT_NAMES.index("jawOpen")] = 0.8  # first 0.1 s after onset at 0.5 s
    coeffs[36:90, ARKIT_NAMES.index("jawOpen")] = 0.2  # later, the jaw closes
    _write_generic(tmp_path / "c.csv", times, coeffs)
    cap = read_capture(tmp_path / "c.csv")
    onsets = [{"capture": "c", "vowel": v, "onset_s": 0.5, "speaker": None} for v in VOWELS]
    z = measure_z([cap], onsets).z
    assert z[ARKIT_NAMES.index("jawOpen"), 0] == pytest.approx(0.8)
    assert measure_z([cap], onsets, window_s=0.5).z[ARKIT_NAMES.index("jawOpen"), 0] < 0.5


def test_capture_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "few.csv").write_text("time,jawOpen\n0,0.1\n")
    with pytest.raises(StageError, match=r"missing ARKit columns.*\(1 of 52 found\)"):
        read_capture(tmp_path / "few.csv")
    _write_generic(tmp_path / "ok.csv", np.arange(10) / FPS, np.zeros((10, 52)))
    text = (tmp_path / "ok.csv").read_text().replace("time_s", "when")
    (tmp_path / "notime.csv").write_text(text)
    with pytest.raises(StageError, match="no time column"):
        read_capture(tmp_path / "notime.csv")
    coeffs = np.zeros((10, 52))
    coeffs[3, 5] = np.nan  # was accepted, and wrote a Z with NaN in it
    _write_generic(tmp_path / "nan.csv", np.arange(10) / FPS, coeffs)
    with pytest.raises(StageError, match=r"nan\.csv:5: .* is nan; ARKit coefficients lie in"):
        read_capture(tmp_path / "nan.csv")
    coeffs[3, 5] = 1.5
    _write_generic(tmp_path / "big.csv", np.arange(10) / FPS, coeffs)
    with pytest.raises(StageError, match=r"big\.csv:5: .* is 1\.5"):
        read_capture(tmp_path / "big.csv")
    times = np.arange(10) / FPS
    times[4] = np.nan
    _write_generic(tmp_path / "nantime.csv", times, np.zeros((10, 52)))
    with pytest.raises(StageError, match="times must increase"):
        read_capture(tmp_path / "nantime.csv")
    (tmp_path / "on.csv").write_text("capture,vowel,onset_s\nok,a,nan\n")
    with pytest.raises(StageError, match=r"on\.csv:2: onset_s is 'nan', expected seconds >= 0"):
        read_onsets(tmp_path / "on.csv")
    for value in ("zero", "-0.3"):  # "zero" said Python's "could not convert string to float"
        (tmp_path / "on.csv").write_text(f"capture,vowel,onset_s\nok,a,{value}\n")
        with pytest.raises(StageError, match=rf"on\.csv:2: onset_s is '{value}', expected"):
            read_onsets(tmp_path / "on.csv")
    (tmp_path / "on.csv").write_text("capture,vowel,onset_s\nok,a,0.1\nok,a,0.1\n")
    with pytest.raises(StageError, match=r"on\.csv:3: the onset at 0.1 s in capture 'ok' is "
                       r"listed twice \(line 2 too\)"):  # fmt: skip
        read_onsets(tmp_path / "on.csv")
    (tmp_path / "on.csv").write_text("capture,vowel\nok,a\n")
    with pytest.raises(StageError, match=r"on\.csv:1: missing column\(s\) onset_s"):
        read_onsets(tmp_path / "on.csv")
    # captures cut short, with a word for a number, or with no rows: named by line and column
    lines = (tmp_path / "ok.csv").read_text().splitlines()
    (tmp_path / "cut.csv").write_text("\n".join([*lines[:4], lines[4][: len(lines[4]) // 2]]))
    with pytest.raises(StageError, match=r"cut\.csv:5: \d+ fields, the header has 53"):
        read_capture(tmp_path / "cut.csv")
    fields = lines[3].split(",")
    fields[7] = "abc"
    (tmp_path / "word.csv").write_text("\n".join([*lines[:3], ",".join(fields), *lines[4:]]))
    with pytest.raises(StageError, match=r"word\.csv:4: \w+ is 'abc', expected a number"):
        read_capture(tmp_path / "word.csv")
    (tmp_path / "head.csv").write_text(lines[0] + "\n")
    with pytest.raises(StageError, match=r"head\.csv: a header and no rows"):
        read_capture(tmp_path / "head.csv")
    (tmp_path / "on.csv").write_text("capture,vowel,onset_s\nok,x,0.1\n")
    with pytest.raises(StageError, match="vowel 'x' is not one of"):
        read_onsets(tmp_path / "on.csv")
    onsets = [{"capture": "ok", "vowel": "a", "onset_s": 0.0, "speaker": None}]
    with pytest.raises(StageError, match="no onsets for vowel 'i'"):
        measure_z([read_capture(tmp_path / "ok.csv")], onsets)
    assert main(["measure-z", str(tmp_path / "ok.csv"), "--out", str(tmp_path / "z.csv")]) == 2
    assert "give --onsets" in capsys.readouterr().err
    both = ["measure-z", str(tmp_path / "ok.csv"), "--onsets", str(tmp_path / "on.csv"),
            "--vowels", "aiueo", "--out", str(tmp_path / "z.csv")]  # fmt: skip
    assert main(both) == 2 and "not both" in capsys.readouterr().err
    _ = json
