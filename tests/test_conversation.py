"""A live conversation as a phase of a protocol's timeline (issue 53.4).

* The protocol key ``presentation.conversation`` is checked (condition, items, the block id
  it reserves); the timeline puts the conversation and the questions about the partner before
  or after the trials; resume shows what is missing (the partner's intro only while a
  question about the partner is to come); the lab window refuses it without a sound output.
* Simulated sessions log it on its own trial; the analysis keeps it out of the trial
  analyses, tabulates it (conversation.csv, conversation_summary.csv) and refuses an edited
  row.
* Online (a rendered short study): the routes refuse an unknown token, a wrong experimenter
  secret and a page of another origin; a talker's turn over its socket reaches the
  participant's viewer socket and is recorded in the participant's folder; the talker ends
  the conversation. In headless Chromium a simulated participant converses with the server
  as the talker (a file), is ended by the talker, and rates the partner: every answer
  stored once, the turn recorded with the frames the participant's page drew.
"""

from __future__ import annotations

import csv
import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
from sqlalchemy import select
from sqlalchemy.orm import Session

from facelab.design import build_trials
from facelab.experiment.cli import main
from facelab.experiment.online.db import Action, Participant, Response
from facelab.experiment.timeline import (
    ConversationScreen,
    TextScreen,
    VasScreen,
    compile_timeline,
    remaining,
)
from facelab.protocol import load_protocol
from facelab.resources import package_file
from facelab.stimuli.speech.tts import synthesize
from tests.protocol_edits import kato_short, kato_vowels_only, protocol_problems

KATO = Path(package_file("facelab.protocols", "kato2021.yaml"))
PRACTICE = "  practice: {stimulus_set: sentences, stimulus: passage, condition: standard}\n"
SECRET = "experimenter-secret-123"


def with_conversation(text: str, spec: str) -> str:
    """``text`` (kato2021) with ``presentation.conversation: spec``."""
    anchor = "  items_layout: sequential\n"
    assert anchor in text
    return text.replace(anchor, anchor + f"  conversation: {spec}\n", 1)


def kato_text() -> str:
    return KATO.read_text(encoding="utf-8")


# --------------------------------------------------------------------------- protocol, timeline


def test_the_conversation_key_is_checked(tmp_path: Path) -> None:
    text = kato_text()
    bad = with_conversation(text, "{condition: nope, minutes: 2, items: [naturalness, nope]}")
    problems = protocol_problems(bad, tmp_path)
    assert "presentation.conversation.condition" in problems and "'nope'" in problems
    assert "presentation.conversation.items[1]: unknown item 'nope'" in problems
    assert "unknown item 'naturalness'" not in problems
    taken = with_conversation(text.replace("  - id: vowels\n    stimulus_set: vowels",
                                           "  - id: conversation\n    stimulus_set: vowels"),
                              "{condition: standard, minutes: 2}")  # fmt: skip
    assert "blocks[0].id" in protocol_problems(taken, tmp_path)
    none = with_conversation(text, "{condition: standard, minutes: 0}")
    assert "presentation.conversation.minutes" in protocol_problems(none, tmp_path)
    # the ids the logs give the conversation's and the questionnaire's rows are reserved
    own = with_conversation(text.replace("  - id: naturalness\n", "  - id: conversation\n"),
                            "{condition: standard, minutes: 2}")  # fmt: skip
    assert "items[0].id: 'conversation' is the conversation's own item" in protocol_problems(
        own, tmp_path)
    sick = text.replace("  - id: naturalness\n", "  - id: ssq_after_nausea\n")
    sick = sick.replace("  items_layout: sequential\n",
                        "  items_layout: sequential\n  ssq: [after]\n")
    assert "items[0].id: 'ssq_after_nausea'" in protocol_problems(sick, tmp_path)


def test_without_a_conversation_a_block_may_be_called_conversation(tmp_path: Path,
                                                                   capsys) -> None:  # fmt: skip
    path = tmp_path / "p.yaml"
    text = kato_text().replace("  - id: vowels\n    stimulus_set: vowels",
                               "  - id: conversation\n    stimulus_set: vowels")  # the block
    path.write_text(text, "utf-8")
    results = tmp_path / "results"
    assert main(["simulate", str(path), "--participants", "2", "--sim-seed", "1",
                 "--results", str(results)]) == 0  # fmt: skip
    assert main(["analyze", str(path), str(results), "--out", str(tmp_path / "out")]) == 0
    capsys.readouterr()
    with (tmp_path / "out" / "ratings.csv").open(encoding="utf-8") as f:
        assert "conversation" in {r["block"] for r in csv.DictReader(f)}  # analysed as any
    assert not (tmp_path / "out" / "conversation.csv").exists()


@pytest.mark.parametrize("when", ["before", "after"])
def test_the_timeline_has_the_conversation_then_the_partner_questions(
    tmp_path: Path, when: str
) -> None:
    path = tmp_path / "conv.yaml"
    spec = f"{{condition: emphasized, minutes: 1.5, when: {when}, items: [naturalness]}}"
    path.write_text(with_conversation(kato_text(), spec), encoding="utf-8")
    protocol = load_protocol(path)
    trials = build_trials(protocol, participant="P0001")
    screens = compile_timeline(protocol, trials, participant="P0001", session=1)
    at = next(i for i, s in enumerate(screens) if isinstance(s, ConversationScreen))
    talk, intro, vas = screens[at : at + 3]
    assert talk.seconds == 90.0 and talk.condition == "emphasized" and talk.trial_index == 0
    assert isinstance(intro, TextScreen) and intro.role == "partner"
    assert isinstance(vas, VasScreen) and [i.id for i in vas.items] == ["naturalness"]
    assert vas.response_keys() == ((0, "naturalness"),)
    first_trial = next(i for i, s in enumerate(screens) if (s.trial_index or 0) >= 1)
    last_trial = max(i for i, s in enumerate(screens) if (s.trial_index or 0) >= 1)
    assert (at < first_trial) if when == "before" else (at > last_trial)
    # resumed after the conversation, before the question about the partner: the intro and
    # the question, not the conversation again
    trial_keys = {k for s in screens if (s.trial_index or 0) >= 1
                  for k in getattr(s, "response_keys", tuple)()}  # fmt: skip
    answered = {(0, "conversation")} | (trial_keys if when == "after" else set())
    left = remaining(screens, answered, language="ja")
    assert not any(isinstance(s, ConversationScreen) for s in left)
    roles = [s.role for s in left if isinstance(s, TextScreen)]
    assert "partner" in roles and "resume" in roles
    # the study has begun: neither its instructions nor its practice trial again
    assert "instructions" not in roles and "practice" not in roles
    assert not any(getattr(s, "practice", False) for s in left)
    intro_at = next(i for i, s in enumerate(left) if isinstance(s, TextScreen)
                    and s.role == "partner")  # fmt: skip
    assert left[intro_at + 1] == vas
    # every question answered too: no intro to a question that will not come
    answered |= {(0, "naturalness")}
    left = remaining(screens, answered, language="ja")
    assert "partner" not in [s.role for s in left if isinstance(s, TextScreen)]


def test_the_lab_window_refuses_a_conversation_it_cannot_let_the_participant_hear(
    tmp_path: Path,
) -> None:
    """facelab run hosts the conversation in its window (tests/test_runner.py runs one); a
    lab machine without a sound output is refused before anything is made, and a talker file
    given to a protocol without a conversation is named."""
    import os
    import subprocess
    import sys

    path = tmp_path / "conv.yaml"
    path.write_text(with_conversation(kato_text(), "{condition: standard, minutes: 1}"), "utf-8")
    home = tmp_path / "home"
    home.mkdir()
    (home / ".asoundrc").write_text("pcm.!default {\n  type hw\n  card 99\n}\n")
    exe = str(Path(sys.executable).with_name("facelab"))
    done = subprocess.run([exe, "run", str(path), "--participant", "P01", "--results",
                           str(tmp_path / "r")], env={**os.environ, "HOME": str(home)},
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 2 and "no usable sound output" in done.stderr
    assert "Traceback" not in done.stderr and not (tmp_path / "r").exists()
    done = subprocess.run([exe, "run", str(KATO), "--participant", "P01", "--results",
                           str(tmp_path / "r"), "--conversation-input", str(path)],
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 2 and "has no presentation.conversation" in done.stderr
    assert not (tmp_path / "r").exists()


# --------------------------------------------------------------------------- simulate, analyse


@pytest.mark.slow
def test_simulated_conversations_are_tabulated_and_kept_out_of_the_trials(
    tmp_path: Path, capsys
) -> None:
    path = tmp_path / "conv.yaml"
    path.write_text(with_conversation(kato_text(), "{condition: emphasized, minutes: 0.5}"),
                    encoding="utf-8")  # fmt: skip
    results = tmp_path / "results"
    assert main(["simulate", str(path), "--participants", "3", "--sim-seed", "4",
                 "--results", str(results)]) == 0  # fmt: skip
    out = tmp_path / "report"
    assert main(["analyze", str(path), str(results), "--out", str(out)]) == 0
    capsys.readouterr()
    with (out / "conversation.csv").open(encoding="utf-8") as f:
        table = list(csv.DictReader(f))
    assert [r["participant"] for r in table] == ["P01", "P02", "P03"]
    for r in table:
        assert r["ended"] == "time" and float(r["seconds"]) == 30.0
        assert r["condition"] == "emphasized"
        assert 0 <= float(r["naturalness"]) <= 100 and 0 <= float(r["mouth_shape"]) <= 100
    with (out / "conversation_summary.csv").open(encoding="utf-8") as f:
        summary = {r["item"]: r for r in csv.DictReader(f)}
    ratings = [float(r["naturalness"]) for r in table]
    assert float(summary["naturalness"]["mean"]) == pytest.approx(np.mean(ratings), abs=1e-6)
    assert summary["naturalness"]["n"] == "3"
    with (out / "pilot_sessions.csv").open(encoding="utf-8") as f:
        sessions = list(csv.DictReader(f))
    assert all(s["responses"] == s["expected"] for s in sessions)  # 3 more rows expected
    with (out / "ratings.csv").open(encoding="utf-8") as f:
        assert "conversation" not in {r["block"] for r in csv.DictReader(f)}
    # an edited row (the conversation's condition changed) is refused, naming it
    tsv = next(results.rglob("sub-P02_*_beh.tsv"))
    lines = tsv.read_text(encoding="utf-8").splitlines()
    lines[1] = lines[1].replace("\temphasized\t", "\tstandard\t", 1)
    tsv.write_text("\n".join(lines) + "\n", encoding="utf-8")
    assert main(["analyze", str(path), str(results), "--out", str(tmp_path / "r2")]) == 2
    err = capsys.readouterr().err
    assert "P02" in err and "condition" in err and "conversation" in err
    lines[1] = lines[1].replace("\tstandard\t", "\temphasized\t", 1)  # restored
    tsv.write_text("\n".join(lines) + "\n", encoding="utf-8")
    assert main(["analyze", str(path), str(results), "--out", str(tmp_path / "r4")]) == 0
    capsys.readouterr()
    # the conversation's answer logged twice: refused, naming it
    third = next(results.rglob("sub-P03_*_beh.tsv"))
    rows = third.read_text(encoding="utf-8").splitlines()
    third.write_text("\n".join([rows[0], rows[1], *rows[1:]]) + "\n", encoding="utf-8")
    assert main(["analyze", str(path), str(results), "--out", str(tmp_path / "r5")]) == 2
    err = capsys.readouterr().err
    assert "P03" in err and "'conversation'" in err and "twice" in err
    third.write_text("\n".join(rows) + "\n", encoding="utf-8")
    # rows of a conversation analysed with a protocol that has none: refused
    assert main(["analyze", str(KATO), str(results), "--out", str(tmp_path / "r3")]) == 2
    assert "presentation.conversation" in capsys.readouterr().err


# --------------------------------------------------------------------------- online

slow = pytest.mark.slow


@pytest.fixture(scope="module")
def study(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The vowels of kato2021 (3 trials: 'あ。い。' in each condition) with a conversation
    after the instructions, rendered once at 320x180, 15 fps; a talker's recording."""
    root = tmp_path_factory.mktemp("conversation")
    text = kato_short(kato_vowels_only(kato_text()))
    text = text.replace("    presentations_per_condition: 2", "    presentations_per_condition: 1")
    text = with_conversation(text, "{condition: emphasized, minutes: 3, items: [naturalness]}")
    (root / "conv.yaml").write_text(text, encoding="utf-8")
    args = ["render", str(root / "conv.yaml"), "--out", str(root / "clips")]
    assert main([*args, "--size", "320x180", "--fps", "15", "--quiet"]) == 0
    spoken = synthesize("はい、わかりました。", sample_rate=16_000)
    sf.write(root / "talk.wav", spoken.samples, 16_000, subtype="FLOAT")
    return root


def _server(study: Path, results: Path, *, talker: str | Path = "mic", path: Path | None = None):
    from facelab.experiment.live_dialogue.conversation import conversation_routes
    from facelab.experiment.online.serve import prepare_server

    path = path or study / "conv.yaml"
    protocol = load_protocol(path)
    routes = conversation_routes(protocol, protocol_path=path,
                                 folder=results / "conversations", talker=talker,
                                 playout_ms=1000.0)  # fmt: skip
    server, _ = prepare_server(
        protocol, protocol_path=path, clips_dir=study / "clips",
        db_url=f"sqlite:///{results / 'db.sqlite'}", results=results, admin_secret=SECRET,
        routes=(routes,),
    )  # fmt: skip
    return server


@slow
def test_a_server_without_the_conversation_routes_refuses_the_protocol(
    study: Path, tmp_path: Path
) -> None:
    from facelab.errors import SessionError
    from facelab.experiment.online.serve import prepare_server

    with pytest.raises(SessionError, match=r"presentation\.conversation"):
        prepare_server(load_protocol(study / "conv.yaml"), protocol_path=study / "conv.yaml",
                       clips_dir=study / "clips", db_url=f"sqlite:///{tmp_path / 'db'}",
                       results=tmp_path, admin_secret=SECRET)  # fmt: skip


@slow
def test_the_conversation_routes_refuse_strangers_and_relay_a_turn(
    study: Path, tmp_path: Path
) -> None:
    from starlette.testclient import TestClient
    from starlette.websockets import WebSocketDisconnect

    from facelab.experiment.online.app import create_app

    server = _server(study, tmp_path)
    p, token = server.join(recruitment=None, source=None)
    # one event loop for the app's sockets and requests, as under uvicorn (without the
    # context manager each socket of a TestClient runs in an event loop of its own)
    with TestClient(create_app(server)) as client:
        assert client.get("/api/conversation").status_code == 401
        r = client.get("/api/conversation", headers={"X-Facelab-Token": token})
        assert r.status_code == 200
        cfg = r.json()
        assert cfg["condition"] == "emphasized" and cfg["sample_rate"] == 16_000 and cfg["names"]
        glb = client.get(cfg["scene"]["avatar"])
        assert glb.status_code == 200 and glb.content[:4] == b"glTF"
        admin = {"X-Facelab-Admin": SECRET}
        wrong = {"X-Facelab-Admin": "wrong-secret-0000"}
        assert client.get("/api/conversation/status", params={"participant": p.participant},
                          headers=wrong).status_code == 401  # fmt: skip
        assert client.get("/api/conversation/status", params={"participant": "P9999"},
                          headers=admin).status_code == 404  # fmt: skip
        # a viewer with an unknown token, and a page of another origin, are turned away
        with client.websocket_connect("/ws/conversation/view") as ws:
            ws.send_text(json.dumps({"token": "not-a-token"}))
            assert "unknown token" in ws.receive_json()["error"]
        with client.websocket_connect(
            "/ws/conversation/view", headers={"origin": "http://elsewhere.example"}
        ) as ws:
            assert "from this site" in ws.receive_json()["error"]
            with pytest.raises(WebSocketDisconnect):
                ws.receive_json()
        with client.websocket_connect("/ws/conversation/talk") as ws:
            ws.send_text(json.dumps({"admin": "wrong-secret-0000", "participant": p.participant}))
            assert "error" in ws.receive_json()
        # the participant's page and the talker: a turn relayed and recorded
        x = synthesize("はい。", sample_rate=16_000).samples.astype(np.float32)
        with client.websocket_connect("/ws/conversation/view") as viewer:
            viewer.send_text(json.dumps({"token": token}))
            _until(lambda: client.get("/api/conversation/status", headers=admin,
                                      params={"participant": p.participant}).json()["viewers"],
                   timeout_s=30, what="the viewer did not join")  # fmt: skip
            with client.websocket_connect("/ws/conversation/talk") as talker:
                talker.send_text(json.dumps({"admin": SECRET, "participant": p.participant}))
                assert talker.receive_json() == {"joined": p.participant, "viewers": 1}
                talker.send_text(json.dumps({"sample_rate": 16_000}))
                assert talker.receive_json() == {"started": True}
                assert viewer.receive_json() == {"turn": 1}
                for k in range(0, len(x), 160):
                    talker.send_bytes(x[k : k + 160].tobytes())
                talker.send_text(json.dumps({"end": 1}))
                kinds = set()
                while True:  # the sound and the face frames, then the turn's end
                    msg = viewer.receive()
                    if msg.get("bytes"):
                        kinds.add(int.from_bytes(msg["bytes"][:4], "little"))
                    elif "end" in json.loads(msg["text"]):
                        break
                assert kinds == {1, 2}
                viewer.send_text(json.dumps({"log": [[1.0, 0.05, 5, 5]], "arrivals": [[0, 0.0]],
                                             "display": "live3d"}))  # fmt: skip
                saved = talker.receive_json()["saved"]
            assert Path(saved).parent == tmp_path / "conversations" / p.participant
            status = client.get("/api/conversation/status", params={"participant": p.participant},
                                headers=admin).json()  # fmt: skip
            assert status["turns"] == 1 and status["viewers"] == 1 and not status["busy"]
            # the talker ends the conversation: the participant's page is told
            r = client.post("/api/conversation/end", json={"participant": p.participant},
                            headers=admin)  # fmt: skip
            assert r.json() == {"ended": True, "viewers": 1}
            assert viewer.receive_json() == {"conversation_end": 1}
            # the page reloads after the end: told at once, and /api/conversation says so
        with client.websocket_connect("/ws/conversation/view") as again:
            again.send_text(json.dumps({"token": token}))
            assert again.receive_json() == {"conversation_end": 1}
        cfg = client.get("/api/conversation", headers={"X-Facelab-Token": token}).json()
        assert cfg["ended"] is True and cfg["turns"] == 1
        audio, rate = sf.read(Path(saved) / "audio.wav", dtype="float32")
        assert rate == 16_000 and np.array_equal(audio, np.clip(x, -1, 1))  # as the talker sent it
        turn = json.loads((Path(saved) / "turn.json").read_text(encoding="utf-8"))
        assert turn["condition"] == "emphasized" and turn["viewer_displays"] == {"1": "live3d"}
        # whose turn it is: the participant, their session and protocol version
        assert (turn["participant"], turn["session"]) == (p.participant, 1)
        assert turn["protocol_sha256"] == p.protocol_sha256


def _talker_page(url: str, wav: Path):
    """A talker's Chromium whose microphone says ``wav`` (Chromium's fake capture)."""
    from facelab.experiment.online.browser import chromium
    from facelab.stimuli.speech.audio import load_audio

    speech = load_audio(wav, sample_rate=48_000)
    fake = wav.with_name("fake-mic.wav")
    sf.write(fake, speech.samples, 48_000, subtype="PCM_16")
    driver = chromium(size=(900, 700), extra_args=(
        "--use-fake-ui-for-media-stream", "--use-fake-device-for-media-stream",
        f"--use-file-for-fake-audio-capture={fake}%noloop",
    ))  # fmt: skip
    driver.get(url)
    return driver, len(speech.samples) / 48_000


def _until(check, *, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = check()
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError(what)


@slow
def test_a_participant_and_a_talker_in_two_browsers_converse_then_the_partner_is_rated(
    study: Path, tmp_path: Path
) -> None:
    """The participant's page (a simulated participant in Chromium) and the talker's page
    (another Chromium, its fake microphone saying a recording) join one conversation: the
    experimenter types the secret, talks one turn, and ends the conversation with the
    page's button. Every answer is stored once; the turn is the talker's speech, recorded
    with the frames the participant's page drew (each the frame of the sound it heard, or an
    older one counted late, never a later one)."""
    import httpx
    from selenium.webdriver.common.by import By

    from facelab.experiment.online.browser import SimulatedBrowser
    from facelab.experiment.online.serve import BackgroundServer

    results = tmp_path / "results"
    results.mkdir()
    server = _server(study, results)
    shots = tmp_path / "shots"
    outcome: dict[str, str] = {}
    admin = {"X-Facelab-Admin": SECRET}
    with BackgroundServer(server) as bg:
        sim = SimulatedBrowser(server, bg.url, 1, seed=3, screenshots=shots)
        thread = threading.Thread(target=lambda: outcome.setdefault("k", sim.run()))
        thread.start()

        def status() -> dict:
            r = httpx.get(f"{bg.url}/api/conversation/status", params={"participant": "P0001"},
                          headers=admin)  # fmt: skip
            return r.json() if r.status_code == 200 else {}

        _until(lambda: status().get("viewers") == 1 or not thread.is_alive(), timeout_s=300,
               what="the participant's page did not join the conversation")  # fmt: skip
        assert thread.is_alive(), outcome
        talker, seconds = _talker_page(f"{bg.url}/talk?participant=P0001", study / "talk.wav")
        try:
            state = "return window.FacelabDialogue && window.FacelabDialogue.state"
            _until(lambda: talker.execute_script(state) == "loading" or None, timeout_s=30,
                   what="the talker page did not load")  # fmt: skip
            talker.find_element(By.CSS_SELECTOR, "[data-facelab=secret]").send_keys(SECRET)
            talker.find_element(By.CSS_SELECTOR, "[data-facelab=talk]").click()
            _until(lambda: talker.execute_script(state) in ("talking", "refused"), timeout_s=30,
                   what="the talker page did not start")  # fmt: skip
            assert talker.execute_script(state) == "talking"
            time.sleep(seconds + 0.5)
            talker.find_element(By.CSS_SELECTOR, "[data-facelab=talk]").click()  # stop
            _until(lambda: talker.execute_script(state) == "saved", timeout_s=60,
                   what="the talker's turn was not saved")  # fmt: skip
            # the talker's page follows the participant: their page in it, the turn recorded
            seen = "const p = window.FacelabDialogue.participant; return p && [p.viewers, p.turns]"
            _until(lambda: talker.execute_script(seen) == [1, 1], timeout_s=30,
                   what="the talker page did not show the participant's state")  # fmt: skip
            talker.save_screenshot(str(tmp_path / "talker.png"))
            talker.find_element(By.CSS_SELECTOR, "[data-facelab=end_conversation]").click()
            _until(lambda: talker.execute_script(state) == "ended", timeout_s=30,
                   what="the talker could not end the conversation")  # fmt: skip
        finally:
            talker.quit()
        thread.join(timeout=600)
    assert outcome.get("k") == "complete"
    with Session(server.engine) as db:
        rows = [x.row for x in db.scalars(select(Response))]
        clicks = {(a.record["trial_index"], a.record["item"]): a.record["value"]
                  for a in db.scalars(select(Action))}  # fmt: skip
        assert db.scalars(select(Participant)).one().completed is not None
    keys = [(r["trial_index"], r["item"]) for r in rows]
    assert len(keys) == len(set(keys)) == 3 * 2 + 2  # 3 trials x 2 items, the conversation, 1
    talk = next(r for r in rows if r["item"] == "conversation")
    assert talk["response"] == "talker" and talk["score"] == 1.0
    assert talk["screen"] == "conversation" and talk["block"] == "conversation"
    assert talk["condition"] == "emphasized" and talk["rt_s"] > seconds
    partner = next(r for r in rows if r["trial_index"] == 0 and r["item"] == "naturalness")
    assert abs(partner["rating"] - clicks[(0, "naturalness")]) < 0.5  # the click, stored
    (turn,) = sorted((results / "conversations" / "P0001").glob("turn-*"))
    record = json.loads((turn / "turn.json").read_text(encoding="utf-8"))
    assert record["viewer_displays"] == {"1": "live3d"}
    assert record["talker"] == "microphone (browser page)"
    audio, rate = sf.read(turn / "audio.wav", dtype="float32")
    assert rate == 16_000 and len(audio) / rate >= 0.8 * seconds
    frames = audio[: len(audio) // 160 * 160].reshape(-1, 160)
    level = 10 * np.log10(np.mean(frames.astype(np.float64) ** 2, axis=1) + 1e-12)
    assert level.max() > -30 and np.mean(level > -45) > 0.15  # the talker's speech
    with (turn / "frames.csv").open(encoding="utf-8") as f:
        drawn = list(csv.DictReader(f))
    assert drawn and all(int(d["frame"]) <= int(d["wanted"]) for d in drawn)
    assert all((d["late"] == "1") == (int(d["frame"]) < int(d["wanted"])) for d in drawn)
    assert (shots / "conversation-page.png").is_file()


@slow
def test_serve_with_a_recording_as_the_talker_then_export_and_analyze(
    study: Path, tmp_path: Path, capsys
) -> None:
    """``facelab serve --simulate-participants 1 --conversation-input talk.wav``: the server
    says the recording when the conversation starts, the conversation ends when its 6 s
    have run out; the export analyses into conversation.csv."""
    text = (study / "conv.yaml").read_text(encoding="utf-8")
    path = tmp_path / "conv6.yaml"
    path.write_text(text.replace("minutes: 3,", "minutes: 0.1,"), encoding="utf-8")
    results, shots = tmp_path / "results", tmp_path / "shots"
    code = main(["serve", str(path), "--clips", str(study / "clips"), "--results", str(results),
                 "--port", "0", "--simulate-participants", "1", "--screenshots", str(shots),
                 "--conversation-input", str(study / "talk.wav"),
                 "--conversation-playout-ms", "1000"])  # fmt: skip
    out = capsys.readouterr().out
    assert code == 0, out
    (turn,) = sorted((results / "kato2021" / "conversations" / "P0001").glob("turn-*"))
    record = json.loads((turn / "turn.json").read_text(encoding="utf-8"))
    assert record["talker"] == str(study / "talk.wav") and record["n_frames"] >= 100
    exported = tmp_path / "exported"
    db = f"sqlite:///{results / 'kato2021' / 'online.sqlite'}"
    assert main(["export", "--db", db, "--results", str(exported)]) == 0
    report = tmp_path / "report"
    assert main(["analyze", str(path), str(exported), "--out", str(report)]) == 0
    with (report / "conversation.csv").open(encoding="utf-8") as f:
        (row,) = list(csv.DictReader(f))
    assert row["ended"] == "time" and row["turns"] == "1" and 6.0 <= float(row["seconds"]) < 30
    assert 0 <= float(row["naturalness"]) <= 100
    # the partner mid-turn, when the page drew a frame with the mouth open (a page loaded by
    # the whole suite may draw none in a 2 s turn: the page's own screenshot is always kept)
    still = shots / "conversation.png"
    if record["frames_shown"] and still.exists():
        assert still.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (shots / "conversation-page.png").is_file()
    assert main(["serve", str(path), "--clips", str(study / "clips"), "--results",
                 str(tmp_path / "r2"), "--conversation-input", str(tmp_path / "none.wav")]) == 2
    assert "none.wav" in capsys.readouterr().err


@slow
def test_a_conversation_in_an_emulated_headset(study: Path, tmp_path: Path) -> None:
    """display webxr: the conversation runs in the headset (the partner in the room, no panel
    over them) with the server as the talker, and ends when its 7 s have run out; the
    participant's page drew the turn in VR, and the partner is rated on a VR panel."""
    from facelab.experiment.online.browser import SimulatedBrowser
    from facelab.experiment.online.serve import BackgroundServer

    text = (study / "conv.yaml").read_text(encoding="utf-8")
    text = text.replace("presentation:\n", "presentation:\n  display: webxr\n", 1)
    path = tmp_path / "conv_vr.yaml"
    path.write_text(text.replace("minutes: 3,", "minutes: 0.12,"), encoding="utf-8")
    results, shots = tmp_path / "results", tmp_path / "shots"
    results.mkdir()
    server = _server(study, results, talker=study / "talk.wav", path=path)
    with BackgroundServer(server) as bg:
        sim = SimulatedBrowser(server, bg.url, 1, seed=5, screenshots=shots, window=(640, 400))
        assert sim.run() == "complete"  # the headset's two eyes drawn small: sooner frames
    with Session(server.engine) as db:
        rows = [x.row for x in db.scalars(select(Response))]
        clicks = {(a.record["trial_index"], a.record["item"]): a.record["value"]
                  for a in db.scalars(select(Action))}  # fmt: skip
    talk = next(r for r in rows if r["item"] == "conversation")
    assert talk["response"] == "time" and talk["score"] == 1.0 and talk["rt_s"] >= 7.2
    partner = next(r for r in rows if r["trial_index"] == 0 and r["item"] == "naturalness")
    assert abs(partner["rating"] - clicks[(0, "naturalness")]) < 0.5  # a ray on the panel
    (turn,) = sorted((results / "conversations" / "P0001").glob("turn-*"))
    record = json.loads((turn / "turn.json").read_text(encoding="utf-8"))
    assert record["viewer_displays"] == {"1": "webxr"}
    with (turn / "frames.csv").open(encoding="utf-8") as f:
        drawn = list(csv.DictReader(f))
    # every drawn frame the sound's or older, never a later one (how many a headset page
    # loaded by the whole suite draws in a 2 s turn is the machine's business: none in a CI
    # run), and the head's pose at each of them
    assert all(int(d["frame"]) <= int(d["wanted"]) for d in drawn)
    heads = []
    if (turn / "poses.csv").exists():
        with (turn / "poses.csv").open(encoding="utf-8") as f:
            heads = list(csv.DictReader(f))
    assert [h["page_ms"] for h in heads] == [d["page_ms"] for d in drawn]
    assert record.get("head_poses", 0) == len(heads)
