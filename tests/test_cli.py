"""The command line: outputs, exit codes, messages, --help everywhere."""

from __future__ import annotations

import argparse
import csv
import io
import subprocess
import sys
from pathlib import Path

import pytest

from facelab.experiment.cli import build_parser, main

COMMANDS = sorted(build_parser()._subparsers._group_actions[0].choices)  # type: ignore[union-attr]


def test_validate_ok(kato_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["validate", str(kato_path)]) == 0
    out = capsys.readouterr().out
    assert "ok:" in out and "18 trials x 2 items" in out


def test_validate_loads_neither_the_renderer_nor_the_signal_stack(kato_path: Path) -> None:
    """`facelab validate` is run after every edit of a protocol: it reads every file the
    protocol names and audits the avatar without importing pyrender or scipy.signal (about
    half of its time before they were left to the commands that render or analyse)."""
    script = (
        "import sys\n"
        "from facelab.experiment.cli import main\n"
        f"assert main(['validate', {str(kato_path)!r}]) == 0\n"
        "print(sorted(m for m in ('pyrender', 'scipy.signal', 'OpenGL') if m in sys.modules))\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "[]"


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


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["design", "{kato}", "--participant", "P01", "--out", "{tmp}/no/such/t.csv"],
            "does not exist",
        ),
        (["design", "{kato}", "--participant", "P01", "--out", "{tmp}"], "is a folder"),
        (["schema", "--out", "{tmp}/no/such/s.json"], "does not exist"),
        (["simulate", "{kato}", "--sim-seed", "1", "--results", "{tmp}/file.txt"], "is a file"),
        (["analyze", "{kato}", "{tmp}", "--force", "--out", "{tmp}/file.txt"], "is a file"),
    ],
)
def test_output_path_mistakes_are_clear_errors(
    kato_path: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    args: list[str],
    message: str,
) -> None:
    (tmp_path / "file.txt").write_text("x")
    filled = [a.format(kato=kato_path, tmp=tmp_path) for a in args]
    if filled[0] == "analyze":  # needs logs to get as far as the output folder
        assert (
            main(
                [
                    "simulate",
                    str(kato_path),
                    "--sim-seed",
                    "1",
                    "--participants",
                    "2",
                    "--results",
                    str(tmp_path),
                ]
            )
            == 0
        )
        capsys.readouterr()
    assert main(filled) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_track_output_paths_are_checked_before_any_work(
    kato_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for option in ("--plot", "--csv"):
        code = main(
            [
                "track",
                str(kato_path),
                "--stimulus",
                "vowels/aiueo",
                option,
                str(tmp_path / "x" / "y"),
            ]
        )
        assert code == 2 and "does not exist" in capsys.readouterr().err


def test_a_picture_named_without_its_format_is_refused_before_anything_is_written(
    kato_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A figure or sheet file name without a picture format's ending was a traceback from
    the drawing library after the other outputs had been written (the track's CSV, the
    behaviour plan); a plot asked of a command that draws none was ignored."""
    t = tmp_path
    cases = [
        (["avatar", "inspect", "default", "--sheet", f"{t}/sheet"], "--sheet", ".png"),
        (["behaviour", "sheet", "--out", f"{t}/units.txt"], "--out", ".tif"),
        (["track", str(kato_path), "--stimulus", "vowels/aiueo", "--csv", f"{t}/track.csv",
          "--plot", f"{t}/track.txt"], "--plot", ".eps"),
        (["behaviour", "plan", "--emotion", "joy=1", "--text", "こんにちは", "--duration-s", "3",
          "--seed", "1", "--out", f"{t}/plan.json", "--figure", f"{t}/plan"], "--figure", ".pdf"),
        (["power", str(kato_path), "--simulate", "--n", "8", "--sims", "2", "--plot",
          f"{t}/power.docx"], "--plot", ".svg"),
    ]  # fmt: skip
    for argv, option, ending in cases:
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert f"{option} " in err and "expected a file name ending in " in err, err
        assert ending in err.split("ending in ", 1)[1], err
        assert "Traceback" not in err
    assert list(tmp_path.iterdir()) == []  # neither the track's CSV nor the plan
    assert main(["power", "--reported-p", "0.02", "--plot", f"{t}/p.png"]) == 2
    assert "--plot draws the power of simulated studies" in capsys.readouterr().err


@pytest.mark.parametrize("session", ["0", "99999999999999999999", "ten"])
def test_session_numbers_are_bounded(
    kato_path: Path, capsys: pytest.CaptureFixture[str], session: str
) -> None:
    with pytest.raises(SystemExit) as info:
        main(["run", str(kato_path), "--participant", "P01", "--session", session])
    assert info.value.code == 2
    assert "--session" in capsys.readouterr().err


def test_shipped_protocols_are_listed_and_copied(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["protocols"]) == 0
    assert "kato2021" in capsys.readouterr().out
    assert main(["protocols", "--copy", "kato2021", "--to", str(tmp_path)]) == 0
    copied = tmp_path / "kato2021.yaml"
    assert main(["validate", str(copied)]) == 0
    assert main(["protocols", "--copy", "kato2021", "--to", str(tmp_path)]) == 2
    assert "exists" in capsys.readouterr().err
    assert main(["protocols", "--copy", "nope", "--to", str(tmp_path)]) == 2
    assert "no shipped protocol 'nope'" in capsys.readouterr().err
    # the name may also come first, as the README writes it
    other = tmp_path / "other"
    assert main(["protocols", "gain_vas", "--to", str(other)]) == 0
    assert (other / "gain_vas.yaml").is_file()
    assert main(["protocols", "gain_vas", "--copy", "kato2021", "--to", str(other)]) == 2
    assert "disagree" in capsys.readouterr().err


def test_every_shipped_protocol_copied_out_validates_where_it_lands(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A copy must bring the files the protocol names (e.g. an impression model)."""
    from facelab.resources import shipped_protocols

    for name in shipped_protocols():
        dest = tmp_path / name
        assert main(["protocols", name, "--to", str(dest)]) == 0
        assert main(["validate", str(dest / f"{name}.yaml")]) == 0, capsys.readouterr().err
    assert (tmp_path / "horii_impression" / "horii_friendly_model.json").is_file()


def test_clip_progress_draws_nothing_into_logs(capsys: pytest.CaptureFixture[str]) -> None:
    from facelab.experiment.cli.common import GridProgress

    progress = GridProgress(quiet=False)  # stderr is captured here, not a terminal
    progress.start(2)
    progress("a", "done", 1, 0, 0)
    progress("b", "failed", 1, 1, 0)
    progress.close()
    captured = capsys.readouterr()
    assert captured.err == "" and captured.out == ""


def test_user_tables_that_are_not_utf8_or_empty_get_clear_errors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    latin = tmp_path / "latin.csv"
    latin.write_bytes(b"person,expression\n\xff\xfe,x\n")
    empty = tmp_path / "empty.csv"
    empty.write_bytes(b"")
    for argv in (
        ["impression", "fit", str(latin), "--label", "x", "--out", str(tmp_path / "m.json")],
        ["impression", "samples", str(latin), "--out", str(tmp_path / "s.csv")],
        ["measure-z", str(latin), "--vowels", "aiueo", "--out", str(tmp_path / "z.csv")],
    ):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "latin.csv" in err and ("UTF-8" in err or "utf-8" in err), err
    assert main(["behaviour", "fit", str(empty), "--out", str(tmp_path / "l.json")]) == 2
    assert "empty.csv: empty; expected a header line with emotion" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        main(["bench", "render", "--runs", "0"])
    assert info.value.code == 2
    assert "--runs: expected a whole number >= 1, got 0" in capsys.readouterr().err


def test_export_names_a_database_it_cannot_reach(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    url = "postgresql+psycopg://nobody@127.0.0.1:1/none"
    assert main(["export", "--db", url, "--results", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "cannot connect" in err and "127.0.0.1" in err and "Traceback" not in err


def test_export_never_writes_into_a_database_that_is_not_facelabs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """export --db at an empty file or another program's SQLite database created facelab's
    tables in it and said "exported 0 online sessions", exit 0; now refused, the file as it
    was (no tables, no WAL journal)."""
    import sqlite3

    empty = tmp_path / "empty.db"
    empty.write_bytes(b"")
    notes = tmp_path / "notes.sqlite"
    with sqlite3.connect(notes) as con:
        con.execute("CREATE TABLE notes (t TEXT)")
    con.close()
    for db in (empty, notes):
        before = db.read_bytes()
        assert main(["export", "--db", f"sqlite:///{db}", "--results", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err
        assert "not a facelab online database" in err and "was not changed" in err, err
        assert db.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty.db", "notes.sqlite"]
    # a facelab database (WAL mode) of a newer schema: refused, and the journal files a
    # read-only look at a WAL database makes (-shm, -wal) are not left beside it
    from facelab.experiment.online.db import open_engine

    newer = tmp_path / "newer.sqlite"
    engine = open_engine(f"sqlite:///{newer}")
    with engine.begin() as connection:
        connection.exec_driver_sql("UPDATE alembic_version SET version_num = '9999'")
    engine.dispose()
    before = {p.name for p in tmp_path.iterdir()}
    assert main(["export", "--db", f"sqlite:///{newer}", "--results", str(tmp_path / "out")]) == 2
    assert "made by a newer facelab (schema 9999" in capsys.readouterr().err
    assert {p.name for p in tmp_path.iterdir()} == before


def test_folders_for_files_and_refused_writes_are_said_in_words(
    kato_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A folder given for an avatar said 'file not found', and one given for a Z matrix
    'was not found'; a write the system refused (--out under /proc) was a traceback."""
    folder = tmp_path / "head.glb"
    folder.mkdir()
    assert main(["avatar", "inspect", str(folder)]) == 2
    assert "head.glb: is a folder, not a file" in capsys.readouterr().err
    protocol = tmp_path / "p.yaml"
    text = kato_path.read_text(encoding="utf-8")
    protocol.write_text(text.replace("{z: standard,", f"{{z: {tmp_path},", 1), encoding="utf-8")
    assert main(["validate", str(protocol)]) == 2
    assert f"{tmp_path} is a folder" in capsys.readouterr().err
    results = tmp_path / "results"
    assert main(["simulate", str(kato_path), "--participants", "2", "--sim-seed", "1",
                 "--results", str(results)]) == 0  # fmt: skip
    capsys.readouterr()
    assert main(["analyze", str(kato_path), str(results), "--out", "/proc/facelab-nope"]) == 2
    err = capsys.readouterr().err
    assert "/proc/facelab-nope: the system refused a file operation" in err, err
    # a write the disk refuses names no file (a full disk): still said, not a traceback
    assert main(["behaviour", "synth", "--duration-s", "5", "--out", "/dev/full", "--force"]) == 2
    err = capsys.readouterr().err
    assert "the system refused a file operation (No space left on device)" in err, err


def test_json_inputs_that_are_broken_or_of_the_wrong_shape_are_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A broken JSON file said the parser's 'Expecting property name enclosed in double
    quotes', a missing one Python's errno text, a key's text value 'could not convert string
    to float', a library of the wrong shape pydantic's 'Field required'."""
    broken = tmp_path / "broken.json"
    broken.write_text("{\n", encoding="utf-8")
    keys = tmp_path / "keys.json"
    keys.write_text('[{"time_s": "x", "joy": 1}]', encoding="utf-8")
    shape = tmp_path / "shape.json"
    shape.write_text('{"units": 3}', encoding="utf-8")
    plan = ["behaviour", "plan", "--text", "こんにちは", "--duration-s", "3", "--seed", "1",
            "--out", str(tmp_path / "plan.json")]  # fmt: skip
    for argv, said in (
        ([*plan, "--emotion-timeline", str(broken)], "broken.json:2: not valid JSON"),
        ([*plan, "--emotion-timeline", str(tmp_path / "none.json")], "none.json: file not found"),
        ([*plan, "--emotion-timeline", str(keys)], 'key 1 is {"time_s": "x", "joy": 1}'),
        ([*plan, "--emotion", "joy=1", "--library", str(shape)], "units: expected a list (got 3)"),
        (["impression", "render", str(broken), "--expression", "e", "--levels", "0.5", "--out",
          str(tmp_path / "clips")], "broken.json:2: not valid JSON (at column 1)"),
    ):  # fmt: skip
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert said in err and "Traceback" not in err and "Errno" not in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.json", "keys.json", "shape.json"]


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "x"])
def test_a_simulated_effect_must_be_rating_points(
    kato_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], value: str
) -> None:
    """--effect standard=nan simulated ratings written as n/a (the analysis then failed on
    them) and power studies of power 0, exit 0."""
    argv = ["simulate", str(kato_path), "--participants", "2", "--sim-seed", "1",
            "--effect", f"standard={value}", "--results", str(tmp_path / "r")]  # fmt: skip
    assert main(argv) == 2
    assert "POINTS a finite number" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("value", ["-1", "2.5", str(2**63)])
def test_seeds_are_checked_before_anything_runs(
    kato_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], value: str
) -> None:
    argv = ["simulate", str(kato_path), "--participants", "1", "--sim-seed", value]
    with pytest.raises(SystemExit) as info:
        main([*argv, "--results", str(tmp_path)])
    assert info.value.code == 2 and "--sim-seed" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (["impression", "render", "m.json", "--levels", "nan"], "--levels: expected a finite"),
        (["impression", "render", "m.json", "--fps", "0"], "--fps: expected a whole number 1..240"),
        (["behaviour", "render", "--lead-s", "-3"], "--lead-s: expected a number >= 0, got -3"),
        (["behaviour", "plan", "--duration-s", "0"], "--duration-s: expected a number > 0"),
        (["power", "--alpha", "1"], "--alpha: expected a number < 1, got 1"),
        (["power", "--icc", "x"], "--icc: expected a number, got 'x'"),
        (["serve", "p.yaml", "--port", "70000"], "--port: expected a whole number 0..65535"),
        (["simulate", "p.yaml", "--participants", "0"], "--participants: expected a whole"),
        (["impression", "fit", "s.csv", "--variance", "1.5"], "--variance: expected a number <= 1"),
    ],
)
def test_numeric_options_are_checked_before_anything_runs(
    argv: list[str], said: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as info:
        main(argv)
    err = capsys.readouterr().err
    assert info.value.code == 2 and said in err and "Traceback" not in err


@pytest.mark.parametrize(
    ("size", "said"),
    [("", "--size '': expected WIDTHxHEIGHT"), ("640x", "expected WIDTHxHEIGHT"),
     ("641x360", "even and >= 64"), ("8000x4000", "expected at most 7680x4320")],
)  # fmt: skip
def test_a_size_given_empty_or_too_large_is_refused_not_ignored(
    kato_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], size: str, said: str
) -> None:
    """`--size ''` once fell back to the protocol's resolution as if the flag were absent."""
    out = tmp_path / "clips"
    assert main(["render", str(kato_path), "--out", str(out), "--size", size]) == 2
    err = capsys.readouterr().err
    assert said in err and "Traceback" not in err and not out.exists()


def test_option_types_accept_what_they_should() -> None:
    from facelab.experiment.cli.common import real, whole

    assert whole(lo=1, hi=240)("240") == 240
    assert real(lo=0, hi=1)("0") == 0.0 and real(lo=0, hi=1)("1") == 1.0
    assert real(above=0, below=1)("0.5") == 0.5 and real()("-1e9") == -1e9
    for parse, value in ((whole(lo=1), "1.5"), (real(above=0), "0"), (real(), "inf")):
        with pytest.raises(argparse.ArgumentTypeError):
            parse(value)


def test_a_missing_optional_dependency_names_the_extra(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import sys

    monkeypatch.setitem(sys.modules, "pygltflib", None)  # import now raises ModuleNotFoundError
    for name in [m for m in sys.modules if m.startswith("facelab.stimuli")]:
        monkeypatch.delitem(sys.modules, name)
    code = main(["avatar", "sample", "--kind", "rpm", "--out", str(tmp_path / "a.glb")])
    err = capsys.readouterr().err
    assert code == 3 and "'pygltflib'" in err and "pip install 'facelab[stimuli]'" in err


def test_words_openjtalk_cannot_speak_and_wrong_expected_vowels_are_refused_before_rendering(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Text that is punctuation, an emoji or a lone っ has no speech to synthesise (the render
    used to fail on OpenJTalk's own message, or draw a mouth that never moves), and
    expected_vowels that are not the vowels OpenJTalk reads were found only after every clip
    was drawn: validate and render refuse both at their lines, and render writes nothing."""
    from tests.protocol_edits import ONE_CONDITION

    text = ONE_CONDITION.replace(
        "      - {id: hai, text: はい, expected_vowels: ai}",
        "      - {id: hai, text: はい, expected_vowels: aiu}\n"
        "      - {id: dot, text: 。}\n      - {id: face, text: 😀}\n      - {id: tsu, text: っ}",
    )
    path = tmp_path / "words.yaml"
    path.write_text(text, encoding="utf-8")
    for command in ("validate", "render"):
        argv = [command, str(path)] + (["--out", str(tmp_path / "clips")] * (command == "render"))
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "invalid protocol (4 problems)" in err, err
        assert ("words.yaml:11: stimulus_sets[0].stimuli[1].expected_vowels: 'aiu', but "
                "OpenJTalk reads 'はい' as 'h a i': give its vowels in order, "
                "'ai'") in err  # fmt: skip
        assert "words.yaml:12: stimulus_sets[0].stimuli[2].text: OpenJTalk reads nothing" in err
        assert "stimuli[3].text: OpenJTalk reads nothing in '😀'" in err
        assert "stimuli[4].text: OpenJTalk reads only a pause or a closure (っ) in 'っ'" in err
        assert "WARNING" not in err and "jpcommon" not in err  # no library text
    assert not (tmp_path / "clips").exists()
    path.write_text(ONE_CONDITION, encoding="utf-8")  # あいうえお run together: valid
    assert main(["validate", str(path)]) == 0
