"""Protocol loading: the paper's protocol, round trips, the schema file, and broken files."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import pytest
import yaml

from facelab.errors import ProtocolError
from facelab.experiment.cli import main
from facelab.protocol import Protocol, load_protocol, schema_json_text
from facelab.protocol_yaml import read_yaml
from tests.conftest import ROOT
from tests.mutation import mutated


def test_kato_protocol_matches_the_paper(kato_path: Path) -> None:
    p = load_protocol(kato_path)
    assert [c.id for c in p.conditions] == ["baseline", "standard", "emphasized"]
    assert [c.method for c in p.conditions] == ["viseme_baseline", "vowel_blend", "vowel_blend"]
    assert [c.params.get("z") for c in p.conditions] == [None, "standard", "emphasized"]
    vowels = p.stimulus_set("vowels").stimuli
    assert len(vowels) == 1 and vowels[0].expected_vowels == "aiueo"
    assert vowels[0].vowel_isolation == ["standard", "emphasized"]
    assert "TTS" in vowels[0].note  # the protocol says the vowels are TTS for now
    blocks = {b.id: b for b in p.blocks}
    assert (blocks["vowels"].sets, blocks["vowels"].presentations_per_condition) == (2, 2)
    assert (blocks["sentences"].sets, blocks["sentences"].presentations_per_condition) == (2, 1)
    assert [i.id for i in p.items] == ["naturalness", "mouth_shape"]
    for item in p.items:
        assert {"ja", "en"} <= set(item.question) and item.range == [0.0, 100.0]
        assert item.marker_start == "hidden" and item.confirm
    assert p.study.participants_planned == 8
    passage = p.stimulus_set("sentences").stimuli[0].text
    assert passage is not None and 100 <= len(passage) <= 200  # ~20 s of speech


def test_model_round_trip(kato_path: Path, tmp_path: Path) -> None:
    p = load_protocol(kato_path)
    assert Protocol.model_validate(p.model_dump()) == p
    # ... and through a YAML file written from the model
    out = tmp_path / "copy.yaml"
    out.write_text(yaml.safe_dump(p.model_dump(), allow_unicode=True), encoding="utf-8")
    assert load_protocol(out) == p


def test_committed_schema_is_current_and_validates_the_protocol(kato_text: str) -> None:
    committed = (ROOT / "protocols" / "schema" / "protocol.schema.json").read_text(encoding="utf-8")
    assert committed == schema_json_text(), (
        "run: facelab schema --out protocols/schema/protocol.schema.json"
    )
    schema = json.loads(committed)
    jsonschema.validate(yaml.safe_load(kato_text), schema)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({**yaml.safe_load(kato_text), "colour": "red"}, schema)


def _line(text: str, needle: str) -> int:
    """Line number of the first line containing ``needle``; a needle ending in a newline
    must equal a whole line, and its last occurrence counts (for duplicates)."""
    lines = text.splitlines()
    if needle.endswith("\n"):
        hits = [n for n, line in enumerate(lines, start=1) if line == needle[:-1]]
        hits = hits[-1:]
    else:
        hits = [n for n, line in enumerate(lines, start=1) if needle in line][:1]
    assert hits, f"{needle!r} not in text"
    return hits[0]


# Each case: (name, edit of the paper's protocol, text on the line to blame, words in the message)
BROKEN: list[tuple[str, tuple[str, str], str, list[str]]] = [
    (
        "unknown top-level key",
        ("seed: 20210527", "seed: 20210527\ncolour: red"),
        "colour: red",
        ["colour", "unknown key", "allowed keys"],
    ),
    (
        "unknown nested key (typo)",
        (
            "    marker_start: hidden\n    confirm: true\n  - id: mouth_shape",
            "    marker_start: hidden\n    confirm: true\n    anchor_left: x\n  - id: mouth_shape",
        ),
        "anchor_left: x",
        ["items[0].anchor_left", "unknown key", "left_anchor"],
    ),
    (
        "wrong type",
        (
            "    sets: 2\n    presentations_per_condition: 2",
            "    sets: two\n    presentations_per_condition: 2",
        ),
        "sets: two",
        ["blocks[0].sets", "whole number", "'two'"],
    ),
    (
        "missing stimulus file",
        ("        text: あ。い。う。え。お。", "        audio: vowels/missing.wav"),
        "audio: vowels/missing.wav",
        ["audio file not found", "missing.wav"],
    ),
    (
        "duplicate condition id",
        ("  - id: emphasized", "  - id: standard"),
        "  - id: standard\n",
        ["duplicate condition id 'standard'"],
    ),
    (
        "empty block",
        ("    presentations_per_condition: 1     #", "    presentations_per_condition: 0     #"),
        "presentations_per_condition: 0",
        ["blocks[1].presentations_per_condition", "greater than or equal to 1"],
    ),
    (
        "block with no conditions",
        (
            "    order: random_within_set\n    break_after: false",
            "    order: random_within_set\n    conditions: []\n    break_after: false",
        ),
        "conditions: []",
        ["blocks[1].conditions", "no trials"],
    ),
    (
        "unknown method",
        ("method: viseme_baseline", "method: viseme_basline"),
        "method: viseme_basline",
        ["unknown method 'viseme_basline'", "vowel_blend"],
    ),
    (
        "unknown method parameter",
        ("params: {z: standard, gain: 1.0}", "params: {z: standard, gian: 1.0}"),
        "gian: 1.0",
        ["conditions[1].params.gian", "unknown parameter", "gain"],
    ),
    (
        "method parameter out of range",
        ("params: {z: emphasized, gain: 1.0}", "params: {z: emphasized, gain: -1.0}"),
        "gain: -1.0",
        ["conditions[2].params.gain", "greater than 0"],
    ),
    (
        "unknown Z matrix",
        ("params: {z: emphasized, gain: 1.0}", "params: {z: shouty, gain: 1.0}"),
        "z: shouty",
        ["conditions[2].params.z", "standard, emphasized"],
    ),
    (
        "VAS range out of 0..100",
        (
            "    range: [0, 100]\n    marker_start: hidden\n    confirm: true\n  - id: mouth_shape",
            "    range: [0, 150]\n    marker_start: hidden\n    confirm: true\n  - id: mouth_shape",
        ),
        "range: [0, 150]",
        ["items[0].range", "0 <= left < right <= 100"],
    ),
    (
        "bad YAML syntax",
        (
            "  camera: {distance_m: 0.65, fov_deg: 30, height_m: 0.0}",
            "  camera: {distance_m: 0.65, fov_deg: 30, height_m: 0.0\n  pad_s: 0.3",
        ),
        "pad_s: 0.3",
        ["not valid YAML"],
    ),
    (
        "unknown stimulus set",
        ("    stimulus_set: sentences\n    sets: 2", "    stimulus_set: sentence\n    sets: 2"),
        "    stimulus_set: sentence\n",
        ["unknown stimulus set 'sentence'", "vowels, sentences"],
    ),
    (
        "missing required key",
        ("  participants_planned: 8\n", "\n"),
        "study:",
        ["study.participants_planned", "required key is missing"],
    ),
    (
        "duplicate YAML key",
        ("  width: 1280\n", "  width: 1280\n  width: 1920\n"),
        "width: 1920",
        ["rendering.width", "duplicate key"],
    ),
    (
        "text and audio both",
        ("        expected_vowels: aiueo", "        audio: x.wav\n        expected_vowels: aiueo"),
        "- id: aiueo",
        ["exactly one of 'text'"],
    ),
    (
        "language missing",
        ("  language: ja\n  items_layout", "  language: fr\n  items_layout"),
        "label: {ja: LipSync",
        ["conditions[0].label", "no 'fr' text"],
    ),
    (
        "tab indentation",
        ("  participants_planned: 8\n", "\tparticipants_planned: 8\n"),
        "participants_planned: 8",
        ["a tab indents this line; YAML indents with spaces only"],
    ),
    (
        "empty list",
        ("background: [0.5, 0.5, 0.5]", "background: [0.5, 0.5]"),
        "background: [0.5, 0.5]",
        ["rendering.background", "expected at least 3 entries"],
    ),
    (
        "empty title",
        ("  title: Vowel-driven blendshape", '  title: ""\n  x_title: Vowel-driven blendshape'),
        'title: ""',
        ["study.title", "expected a text (not empty)"],
    ),
    (
        "simulated effect not a number",
        ("effects: {baseline: 0, standard: 15,", "effects: {baseline: 0, standard: .nan,"),
        "effects: {baseline: 0, standard: .nan,",
        ["simulation.effects.standard", "expected a number (got .nan)"],
    ),
    (
        "simulated effect infinite",
        ("effects: {baseline: 0, standard: 15,", "effects: {baseline: 0, standard: .inf,"),
        "effects: {baseline: 0, standard: .inf,",
        ["simulation.effects.standard", "finite number"],
    ),
    (
        "effect keyed by no id",
        ("emphasized: 6}", '"Emphasized!": 6}'),
        '"Emphasized!": 6}',
        ["'Emphasized!' is not a valid id", "name conditions"],
    ),
    (
        "bad enum value",
        ("    order: random_within_set\n    break_after", "    order: shuffled\n    break_after"),
        "order: shuffled",
        ["blocks[1].order", "random_within_set", "'shuffled'"],
    ),
]


@pytest.mark.parametrize(
    ("edit", "blame", "words"), [c[1:] for c in BROKEN], ids=[c[0] for c in BROKEN]
)
def test_broken_protocol_exits_2_naming_problem_and_line(
    tmp_path: Path,
    kato_text: str,
    capsys: pytest.CaptureFixture[str],
    edit: tuple[str, str],
    blame: str,
    words: list[str],
) -> None:
    old, new = edit
    assert old in kato_text, "the test's edit no longer matches the protocol"
    text = kato_text.replace(old, new, 1)
    path = tmp_path / "broken.yaml"
    path.write_text(text, encoding="utf-8")
    code = main(["validate", str(path)])
    err = capsys.readouterr().err
    assert code == 2
    assert "Traceback" not in err
    for word in words:
        assert word in err, f"{word!r} not in: {err}"
    assert f"{path}:{_line(text, blame)}:" in err, err


def test_all_problems_are_reported_at_once(tmp_path: Path, kato_text: str) -> None:
    text = kato_text.replace("  fps: 30", "  fps: thirty").replace(
        "    sets: 2\n", "    sets: 0\n", 1
    )
    path = tmp_path / "two.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ProtocolError) as info:
        load_protocol(path)
    assert [i.dotted() for i in info.value.issues] == ["blocks[0].sets", "rendering.fps"]
    assert all(i.line for i in info.value.issues)


def test_numbers_yaml_reads_as_text_get_a_hint(tmp_path: Path, kato_text: str) -> None:
    # YAML 1.1 reads 1e9 (no decimal point) and anything quoted as strings
    text = kato_text.replace("  pad_s: 0.3", "  pad_s: 3e-1").replace("  fps: 30", "  fps: '30'")
    path = tmp_path / "text_numbers.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ProtocolError) as info:
        load_protocol(path)
    messages = {i.dotted(): i.message for i in info.value.issues}
    assert (
        "write it with a decimal point and a signed exponent (3.0e-1)"
        in messages["rendering.pad_s"]
    )
    assert "a number in quotes is text: remove the quotes" in messages["rendering.fps"]


def test_nan_is_named_alike_in_sections_and_method_parameters(
    tmp_path: Path, kato_text: str
) -> None:
    # .nan compares false with every bound; the message must not read as a range problem
    text = kato_text.replace("  pad_s: 0.3", "  pad_s: .nan").replace("gain: 1.0}", "gain: .nan}")
    path = tmp_path / "nan.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ProtocolError) as info:
        load_protocol(path)
    messages = {i.dotted(): i.message for i in info.value.issues}
    assert messages["rendering.pad_s"] == "expected a number (got .nan)"
    assert messages["conditions[1].params.gain"] == "expected a number (got .nan)"


def test_missing_file_and_non_mapping(tmp_path: Path) -> None:
    with pytest.raises(ProtocolError, match="file not found"):
        load_protocol(tmp_path / "nope.yaml")
    bad = tmp_path / "list.yaml"
    bad.write_text("- a\n- b\n", encoding="utf-8")
    with pytest.raises(ProtocolError, match="expected a YAML mapping"):
        load_protocol(bad)


def test_recorded_audio_stimulus_is_accepted(tmp_path: Path, kato_text: str) -> None:
    (tmp_path / "vowels").mkdir()
    (tmp_path / "vowels" / "aiueo.wav").write_bytes(b"RIFF")  # existence is what validate checks
    path = tmp_path / "rec.yaml"
    path.write_text(
        kato_text.replace("        text: あ。い。う。え。お。", "        audio: vowels/aiueo.wav"),
        encoding="utf-8",
    )
    stim = load_protocol(path).stimulus_set("vowels").stimuli[0]
    assert stim.audio == "vowels/aiueo.wav" and stim.text is None


# --------------------------------------------------------------- files that could hang or crash

BOMB = "\n".join(
    [
        'a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]',
        *(
            f"{chr(98 + i)}: &{chr(98 + i)} [" + ",".join([f"*{chr(97 + i)}"] * 9) + "]"
            for i in range(8)
        ),
    ]
)


def test_alias_bomb_is_refused_before_expanding(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "bomb.yaml"
    path.write_text(BOMB + "\n", encoding="utf-8")  # 9**9 = 387 million strings expanded
    assert main(["validate", str(path)]) == 2
    err = capsys.readouterr().err
    assert "alias bomb" in err and "Traceback" not in err
    many = "x: &x 1\n" + "".join(f"k{i}: *x\n" for i in range(1_200))
    path.write_text(many, encoding="utf-8")
    assert main(["validate", str(path)]) == 2
    assert "more than 1000 YAML aliases" in capsys.readouterr().err


def test_deep_nesting_is_refused_not_a_recursion_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "deep.yaml"
    # 100 levels: facelab's own limit; 5,000: libyaml (PyYAML >= 6.0.4) stops at 1,000 first
    for levels in (100, 5000):
        path.write_text("a: " + "[" * levels + "]" * levels + "\n", encoding="utf-8")
        assert main(["validate", str(path)]) == 2
        err = capsys.readouterr().err
        assert f"{path}:1: (document): nested more than 64 levels" in err
        assert "RecursionError" not in err and "Traceback" not in err


def test_aliases_within_limits_still_work(tmp_path: Path, kato_text: str) -> None:
    text = kato_text.replace("    range: [0, 100]\n", "    range: &scale [0, 100]\n", 1)
    text = text.replace("    range: [0, 100]\n", "    range: *scale\n", 1)
    path = tmp_path / "alias.yaml"
    path.write_text(text, encoding="utf-8")
    assert [i.range for i in load_protocol(path).items] == [[0.0, 100.0], [0.0, 100.0]]


def test_duplicate_keys_types_and_cross_checks_in_one_run(tmp_path: Path, kato_text: str) -> None:
    """A duplicate key, a type error and a broken reference are all reported together."""
    text = kato_text.replace("  width: 1280\n", "  width: 1280\n  width: 1920\n")
    text = text.replace("  fps: 30", "  fps: thirty")
    text = text.replace(
        "    stimulus_set: sentences\n    sets: 2", "    stimulus_set: sentence\n    sets: 2"
    )
    path = tmp_path / "three.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ProtocolError) as info:
        load_protocol(path)
    found = {i.dotted(): i.message for i in info.value.issues}
    assert "duplicate key" in found["rendering.width"]
    assert "whole number" in found["rendering.fps"]
    assert "unknown stimulus set 'sentence'" in found["blocks[1].stimulus_set"]


@pytest.mark.parametrize("bad_id", ["x__y", "a" * 65, "_x", "9a"])
def test_ids_that_would_make_clip_names_collide_are_refused(
    tmp_path: Path, kato_text: str, bad_id: str
) -> None:
    """Clip files are <set>__<stimulus>__<condition>: with '__' inside ids, set 'short' +
    stimulus 'x__y' and set 'short__x' + stimulus 'y' would share one file."""
    path = tmp_path / "ids.yaml"
    path.write_text(kato_text.replace("  - id: passage", f"  - id: {bad_id}", 1), encoding="utf-8")
    with pytest.raises(ProtocolError) as info:
        load_protocol(path)
    (issue,) = [i for i in info.value.issues if i.dotted().endswith(".id")]
    assert issue.line and ("no '__'" in issue.message or "64 characters" in issue.message)


@pytest.mark.slow
def test_a_large_protocol_validates(tmp_path: Path, kato_text: str) -> None:
    """150,000 stimuli (7.8 MB of YAML): answered, not hung (timing: see the closing note)."""
    stims = "".join(f"      - id: s{i}\n        text: こんにちは。\n" for i in range(150_000))
    marker = "  - id: sentences\n"
    head, tail = kato_text.split(marker, 1)
    head2, stimuli = tail.split("    stimuli:\n", 1)
    path = tmp_path / "big.yaml"
    path.write_text(head + marker + head2 + "    stimuli:\n" + stims + stimuli, encoding="utf-8")
    protocol = load_protocol(path)
    assert len(protocol.stimulus_set("sentences").stimuli) == 150_001


SHIPPED_YAML = sorted([*ROOT.glob("protocols/*.yaml"), *ROOT.glob("stimuli/data/*.yaml")])


@pytest.mark.parametrize("path", SHIPPED_YAML, ids=lambda p: p.name)
def test_shipped_yaml_reads_the_same_with_pure_python_pyyaml(path: Path) -> None:
    """facelab reads YAML with libyaml when PyYAML has it; libyaml accepts plain scalars (a
    question ending in '?' inside {…}) that PyYAML's own parser - and PyYAML without libyaml -
    refuses. The files users copy out must read the same everywhere."""
    text = path.read_text(encoding="utf-8")
    assert yaml.load(text, Loader=yaml.SafeLoader) == read_yaml(text)[1]


#: what the Protocol's lookup methods read
_LOOKUPS = {
    "condition": {"conditions"},
    "stimulus_set": {"stimulus_sets"},
    "task": {"tasks"},
    "block_task": {"tasks"},
    "block_conditions": {"tasks", "conditions"},
}


def _sections_read() -> dict[str, tuple[set[str], set[str]]]:
    """check function -> (sections it declares, sections it reads), from the source of
    core/protocol_checks.py; helper functions given ``protocol`` count for their callers."""
    import ast

    tree = ast.parse((ROOT / "core" / "protocol_checks.py").read_text(encoding="utf-8"))
    fields = set(Protocol.model_fields)
    funcs = {f.name: f for f in tree.body if isinstance(f, ast.FunctionDef)}

    def direct(fn: ast.FunctionDef) -> tuple[set[str], set[str]]:
        read: set[str] = set()
        calls: set[str] = set()
        for node in ast.walk(fn):
            if (
                isinstance(node, ast.Attribute)
                and isinstance(node.value, ast.Name)
                and node.value.id == "protocol"
            ):
                read |= {node.attr} & fields
                read |= _LOOKUPS.get(node.attr, set())
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Name)
                and node.func.id in funcs
                and any(isinstance(a, ast.Name) and a.id == "protocol" for a in node.args)
            ):
                calls.add(node.func.id)
        return read, calls

    def reads(name: str, seen: frozenset[str] = frozenset()) -> set[str]:
        read, calls = direct(funcs[name])
        for c in calls - seen - {name}:
            read |= reads(c, seen | {name})
        return read

    out = {}
    for name, fn in funcs.items():
        for dec in fn.decorator_list:
            if isinstance(dec, ast.Call) and getattr(dec.func, "id", "") == "_check":
                declared = {a.value for a in dec.args if isinstance(a, ast.Constant)}
                out[name] = (declared, reads(name))
    return out


def test_every_cross_check_declares_the_sections_it_reads() -> None:
    """A check runs on a partial protocol when other sections failed to validate; reading an
    undeclared section there was an AttributeError traceback (found by fuzzing the shipped
    protocols: a broken 'stimulus_sets' with an identify task)."""
    checks = _sections_read()
    assert len(checks) >= 10
    undeclared = {name: sorted(r - d) for name, (d, r) in checks.items() if r - d}
    assert not undeclared


def test_an_identify_task_with_broken_stimulus_sets_is_reported_not_a_traceback(
    tmp_path: Path,
) -> None:
    text = (ROOT / "protocols" / "method_identify.yaml").read_text(encoding="utf-8")
    data = yaml.safe_load(text)
    data["stimulus_sets"] = 7
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(data, allow_unicode=True), encoding="utf-8")
    with pytest.raises(ProtocolError, match="stimulus_sets"):
        load_protocol(path)


@pytest.mark.slow
def test_mutated_shipped_protocols_load_or_are_refused(tmp_path: Path) -> None:
    """300 random mutations of the shipped protocols (deleted keys and list entries, values
    of other types): each one loads - and designs a participant and plans its clips - or
    raises ProtocolError; nothing else (this found the undeclared sections of two checks)."""
    import random
    import shutil

    from facelab.design import build_trials
    from facelab.stimuli.render.clipspec import plan

    rng = random.Random(20261124)
    sources = sorted(ROOT.glob("protocols/*.yaml"))
    values = [None, 0, -1, 1e9, "", "x", [], {}, [1, "a"], {"a": 1}, True, 0.5, "a__b", 10**30]

    work = tmp_path / "protocols"
    shutil.copytree(ROOT / "protocols", work)
    outcomes = {"loaded": 0, "refused": 0}
    for _ in range(300):
        source = rng.choice(sources)
        data = yaml.load(source.read_text(encoding="utf-8"), Loader=yaml.SafeLoader)
        data = mutated(data, rng=rng, values=values)
        path = work / source.name
        path.write_text(yaml.safe_dump(data, allow_unicode=True), encoding="utf-8")
        try:
            protocol = load_protocol(path)
        except ProtocolError:
            outcomes["refused"] += 1
            continue
        finally:
            shutil.copy(source, path)
        outcomes["loaded"] += 1
        build_trials(protocol, participant="P01")
        plan(protocol)
    assert min(outcomes.values()) >= 20, outcomes  # both paths exercised


def test_constrained_strings_are_explained_in_words_not_by_their_pattern(tmp_path: Path) -> None:
    """A wrong expected_vowels or language code names what is expected, not the regular
    expression pydantic matched it against."""
    from tests.protocol_edits import ONE_CONDITION, protocol_problems

    text = ONE_CONDITION.replace("expected_vowels: aiueo}", "expected_vowels: AIUEO}")
    text = text.replace("language: ja", "language: Japanese")
    problems = protocol_problems(text, tmp_path)
    assert ("stimulus_sets[0].stimuli[0].expected_vowels: 'AIUEO': expected the vowels "
            "spoken, in order, as lower-case a i u e o (e.g. aiueo)") in problems  # fmt: skip
    assert "presentation.language: 'Japanese': expected a language code such as ja" in problems
    assert "pattern" not in problems and "^" not in problems


def test_odd_width_and_height_are_each_named(tmp_path: Path) -> None:
    from tests.protocol_edits import ONE_CONDITION, protocol_problems

    odd = ONE_CONDITION.replace("width: 160, height: 90", "width: 161, height: 65")
    problems = protocol_problems(odd, tmp_path)
    assert "rendering.width: expected an even number (H.264 needs even sizes), got 161" in problems
    assert "rendering.height: expected an even number (H.264 needs even sizes), got 65" in problems


def test_file_checks_add_every_problem_at_a_key_not_reported_yet(tmp_path: Path) -> None:
    """``load_protocol(file_checks=...)``: the checks' problems join the protocol's own in one
    report - all of them, several at one key included (three missing track files of one
    condition), but none at a key already reported; checks that fail after problems were
    found add one line that the files were not all read (no traceback), and fail as before
    when nothing else was found."""
    from facelab.errors import Issue, ProtocolError
    from facelab.protocol import load_protocol
    from facelab.resources import protocol_path

    text = protocol_path("kato2021").read_text(encoding="utf-8")
    good, bad = tmp_path / "good.yaml", tmp_path / "bad.yaml"
    good.write_text(text, encoding="utf-8")
    bad.write_text(text.replace("params: {z: standard, gain: 1.0}",
                                "params: {z: nothere.csv, gain: 1.0}", 1), encoding="utf-8")

    def checks(protocol, base):
        return [Issue(("conditions", 1, "params", "z"), "said again"),
                *(Issue(("conditions", 0, "params"), f"track {k} missing") for k in range(3))]

    for path in (good, bad):
        with pytest.raises(ProtocolError) as caught:
            load_protocol(path, file_checks=checks)
        said = [(i.path, i.message) for i in caught.value.issues]
        assert [m for p, m in said if p == ("conditions", 0, "params")] == [
            f"track {k} missing" for k in range(3)]
        z = [m for p, m in said if p == ("conditions", 1, "params", "z")]
        assert z == (["said again"] if path == good else [z[0]]) and len(z) == 1
        assert all(i.line for i in caught.value.issues if i.path)

    def broken(protocol, base):
        raise KeyError("a bug")

    with pytest.raises(ProtocolError) as caught:
        load_protocol(bad, file_checks=broken)
    assert "were not all read" in caught.value.issues[-1].message
    with pytest.raises(KeyError):
        load_protocol(good, file_checks=broken)
