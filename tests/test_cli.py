"""The command line: outputs, exit codes, messages, --help everywhere."""

from __future__ import annotations

import csv
import io
import subprocess
import sys
from pathlib import Path

import pytest

from facelab.experiment.cli import _parser, main

COMMANDS = sorted(_parser()._subparsers._group_actions[0].choices)  # type: ignore[union-attr]


def test_validate_ok(kato_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["validate", str(kato_path)]) == 0
    out = capsys.readouterr().out
    assert "ok:" in out and "18 trials x 2 items" in out


def test_design_prints_csv(kato_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["design", str(kato_path), "--participant", "P01"]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert list(rows[0]) == [
        "trial_index",
        "block",
        "set_index",
        "stimulus_set",
        "stimulus",
        "condition",
        "repetition",
    ]
    assert len(rows) == 18
    assert main(["design", str(kato_path), "--participant", "P01", "--seed", "7"]) == 0
    assert list(csv.DictReader(io.StringIO(capsys.readouterr().out))) != rows


def test_design_out_never_overwrites(
    kato_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "trials.csv"
    assert main(["design", str(kato_path), "--participant", "P01", "--out", str(out)]) == 0
    before = out.read_bytes()
    assert main(["design", str(kato_path), "--participant", "P02", "--out", str(out)]) == 2
    assert "exists" in capsys.readouterr().err and out.read_bytes() == before


def test_bad_participant_exits_2(kato_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["design", str(kato_path), "--participant", "P 01"]) == 2
    assert "participant id 'P 01' is not valid" in capsys.readouterr().err


@pytest.mark.parametrize("command", COMMANDS)
def test_help_everywhere(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main([command, "--help"])
    assert info.value.code == 0
    assert "usage: facelab" in capsys.readouterr().out


def test_console_script_gives_no_traceback(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("study: [\n", encoding="utf-8")
    exe = Path(sys.executable).with_name("facelab")
    proc = subprocess.run(
        [str(exe), "validate", str(bad)], capture_output=True, text=True, check=False
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert f"{bad}:2: (document): not valid YAML" in proc.stderr
    proc = subprocess.run([str(exe), "nonsense"], capture_output=True, text=True, check=False)
    assert proc.returncode == 2 and "invalid choice" in proc.stderr
