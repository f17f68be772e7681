"""The task screens in the real PsychoPy window (Xvfb), driven by the scripted participant:
a forced-choice staircase killed mid-session and resumed, and an identification session."""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from facelab.protocol import load_protocol
from facelab.staircase import UpDownStaircase
from tests.task_protocols import SIDE_BY_SIDE, short_task_protocol

pytestmark = [pytest.mark.slow, pytest.mark.display]
EXE = str(Path(sys.executable).with_name("facelab"))


#: method_identify cut to one set of three trials, with the sickness questionnaire after them
IDENTIFY_WITH_SSQ_AFTER = {
    r"    sets: 4": "    sets: 1",
    r"presentations_per_condition: 2": "presentations_per_condition: 1",
    r"      - \{id: sentence.*\n": "",
    r"presentation:\n  language: ja\n": "presentation:\n  language: ja\n  ssq: [after]\n",
}


def _run(path: Path, root: Path, *extra: str) -> subprocess.Popen:
    if not os.environ.get("DISPLAY"):
        pytest.fail("no DISPLAY: run the tests with the README's test command (xvfb-run)")
    cmd = [
        EXE,
        "run",
        str(path),
        "--clips",
        str(root / "clips"),
        "--results",
        str(root / "results"),
        "--participant",
        "P01",
        "--simulate",
        "--windowed",
        "--size",
        "800x500",
        "--screenshots",
        str(root / "shots"),
        *extra,
    ]
    env = {**os.environ, "SDL_AUDIODRIVER": "dummy"}
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _session(root: Path, study: str, suffix: str) -> Path:
    return root / "results" / study / "sub-P01" / "ses-1" / f"sub-P01_ses-1_task-{study}{suffix}"


def _beh_rows(root: Path, study: str) -> list[dict[str, str]]:
    text = _session(root, study, "_beh.tsv").read_text(encoding="utf-8")
    return list(csv.DictReader(text.splitlines(), delimiter="\t"))


def test_staircase_in_the_window_survives_a_kill(tmp_path: Path) -> None:
    path = short_task_protocol(
        "gain_staircase", tmp_path, {r"trials: 50": "trials: 8", r"practice: .*\n": ""}
    )
    proc = _run(path, tmp_path)
    saved = 0
    assert proc.stdout is not None
    while saved < 3:
        line = proc.stdout.readline()
        assert line, proc.stderr.read()[-1500:] if proc.stderr else ""
        saved += line.endswith("(saved)\n")
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    resumed = _run(path, tmp_path, "--resume")
    _, err = resumed.communicate(timeout=600)
    assert resumed.returncode == 0, err[-1500:]
    rows = _beh_rows(tmp_path, "gainstair")
    assert [int(r["trial_index"]) for r in rows] == list(range(1, 9))
    assert {r["screen"] for r in rows} == {"choice_2afc"}
    # the levels shown follow the rule from the logged answers, across the kill
    protocol = load_protocol(path)
    from facelab.staircase import new_staircase

    stair: UpDownStaircase = new_staircase(protocol, "main")
    for r in rows:
        assert r["condition"] == stair.condition
        stair.update(r["correct"] == "1")
    steps = [
        json.loads(x)
        for x in _session(tmp_path, "gainstair", "_staircase.jsonl").read_text().splitlines()
    ]
    # every step is in the file, the one cut off by the kill rebuilt on resume
    assert sorted(s["trial_index"] for s in steps) == list(range(1, 9))
    last = max(steps, key=lambda s: s["trial_index"])
    assert last["next_condition"] == stair.condition
    # what the scripted participant pressed is what was logged (interval 1 or 2)
    actions = [
        json.loads(x)
        for x in _session(tmp_path, "gainstair", "_actions.jsonl").read_text().splitlines()
    ]
    pressed = {a["trial_index"]: a["value"] for a in actions if a["trial_index"]}
    for r in rows:
        chose_comparison = pressed[int(r["trial_index"])] == int(r["position"])
        assert r["response"] == (r["condition"] if chose_comparison else "g100")
    assert (tmp_path / "shots" / "choice_2afc_screen.png").exists()


def test_identification_in_the_window(tmp_path: Path) -> None:
    """Identification answered by number keys, then the sickness questionnaire after the last
    trial (issue 51.2): its 16 symptoms answered with the keys too, each logged with the
    value pressed."""
    path = short_task_protocol("method_identify", tmp_path, IDENTIFY_WITH_SSQ_AFTER)
    proc = _run(path, tmp_path)
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err[-1500:]
    rows = _beh_rows(tmp_path, "methodid")
    actions = [
        json.loads(x)
        for x in _session(tmp_path, "methodid", "_actions.jsonl").read_text().splitlines()
    ]
    sickness = [r for r in rows if r["screen"] == "ssq"]
    rows = [r for r in rows if r["screen"] != "ssq"]
    assert [r["response"] for r in rows] == [a["value"] for a in actions if a["trial_index"]]
    pressed = {a["item"]: a["value"] for a in actions if a["item"].startswith("ssq_")}
    assert len(sickness) == 16 == len(pressed)
    assert {r["item"]: int(r["response"]) for r in sickness} == pressed
    assert {r["condition"] for r in sickness} == {"after"}
    assert (tmp_path / "shots" / "ssq_screen.png").exists()
    answers = {
        "baseline": "visemes",
        "standard": "vowel_standard",
        "emphasized": "vowel_emphasized",
    }
    assert all(r["correct"] == str(int(answers[r["condition"]] == r["response"])) for r in rows)
    assert (tmp_path / "shots" / "identify_screen.png").exists()


def test_side_by_side_choice_in_the_window(tmp_path: Path) -> None:
    """Two silent clips at once, left and right: both drawn (each half of the screenshot
    shows a face), a playback record per clip, the side of the comparison logged."""
    import numpy as np
    from PIL import Image

    name, edits = SIDE_BY_SIDE
    path = short_task_protocol(name, tmp_path, edits)
    proc = _run(path, tmp_path)
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err[-1500:]
    study = "horii_impression_side"
    rows = _beh_rows(tmp_path, study)
    assert len(rows) == 2 and {r["position"] for r in rows} == {"1", "2"}  # both sides
    actions = [
        json.loads(x) for x in _session(tmp_path, study, "_actions.jsonl").read_text().splitlines()
    ]
    pressed = {a["trial_index"]: a["value"] for a in actions if a["trial_index"]}
    for r in rows:
        chose_comparison = pressed[int(r["trial_index"])] == int(r["position"])
        assert r["response"] == ("q15" if chose_comparison else "q0")
        assert r["clip_onset"] != ""
    playback = [
        json.loads(x) for x in _session(tmp_path, study, "_playback.jsonl").read_text().splitlines()
    ]
    assert len(playback) == 4  # one record per clip, two clips per trial
    for r in rows:
        mine = [p for p in playback if p["trial_index"] == int(r["trial_index"])]
        left = "q15" if r["position"] == "1" else "q0"
        assert [p["clip"].rsplit("__", 1)[1] for p in mine] == [
            left,
            "q0" if left == "q15" else "q15",
        ]
        assert mine[0]["onset"] == mine[1]["onset"]  # started on the same flip
        assert all(p["frames_expected"] > 0 for p in mine)
    shot = np.asarray(
        Image.open(tmp_path / "shots" / "clip_pair_mid_playback.png").convert("L"), float
    )
    h, w = shot.shape
    for half in (shot[h // 4 : 3 * h // 4, : w // 2], shot[h // 4 : 3 * h // 4, w // 2 :]):
        assert half.std() > 10  # a face on each side, not a blank or a black square
    assert (tmp_path / "shots" / "choice_2afc_screen.png").exists()


def test_typed_answers_in_the_window(tmp_path: Path) -> None:
    """Typed sentences (issue 52.2): the scripted participant types each answer into the
    window's field with real X key events (Japanese characters, one every 0.15 s, then
    Return); every logged response is the text typed, scored, and the Brand-Kollmeier
    staircase moved by those scores."""
    from tests.test_typed_answers import SHORT

    path = short_task_protocol("kato2021_srt_sentences", tmp_path, SHORT)
    proc = _run(path, tmp_path)
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err[-1500:]
    study = "kato2021_srt_sentences"
    rows = _beh_rows(tmp_path, study)
    actions = [json.loads(x) for x in _session(tmp_path, study, "_actions.jsonl").read_text(
        encoding="utf-8").splitlines()]  # fmt: skip
    typed = {a["trial_index"]: a["value"] for a in actions if a["trial_index"] is not None}
    assert len(rows) == 4 == len(typed)
    for r in rows:
        shown = "" if r["response"] == "n/a" else r["response"]
        assert shown == typed[int(r["trial_index"])], (r, typed)
        assert r["screen"] == "typed" and 0.0 <= float(r["score"]) <= 1.0
    assert any(re.search(r"[\u3040-\u30ff\u4e00-\u9fff]", v) for v in typed.values())
    steps = [json.loads(x) for x in _session(tmp_path, study, "_staircase.jsonl").read_text(
        encoding="utf-8").splitlines()]  # fmt: skip
    assert [s["score"] for s in steps] == [float(r["score"]) for r in rows]
    assert (tmp_path / "shots" / "typed_screen.png").exists()


def test_matrix_answers_in_the_window(tmp_path: Path) -> None:
    """A word matrix (issue 52.2) in the lab window: the scripted participant clicks a word
    in each column and then Confirm with real X pointer events; every logged response is
    the words clicked, scored word by word, and the staircase moved by those scores."""
    from tests.test_word_matrix import SHORT

    path = short_task_protocol("kato2021_srt_matrix", tmp_path, SHORT)
    proc = _run(path, tmp_path)
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err[-1500:]
    study = "kato2021_srt_matrix"
    rows = _beh_rows(tmp_path, study)
    actions = [json.loads(x) for x in _session(tmp_path, study, "_actions.jsonl").read_text(
        encoding="utf-8").splitlines()]  # fmt: skip
    clicked = {a["trial_index"]: a["value"] for a in actions if a["trial_index"] is not None}
    protocol = load_protocol(path)
    task = protocol.tasks[0]
    said = {st.id: task.words_said(st) for st in protocol.stimulus_sets[0].stimuli}
    assert len(rows) == 4 == len(clicked)
    for r in rows:
        assert r["response"] == clicked[int(r["trial_index"])] and r["screen"] == "matrix"
        picked = r["response"].split(" ")
        right = sum(a == b for a, b in zip(picked, said[r["stimulus"]], strict=True))
        assert float(r["score"]) == right / 5 and int(r["correct"]) == int(right == 5)
    steps = [json.loads(x) for x in _session(tmp_path, study, "_staircase.jsonl").read_text(
        encoding="utf-8").splitlines()]  # fmt: skip
    assert [s["score"] for s in steps] == [float(r["score"]) for r in rows]
    assert (tmp_path / "shots" / "matrix_screen.png").exists()


def test_typed_kana_keep_their_keys_while_xdotool_types(tmp_path: Path) -> None:
    """The scripted typist gives each kana/kanji a keycode of its own before xdotool types:
    the keyboard map must not change while the keys go out (xdotool's one scratch keycode,
    bound and unbound per character, lost a character when the window read its events late:
    止まった logged as 止った in a loaded CI run)."""
    import time

    if not os.environ.get("DISPLAY"):
        pytest.fail("this test needs an X display (the suite runs under xvfb-run)")
    # a client holding the display, as the window does (the last client leaving resets the
    # X server, keyboard map and all)
    holder = subprocess.Popen(["xdotool", "sleep", "60"])
    time.sleep(0.3)
    try:
        _type_with_keys_mapped(tmp_path)
    finally:
        holder.kill()


def _type_with_keys_mapped(tmp_path: Path) -> None:
    import time

    from facelab.experiment.scripted import ScriptedParticipant

    typist = ScriptedParticipant(
        model=None,  # type: ignore[arg-type]  # no ratings here
        window_origin=(0, 0),
        window_size=(200, 200),
        actions=tmp_path / "actions.jsonl",
    )
    text = "赤い 車 止まった"

    def keymap() -> str:
        return subprocess.run(["xmodmap", "-pke"], capture_output=True, text=True).stdout

    typist._map_characters(text)
    before = keymap()
    for char in set(text) - {" "}:
        assert f"U{ord(char):04X}" in before, char
    proc = subprocess.Popen(["xdotool", "type", "--delay", "120", "--", text])
    seen = []
    while proc.poll() is None:
        seen.append(keymap())
        time.sleep(0.05)
    assert len(seen) >= 5 and all(m == before for m in seen)
    # a second text reuses the keycodes least recently given, never those it needs itself
    typist._map_characters("止まれ")
    assert {typist.keycodes[c] for c in "止ま"} == {
        int(line.split()[1]) for line in keymap().splitlines()
        if "U6B62" in line or "U307E" in line
    }  # fmt: skip


def test_quitting_shows_the_sickness_questionnaire_before_the_window_closes(
    tmp_path: Path,
) -> None:
    """A participant who stops because they feel sick is the one whose SSQ matters: with
    ``ssq: [after]``, Escape and y during the trials first show the questionnaire's 16
    symptoms (answered by the scripted participant), then the session ends (exit 4) and
    stays resumable."""
    import shutil
    import time

    path = short_task_protocol("method_identify", tmp_path, IDENTIFY_WITH_SSQ_AFTER)
    proc = _run(path, tmp_path)
    assert proc.stdout is not None
    while True:
        line = proc.stdout.readline()
        assert line, proc.stderr.read()[-1500:] if proc.stderr else ""
        if line.endswith("(saved)\n"):
            break
    xdotool = shutil.which("xdotool")
    assert xdotool
    subprocess.run([xdotool, "key", "Escape"], check=True)
    time.sleep(1.0)
    subprocess.run([xdotool, "key", "y"], check=True)
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 4, err[-1500:]
    assert "sickness questionnaire (after) is shown" in out
    rows = _beh_rows(tmp_path, "methodid")
    sickness = [r for r in rows if r["screen"] == "ssq"]
    assert len(sickness) == 16 and {r["condition"] for r in sickness} == {"after"}
    assert 1 <= sum(r["screen"] == "identify" for r in rows) < 3  # quit before the last trial
