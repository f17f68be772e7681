"""One command-line grammar (issue 31.6): the protocol positional, one meaning per flag name,
options that belong to their verb, one overwrite rule - and the old spellings still working
for one release, each with a deprecation message."""

from __future__ import annotations

from pathlib import Path

import pytest

from facelab.experiment.cli import main


def _simulate(kato: Path, results: Path, *extra: str) -> int:
    return main(["simulate", str(kato), "--participants", "2", "--results", str(results), *extra])


@pytest.mark.parametrize(
    "argv",
    [
        # an option of another verb is an error, not silently ignored
        ["impression", "synth", "--out", "s.csv", "--avatar", "nope.glb"],
        ["impression", "fit", "s.csv", "--label", "x", "--out", "m.json", "--levels", "1"],
        ["behaviour", "sheet", "--out", "x.png", "--alpha", "0.3"],
        ["avatar", "sample", "--out", "x.glb", "--sheet", "x.png"],
        ["bench", "visemes", "--avatar", "default"],
        # each verb's required options are argparse's
        ["impression", "fit", "s.csv", "--out", "m.json"],
    ],
)
def test_options_belong_to_their_verb(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "unrecognized arguments" in err or "required" in err


def test_analyze_takes_the_protocol_first_and_the_old_spelling_with_a_warning(
    kato_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert _simulate(kato_path, tmp_path, "--sim-seed", "3") == 0
    out = tmp_path / "a"
    assert main(["analyze", str(kato_path), str(tmp_path), "--out", str(out)]) == 0
    first = (out / "paper_layout.csv").read_bytes()
    capsys.readouterr()
    # one overwrite rule: an analysis that is there is replaced only with --force
    assert main(["analyze", str(kato_path), str(tmp_path), "--out", str(out)]) == 2
    assert "--force" in capsys.readouterr().err
    assert main(["analyze", str(tmp_path), "--protocol", str(kato_path), "--out", str(out),
                 "--force"]) == 0  # fmt: skip
    assert "--protocol is deprecated" in capsys.readouterr().err
    assert (out / "paper_layout.csv").read_bytes() == first
    assert main(["analyze", str(kato_path)]) == 2  # the results are missing


def test_seed_flags_have_one_meaning_each(
    kato_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # --sim-seed: simulated answers; the old --seed of simulate still works, with a message
    assert _simulate(kato_path, tmp_path / "new", "--sim-seed", "4") == 0
    assert _simulate(kato_path, tmp_path / "old", "--seed", "4") == 0
    assert "--seed is deprecated; use --sim-seed" in capsys.readouterr().err
    new = sorted((tmp_path / "new").rglob("*_beh.tsv"))
    old = sorted((tmp_path / "old").rglob("*_beh.tsv"))
    assert [p.read_bytes() for p in new] == [p.read_bytes() for p in old]
    assert _simulate(kato_path, tmp_path / "none") == 2  # the seed of the answers is asked for
    # --seed of design is the study seed; --boot-seed the bootstrap's
    assert main(["design", str(kato_path), "--participant", "P01", "--seed", "7"]) == 0


def test_power_takes_the_protocol_first(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from facelab.resources import protocol_path

    path = str(protocol_path("gain_vas"))
    argv = ["--n", "4", "--sims", "5", "--jobs", "1", "--json"]
    assert main(["power", path, "--simulate", *argv]) == 0
    new = capsys.readouterr().out
    assert main(["power", "--simulate", path, *argv]) == 0
    captured = capsys.readouterr()
    assert "--simulate PROTOCOL is deprecated" in captured.err
    assert captured.out.replace(" ", "") == new.replace(" ", "")
    assert main(["power", "--reported-p", "0.01", "--participants", "8", "--sims", "200"]) == 0
    assert "--participants is deprecated; use --reported-n" in capsys.readouterr().err


def test_measure_z_capture_rate_is_capture_fps(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["measure-z", "--help"])
    text = capsys.readouterr().out
    assert "--capture-fps" in text and "--fps" not in text.replace("--capture-fps", "")


def test_errors_name_the_verbs_usage_and_spellings_do_not_conflict(
    kato_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An unknown option is said with the verb's own usage; the old and the new spelling of
    one option given together are an error, not "the last one wins"."""
    with pytest.raises(SystemExit) as info:
        main(["render", str(kato_path), "--bogus"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "usage: facelab render" in err and "unrecognized arguments: --bogus" in err
    with pytest.raises(SystemExit):
        main(["impression", "synth", "--out", "x.csv", "--bogus"])
    assert "usage: facelab impression synth" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        _simulate(kato_path, tmp_path, "--seed", "3", "--sim-seed", "4")
    assert info.value.code == 2
    assert "--seed and --sim-seed are one option" in capsys.readouterr().err
    assert not (tmp_path / "kato2021").exists()  # nothing written


def test_a_shipped_protocol_is_named_by_its_name(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)  # no kato2021 file here
    assert main(["validate", "kato2021"]) == 0
    assert "study 'kato2021'" in capsys.readouterr().out
    assert main(["design", "kato2021", "--participant", "P01"]) == 0
    assert main(["validate", "no_such_protocol"]) == 2
