"""Live dialogue (issue 53): the condition's method run on streaming audio gives the frames the
offline chain gives the same recording; methods that cannot run live say so; a turn is
recorded (audio, the track as sent, the viewers' frame log, latency) and never overwritten;
the server's sockets stream a talker to viewers; ``facelab live --simulate`` runs talker and
viewer in headless Chromium with a file as the microphone, and ``facelab render --turn``
renders the recorded turn under every condition."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from facelab.errors import FacelabError, SessionError, StageError
from facelab.experiment.cli import main
from facelab.experiment.live_dialogue.turn import (
    BUDGET_BEHIND_MS,
    Turn,
    latency_summary,
    next_turn_dir,
    turns_protocol,
)
from facelab.experiment.live_dialogue.window_view import LEAD_MAX_S
from facelab.formats import read_manifest, read_track
from facelab.methods import METHODS
from facelab.protocol import load_protocol
from facelab.resources import package_file
from facelab.stimuli.arkit import VISEME_TARGETS
from facelab.stimuli.avatar.samples import write_sample
from facelab.stimuli.methods import get
from facelab.stimuli.methods.live_drive import LiveDriver, _columns, live_problem
from facelab.stimuli.methods.registry import Method
from facelab.stimuli.methods.types import BlendshapeTrack, DriveInput
from facelab.stimuli.render.scene import load_avatar
from facelab.stimuli.speech.analyser import analyze
from facelab.stimuli.speech.tts import synthesize

KATO = Path(package_file("facelab.protocols", "kato2021.yaml"))


@pytest.fixture(scope="module")
def speech():
    return synthesize("はい、そうです。", sample_rate=16_000)


@pytest.fixture(scope="module")
def kato():
    protocol = load_protocol(KATO)
    return protocol, load_avatar(protocol, base_dir=KATO.parent)


def offline_frames(samples, *, method, params, avatar, names, base_dir, warp=1.0):
    """The offline chain on the same samples: analyse at ``warp``, compensate, drive."""
    track = analyze(samples, sample_rate=16_000, warp=warp).compensated()
    out = get(method).drive_on(avatar, DriveInput(track=track, base_dir=base_dir), params)
    return np.clip(_columns(out, names), 0, 1)


def stream(driver: LiveDriver, samples, *, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    got, k, expect = [], 0, 0
    while k < len(samples):
        n = int(rng.integers(1, 500))
        frames = driver.feed(samples[k : k + n])
        k += n
        assert frames.start == expect  # no frame skipped or repeated
        expect += len(frames)
        got.append(frames.weights)
    got.append(driver.flush().weights)
    return np.vstack(got)


@pytest.mark.parametrize("condition", ["baseline", "standard", "emphasized"])
def test_streamed_frames_are_the_offline_frames(kato, speech, condition) -> None:
    protocol, avatar = kato
    cond = protocol.condition(condition)
    driver = LiveDriver(method_name=cond.method, params=cond.settings, avatar=avatar,
                        sample_rate=16_000, base_dir=KATO.parent, warp=1.0)  # fmt: skip
    live = stream(driver, speech.samples, seed=3)
    ref = offline_frames(speech.samples, method=cond.method, params=cond.settings,
                         avatar=avatar, names=driver.names, base_dir=KATO.parent)  # fmt: skip
    assert live.shape == ref.shape == (len(ref), len(driver.names))
    assert np.abs(live - ref).max() < 1e-9
    assert live.max() > 0.2  # the mouth moves
    # a frame waits for the analysis window's half and the next analysis frame
    assert 0.02 < driver.latency_s < 0.045


def test_a_vrm_with_vowel_presets_runs_live_through_its_stand_in(tmp_path, speech) -> None:
    from facelab.stimuli.avatar import load

    avatar = load(write_sample(tmp_path / "v.vrm", kind="vrm1", vroid=True))
    params = METHODS["vowel_blend"].parse({"z": "standard"})
    driver = LiveDriver(method_name="vowel_blend", params=params, avatar=avatar,
                        sample_rate=16_000, warp=1.0)  # fmt: skip
    assert set(driver.names) <= set(avatar.targets)
    live = stream(driver, speech.samples, seed=5)
    ref = offline_frames(speech.samples, method="vowel_blend", params=params, avatar=avatar,
                         names=driver.names, base_dir=Path("."))  # fmt: skip
    assert np.abs(live - ref).max() < 1e-9 and live.max() > 0.2


def test_the_live_warp_follows_a_longer_vocal_tract(kato) -> None:
    """Speech read at 0.8 of its rate (formants 20 % lower, as a longer vocal tract): the
    live analysis moves its mel-filter warp below 0.9 within the first second, and after its
    last change its frames are the offline analysis at that warp."""
    from facelab.stimuli.speech.audio import resample
    from facelab.stimuli.speech.training import corpus

    protocol, avatar = kato
    _, held = corpus()
    x = np.concatenate([synthesize(t, sample_rate=16_000).samples for t in held[:2]])
    low = resample(x.astype(np.float32), rate_in=16_000, rate_out=20_000).astype(np.float64)
    cond = protocol.condition("standard")
    driver = LiveDriver(method_name=cond.method, params=cond.settings, avatar=avatar,
                        sample_rate=16_000, base_dir=KATO.parent)  # fmt: skip
    live = stream(driver, low, seed=9)
    changes = driver.stream.warps
    assert changes[0] == (0, 1.0) and len(changes) >= 2
    assert changes[1][0] <= 16_500 and changes[1][1] < 0.9, changes  # ~1 s (+ a chunk)
    at, warp = changes[-1]
    track = analyze(low, sample_rate=16_000, warp=warp).compensated()
    out = get(cond.method).drive_on(avatar, DriveInput(track=track, base_dir=KATO.parent),
                                    cond.settings)  # fmt: skip
    ref = np.clip(_columns(out, driver.names), 0, 1)
    after = at // 160 + 1  # frames whose analysis and next frame both come after the change
    assert np.abs(live[after:] - ref[after:]).max() < 1e-9


def test_methods_that_cannot_run_live_say_why(kato) -> None:
    _, avatar = kato
    said = {
        name: live_problem(name, get(name).examples()[0], avatar=avatar)
        for name in ("text_visemes", "external_track", "impression")
    }
    assert "phoneme timing" in said["text_visemes"]
    assert "made beforehand" in said["external_track"]
    assert "whole clip" in said["impression"]


class _Running(Method):
    """A method that claims to run live but whose frame depends on later frames."""

    spec = METHODS["viseme_baseline"]
    live_problem = None

    def drive(self, inp, params):
        w = inp.track.weights  # every frame the mean of the whole track
        return BlendshapeTrack(inp.track.times, np.repeat(w.mean(axis=0, keepdims=True),
                                                          len(w), axis=0), VISEME_TARGETS)


def test_a_method_claiming_to_run_live_is_checked(kato, monkeypatch) -> None:
    from facelab.stimuli.methods import registry

    _, avatar = kato
    monkeypatch.setitem(registry.REGISTRY, "viseme_baseline", _Running())
    said = live_problem("viseme_baseline", METHODS["viseme_baseline"].parse({}), avatar=avatar)
    assert said is not None and "depends on frames after it" in said
    with pytest.raises(StageError, match="depends on frames after it"):
        LiveDriver(method_name="viseme_baseline", params=METHODS["viseme_baseline"].parse({}),
                   avatar=avatar, sample_rate=16_000)  # fmt: skip


def test_a_rate_the_analyser_cannot_frame_is_refused(kato) -> None:
    protocol, avatar = kato
    cond = protocol.condition("standard")
    with pytest.raises(StageError, match="22050 Hz"):
        LiveDriver(method_name=cond.method, params=cond.settings, avatar=avatar,
                   sample_rate=22_050)  # fmt: skip


def test_live_passes_over_a_missing_shape_the_method_holds_at_zero(kato) -> None:
    """As the offline render does: an ARKit export without tongueOut (Z holds it at 0) runs
    live with that channel left out; one without jawOpen, which Z moves, is refused."""
    protocol, avatar = kato
    cond = protocol.condition("standard")
    lacking = avatar.replace(targets={k: v for k, v in avatar.targets.items()
                                      if k != "tongueOut"})  # fmt: skip
    driver = LiveDriver(method_name=cond.method, params=cond.settings, avatar=lacking,
                        sample_rate=16_000)  # fmt: skip
    assert "tongueOut" not in driver.names and "jawOpen" in driver.names
    no_jaw = avatar.replace(targets={
        k: v for k, v in avatar.targets.items() if k != "jawOpen" and not k.startswith("viseme_")})
    with pytest.raises(StageError, match="jawOpen"):  # no vowel shapes to stand in either
        LiveDriver(method_name=cond.method, params=cond.settings, avatar=no_jaw,
                   sample_rate=16_000)  # fmt: skip


# --------------------------------------------------------------------------- a recorded turn


def rows(latencies_ms, *, late=()):
    return [{"viewer": 1, "page_ms": 16.7 * i, "heard_s": 0.1 + i * 0.0167,
             "frame": 0, "wanted": 0, "latency_ms": v, "late": int(i in late)}
            for i, v in enumerate(latencies_ms)]  # fmt: skip


def test_latency_summary_counts_frames_and_checks_the_budget() -> None:
    good = latency_summary(rows([2.0] * 90 + [8.0] * 10, late=(3,)), n_frames=400)
    assert good["frames_shown"] == 100 and good["frames_late"] == 1
    assert good["latency_ms_median"] == 2.0 and good["within_budget"] is True
    assert good["frame_interval_ms_median"] == pytest.approx(16.7)
    slow = latency_summary(rows([BUDGET_BEHIND_MS + 5] * 20), n_frames=400)
    assert slow["within_budget"] is False
    ahead = latency_summary(rows([2.0] * 19 + [-60.0]), n_frames=400)
    assert ahead["ahead_ms_max"] == 60.0 and ahead["within_budget"] is False
    after_end = latency_summary(rows([2.0] * 20), n_frames=5)  # heard after 0.05 s: none
    assert after_end["frames_shown"] == 0 and after_end["within_budget"] is None


def test_a_turn_is_saved_whole_and_never_overwritten(tmp_path) -> None:
    session = tmp_path / "s"
    session.mkdir()
    turn = Turn(sample_rate=16_000, names=("jawOpen", "mouthFunnel"))
    rng = np.random.default_rng(1)
    audio = rng.uniform(-0.5, 0.5, 16_000).astype(np.float32)
    turn.add_audio(audio[:8000])
    turn.add_audio(audio[8000:])
    turn.add_frames(0, rng.uniform(0, 1, (60, 2)))
    turn.add_frames(60, rng.uniform(0, 1, (40, 2)))
    with pytest.raises(SessionError, match="would not line up"):
        turn.add_frames(99, rng.uniform(0, 1, (1, 2)))
    # the page's own 'wanted' (last column) is not trusted: computed from heard_s
    turn.add_viewer_log(1, [[10.0, 0.105, 10, 99], [26.7, 0.121, 11, 0]],
                        arrivals=[[12, 0.02], [30, 0.29]])  # fmt: skip
    assert next_turn_dir(session).name == "turn-001"
    (session / ".turn-crashed").mkdir()  # a save that died half-way: not a turn
    record = turn.save_new(session, condition="c", avatar_sha256="a" * 64, info={"x": 1},
                           playout_ms=120)  # fmt: skip
    folder = Path(record["folder"])
    assert folder.name == "turn-001" and record["turn"] == "turn-001"
    assert sorted(p.name for p in folder.iterdir()) == [
        "audio.wav", "frames.csv", "track.bin", "turn.json"]  # fmt: skip
    saved, rate = sf.read(folder / "audio.wav", dtype="float32")
    assert rate == 16_000 and np.array_equal(saved, audio)  # exactly what was analysed
    track = read_track(folder / "track.bin")
    assert track.header["fps"] == 100 and track.names == ["jawOpen", "mouthFunnel"]
    assert np.allclose(track.values, turn.weights)
    assert record["frames_shown"] == 2 and record["frames_late"] == 1
    assert record["latency_ms_max"] == pytest.approx(11.0)
    assert record["frame_margin_ms_min"] == pytest.approx(10.0)  # frame 30 due 0.30, at 0.29
    assert json.loads((folder / "turn.json").read_text())["duration_s"] == 1.0
    assert folder.stat().st_mode & 0o777 == 0o755
    first = {p.name: p.read_bytes() for p in folder.iterdir()}
    again = turn.save_new(session, condition="c", avatar_sha256="a" * 64, info={},
                          playout_ms=120)  # fmt: skip
    assert Path(again["folder"]).name == "turn-002"  # the first turn is untouched
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == first


def test_a_viewer_in_a_headset_has_its_head_poses_saved(tmp_path) -> None:
    turn = Turn(sample_rate=16_000, names=("jawOpen",))
    turn.add_audio(np.zeros(1600, np.float32))
    turn.add_frames(0, np.zeros((10, 1)))
    turn.add_viewer_log(1, [[10.0, 0.05, 5, 5]], poses=[[10.0, 0, 1.2, 0, 175.0, -3.0, 1.0],
                                                        [26.7, 0, 1.2, 0.01, -170.0, 4.0, 0.0]])
    record = turn.save_new(tmp_path, condition="c", avatar_sha256="a" * 64, info={},
                           playout_ms=120)  # fmt: skip
    folder = Path(record["folder"])
    rows = (folder / "poses.csv").read_text().splitlines()
    assert rows[0] == "viewer,page_ms,x,y,z,yaw,pitch,roll" and len(rows) == 3
    assert rows[2] == "1,26.7,0.0,1.2,0.01,-170.0,4.0,0.0"
    # the turn across 180 deg is 15 deg, not 345
    assert record["head_poses"] == 2 and record["head_yaw_range_deg"] == pytest.approx(15.0)
    assert record["head_pitch_range_deg"] == pytest.approx(7.0)


def test_a_turn_name_taken_meanwhile_is_not_overwritten(tmp_path, monkeypatch) -> None:
    """Another saver takes turn-001 between the name's choice and the rename: the turn goes
    to the next free name, the other's files untouched; numbering goes past 999."""
    import facelab.experiment.live_dialogue.turn as turn_module

    session = tmp_path / "s"
    (session / "turn-001").mkdir(parents=True)
    (session / "turn-001" / "turn.json").write_text("theirs")
    names = iter([session / "turn-001", session / "turn-002"])
    monkeypatch.setattr(turn_module, "next_turn_dir", lambda _: next(names))
    turn = Turn(sample_rate=16_000, names=("jawOpen",))
    turn.add_audio(np.zeros(160, np.float32))
    record = turn.save_new(session, condition="c", avatar_sha256="a" * 64, info={},
                           playout_ms=120)  # fmt: skip
    assert Path(record["folder"]).name == "turn-002"
    assert (session / "turn-001" / "turn.json").read_text() == "theirs"
    assert not list(session.glob(".turn-*"))  # no scratch folder left behind
    monkeypatch.undo()
    (session / "turn-999").mkdir()
    (session / "turn-1000").mkdir()
    assert next_turn_dir(session).name == "turn-1001"


def test_the_live_warp_survives_silence_and_calibration(kato) -> None:
    """A turn that starts with silence keeps the warp the talker's last turn settled on (too
    little speech to judge is no reason to change it); a calibrated model runs at warp 1."""
    from facelab.stimuli.speech.analyser import WarpAdaptingAnalyzer, default_model

    quiet = WarpAdaptingAnalyzer(sample_rate=16_000, warp=0.88)
    for _ in range(120):  # 1.2 s of silence in 10 ms chunks
        quiet.feed(np.zeros(160))
    assert quiet.warps == [(0, 0.88)] and quiet.warp == 0.88
    from dataclasses import replace

    model = default_model()
    calibrated = WarpAdaptingAnalyzer(
        sample_rate=16_000, warp=0.8,
        model=replace(model, info={**model.info, "calibrated": "x"}),
    )  # fmt: skip
    speech = synthesize("こんにちは、今日はいい天気ですね。", sample_rate=16_000).samples
    calibrated.feed(speech)
    assert calibrated.warp == 1.0 and calibrated.warps == [(0, 1.0)]


def test_turns_become_a_protocol_s_stimuli(tmp_path) -> None:
    for name in ("turn-001", "turn-002"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "turn.json").write_text("{}")
        sf.write(tmp_path / name / "audio.wav", np.zeros(1600, np.float32), 16_000)
    protocol = turns_protocol(KATO, [tmp_path / "turn-001", tmp_path / "turn-002"])
    (sset,) = protocol.stimulus_sets
    assert sset.id == "live" and [s.id for s in sset.stimuli] == ["turn-001", "turn-002"]
    assert all(b.stimulus_set == "live" for b in protocol.blocks)
    assert [c.id for c in protocol.conditions] == ["baseline", "standard", "emphasized"]
    with pytest.raises(SessionError, match="not a recorded live turn"):
        turns_protocol(KATO, [tmp_path])


# --------------------------------------------------------------------------- the server


def test_a_file_talker_streams_to_a_viewer_socket(tmp_path) -> None:
    from starlette.testclient import TestClient

    from facelab.experiment.live_dialogue.app import LiveConfig, LiveHub, create_live_app

    wav = tmp_path / "talk.wav"
    x = synthesize("はい。", sample_rate=16_000).samples
    sf.write(wav, x, 16_000, subtype="FLOAT")
    config = LiveConfig(protocol=load_protocol(KATO), protocol_path=KATO, condition="standard",
                        session=tmp_path / "session", talker=wav)  # fmt: skip
    config.session.mkdir()
    hub = LiveHub.open(config)
    audio, frames = {}, {}
    with TestClient(create_live_app(hub)) as client:
        assert client.get("/live.json").json()["names"] == list(hub.driver.names)
        with client.websocket_connect("/ws/view") as ws:
            assert "turn" in ws.receive_json()
            while True:
                msg = ws.receive()
                if msg.get("text"):
                    end = json.loads(msg["text"])["end"]
                    break
                data = msg["bytes"]
                kind, start, count, width = np.frombuffer(data[:16], "<u4")
                values = np.frombuffer(data[16:], "<f4").reshape(count, width)
                (audio if kind == 1 else frames)[int(start)] = values
            ws.send_text(json.dumps({"log": [[0.0, 0.05, 5, 5], [16.7, 0.066, 5, 6]]}))
            for _ in range(200):
                if hub.turns:
                    break
                time.sleep(0.05)
    got = np.concatenate([audio[k].ravel() for k in sorted(audio)])
    assert end == len(x) and np.allclose(got, x, atol=1e-7)
    sent = np.vstack([frames[k] for k in sorted(frames)])
    (record,) = hub.turns
    track = read_track(Path(record["folder"]) / "track.bin")
    assert np.array_equal(track.values, sent.astype(np.float32))  # recorded = what was sent
    assert record["frames_shown"] == 2 and record["frames_late"] == 1


def test_a_microphone_talker_over_its_socket(tmp_path) -> None:
    """The /talk socket: a turn starts at 16 kHz, bad messages are ignored (not-an-object
    JSON, NaN samples become silence, a viewer's malformed log), a second talker is refused
    in words, and a talker that disconnects without 'end' still gets its turn saved."""
    from starlette.testclient import TestClient

    from facelab.experiment.live_dialogue.app import LiveConfig, LiveHub, create_live_app

    config = LiveConfig(protocol=load_protocol(KATO), protocol_path=KATO, condition="baseline",
                        session=tmp_path / "session")  # fmt: skip
    hub = LiveHub.open(config)
    x = synthesize("はい。", sample_rate=16_000).samples.astype(np.float32)
    x[800:810] = np.nan
    with TestClient(create_live_app(hub)) as client, \
            client.websocket_connect("/ws/view") as viewer:  # fmt: skip
        with client.websocket_connect("/ws/talk") as talker:
            talker.send_text("[1, 2]")
            talker.send_text(json.dumps({"sample_rate": 44_100}))
            assert "16000 Hz" in talker.receive_json()["error"]
            talker.send_text(json.dumps({"sample_rate": 16_000}))
            assert talker.receive_json() == {"started": True}
            assert "turn" in viewer.receive_json()
            with client.websocket_connect("/ws/talk") as second:
                second.send_text(json.dumps({"sample_rate": 16_000}))
                assert "another talker" in second.receive_json()["error"]
            for k in range(0, len(x), 160):
                talker.send_bytes(x[k : k + 160].tobytes())
            for _ in range(400):  # every chunk analysed before the talker leaves
                if hub.driver.samples_in == len(x):
                    break
                time.sleep(0.05)
        # the talker left without 'end': the turn ends; the viewer's log has junk in it
        while True:
            msg = viewer.receive()
            if msg.get("text") and "end" in json.loads(msg["text"]):
                break
        viewer.send_text(json.dumps({"log": [["x", 1, 2, 3], [1.0, 0.05, 5, 5], None],
                                     "arrivals": "no"}))  # fmt: skip
        for _ in range(200):
            if hub.turns:
                break
            time.sleep(0.05)
    (record,) = hub.turns
    assert not hub.busy and record["frames_shown"] == 1
    audio, _ = sf.read(Path(record["folder"]) / "audio.wav", dtype="float32")
    assert len(audio) == len(x) and np.all(audio[800:810] == 0)  # silence, timing kept
    assert np.array_equal(audio[:800], x[:800])


def test_live_refuses_what_it_cannot_do(tmp_path, capsys) -> None:
    assert main(["live", str(KATO), "--condition", "nope"]) == 2
    assert "conditions are baseline, standard, emphasized" in capsys.readouterr().err
    assert main(["live", str(KATO), "--condition", "standard", "--size", "640x480"]) == 2
    assert "--size goes with --display window" in capsys.readouterr().err
    assert main(["live", str(KATO), "--condition", "standard", "--json", "x.json"]) == 2
    assert "--json goes with --simulate" in capsys.readouterr().err
    bad = tmp_path / "bad.wav"
    bad.write_bytes(b"RIFF0000WAVEjunk")
    assert main(["live", str(KATO), "--condition", "standard", "--input", str(bad),
                 "--session", str(tmp_path / "never")]) == 2  # fmt: skip
    assert "bad.wav" in capsys.readouterr().err
    assert not (tmp_path / "never").exists()  # nothing made for a session that cannot run
    proto = tmp_path / "p.yaml"
    proto.write_text(KATO.read_text().replace("method: viseme_baseline", "method: text_visemes"))
    assert main(["live", str(proto), "--condition", "baseline", "--session",
                 str(tmp_path / "s")]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert "cannot run live" in err and "phoneme timing" in err and "Traceback" not in err


# --------------------------------------------------------------------------- in Chromium


def drawn_right(folder: Path, record: dict, *, ahead_ms: float = 0.0) -> None:
    """The viewer drew frames of the turn, each the frame of the audio it heard or (late, the
    frame not there yet: a starved page or server) an older one, never a later one; and the
    figures in turn.json are those of frames.csv. How many frames a headless page draws, and
    whether a loaded machine makes some late, is the machine's business: 2 drawn frames of a
    3.4 s turn in one CI run, 8 on an idle machine."""
    import csv

    with open(folder / "frames.csv", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert rows, "the viewer drew no frame of the turn"
    for row in rows:
        frame, wanted = int(row["frame"]), int(row["wanted"])
        # never the mouth of sound not yet heard (a page draws the frame it has when it
        # draws); or, for a viewer that asks for the frame of the flip ahead (the lab
        # window), never more than ``ahead_ms`` before the sound
        assert (frame - wanted) * 10 <= ahead_ms
        assert int(row["late"]) == int(frame < wanted)
        if frame == wanted:  # on time: behind by less than one 10 ms frame step
            assert 0 <= float(row["latency_ms"]) <= 10.0
    during = [r for r in rows if 0 <= float(r["heard_s"]) < record["n_frames"] / 100]
    assert record["frames_shown"] == len(during)
    assert record["frames_late"] == sum(int(r["late"]) for r in during)
    assert record["ahead_ms_max"] is None or record["ahead_ms_max"] <= ahead_ms
    assert isinstance(record["audio_chunks_late"], int)


@pytest.mark.slow
def test_a_simulated_live_turn_in_chromium(tmp_path) -> None:
    """The talker's page captures a file through Chromium's fake microphone; the viewer's
    page plays it and draws the face; the turn is recorded within the latency budget, its
    track is the offline chain's on its audio, and it renders under two conditions."""
    talk = tmp_path / "talk.wav"
    spoken = synthesize("はい、わかりました。すぐに行きます。", sample_rate=24_000)
    sf.write(talk, spoken.samples, 24_000, subtype="PCM_16")
    out, shot = tmp_path / "live.json", tmp_path / "viewer.png"
    # a playout long enough for a machine loaded by the rest of the suite (the default 120 ms
    # is what `facelab live` measures by itself; the test asserts the mechanism, not speed:
    # how many frames a loaded headless page draws is the machine's business - 2 of a 3.4 s
    # turn in a CI run - so every drawn frame must be right, and there must be one)
    code = main(["live", str(KATO), "--condition", "emphasized", "--simulate", str(talk),
                 "--json", str(out), "--screenshot", str(shot), "--session",
                 str(tmp_path / "session"), "--playout-ms", "1000"])  # fmt: skip
    assert code == 0
    record = json.loads(out.read_text())
    for key in ("latency_ms_median", "latency_ms_p95", "frames_shown", "frames_late",
                "recording"):  # fmt: skip
        assert key in record
    folder = Path(record["recording"])
    drawn_right(folder, record)
    audio, rate = sf.read(folder / "audio.wav", dtype="float32")
    # the file's speech reached the server through Chromium's fake microphone (how faithfully
    # a loaded machine's capture keeps its timing is Chromium's business: its envelope's
    # correlation with the file was 0.70 in a CI run, above 0.9 idle)
    assert rate == 16_000 and len(audio) / rate >= 0.8 * spoken.duration_s
    frames = audio[: len(audio) // 160 * 160].reshape(-1, 160)
    level = 10 * np.log10(np.mean(frames.astype(np.float64) ** 2, axis=1) + 1e-12)
    assert level.max() > -30 and np.mean(level > -45) > 0.15  # speech (0.43 idle), not silence
    # the track shown is the offline chain on the recorded audio, at the warp the live
    # analysis had reached: each stretch between two warp changes is that warp's analysis
    protocol = load_protocol(KATO)
    avatar = load_avatar(protocol, base_dir=KATO.parent)
    track = read_track(folder / "track.bin")
    cond = protocol.condition("emphasized")
    changes = record["analysis_warps"]
    assert changes[0] == [0.0, 1.0]
    # a change after n samples: frames up to about n/160 - 3 were made at the old warp, the
    # next one mixes the two (the lag compensation's next frame), later ones the new warp
    ends = [round(at * 100) - 3 for at, _ in changes[1:]] + [len(track.values)]
    checked = 0
    for (at, warp), stop in zip(changes, ends, strict=True):
        start = 0 if at == 0 else round(at * 100) - 1
        ref = offline_frames(audio.astype(np.float64), method=cond.method,
                             params=cond.settings, avatar=avatar, names=tuple(track.names),
                             base_dir=KATO.parent, warp=warp)  # fmt: skip
        assert ref.shape == track.values.shape
        if stop > start:
            assert np.abs(track.values[start:stop] - ref[start:stop]).max() < 1e-5, (at, warp)
            checked += stop - start
    assert checked > 0.9 * len(track.values)
    # the viewer's still: the canvas at the offline size, drawn at a frame with the mouth moved
    from PIL import Image

    assert Image.open(shot).size == (1280, 720)
    snapped = record["screenshot_frame"]  # the most moved face drawn, or one past 0.25
    assert 0 <= snapped["frame"] < len(track.values)
    assert snapped["peak"] == pytest.approx(float(track.values[snapped["frame"]].max()), abs=1e-6)
    # the recorded turn rendered under two conditions
    clips = tmp_path / "clips"
    assert main(["render", str(KATO), "--turn", str(folder), "--out", str(clips),
                 "--size", "320x180", "--quiet"]) == 0  # fmt: skip
    rows = read_manifest(clips)
    assert {r["condition"] for r in rows} == {"baseline", "standard", "emphasized"}
    assert {r["stimulus"] for r in rows} == {folder.name}
    with pytest.raises(FacelabError):
        turns_protocol(KATO, [tmp_path / "nowhere"])


@pytest.mark.slow
def test_a_simulated_live_turn_in_an_emulated_headset(tmp_path) -> None:
    """--display webxr: the viewer enters VR in an emulated headset (IWER) and the turn is
    drawn in the immersive session, within the budget; the viewer says it showed VR."""
    talk = tmp_path / "talk.wav"
    sf.write(talk, synthesize("はい、わかりました。すぐに行きます。", sample_rate=24_000).samples,
             24_000, subtype="PCM_16")  # fmt: skip
    out, shot = tmp_path / "live.json", tmp_path / "vr.png"
    assert main(["live", str(KATO), "--condition", "standard", "--display", "webxr",
                 "--simulate", str(talk), "--json", str(out), "--screenshot", str(shot),
                 "--session", str(tmp_path / "session"), "--playout-ms", "1000"]) == 0  # fmt: skip
    record = json.loads(out.read_text())
    assert record["viewer_displays"] == {"1": "webxr"}
    # an emulated headset's frames come every 150-500 ms idle, fewer on a loaded machine
    drawn_right(Path(record["recording"]), record)
    from PIL import Image

    picture = np.asarray(Image.open(shot).convert("L"), float)
    left, right = picture[:, : picture.shape[1] // 2], picture[:, picture.shape[1] // 2 :]
    assert left.std() > 10 and right.std() > 10  # both eyes' views show the avatar


# --------------------------------------------------------------------------- the lab window


def _facelab() -> str:
    import sys

    return str(Path(sys.executable).with_name("facelab"))


def _sound_home(folder: Path, *, device: str) -> dict[str, str]:
    """The environment of a ``facelab live`` whose ALSA default output is ``device``: ALSA's
    null output (written at once, never heard: this machine has no sound card) or one that
    cannot open."""
    import os

    folder.mkdir(parents=True, exist_ok=True)
    pcm = "type null" if device == "null" else "type hw\n  card 99"
    (folder / ".asoundrc").write_text(f"pcm.!default {{\n  {pcm}\n}}\n")
    return {**os.environ, "HOME": str(folder)}


def test_the_window_is_refused_without_a_sound_output(tmp_path) -> None:
    """A lab machine whose PortAudio finds no output: the participant could not hear the
    talker, so the window is refused in words, before anything is recorded."""
    import subprocess

    env = _sound_home(tmp_path / "home", device="none")
    done = subprocess.run(
        [_facelab(), "live", str(KATO), "--condition", "standard",
         "--display", "window", "--input", str(tmp_path / "none.wav"), "--session",
         str(tmp_path / "never")], env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 2  # the missing input file is said first
    assert "none.wav: no such audio file" in done.stderr
    talk = tmp_path / "talk.wav"
    sf.write(talk, synthesize("はい。", sample_rate=16_000).samples, 16_000)
    done = subprocess.run(
        [_facelab(), "live", str(KATO), "--condition", "standard",
         "--display", "window", "--input", str(talk), "--session", str(tmp_path / "never")],
        env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert "no usable sound output" in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "never").exists()


def test_render_size_keeps_the_protocol_s_frame_inside_the_window() -> None:
    from facelab.experiment.live_dialogue.window_view import render_size

    assert render_size(width=1280, height=720, window=(1280, 800)) == (1280, 720)
    assert render_size(width=1280, height=720, window=(960, 600)) == (960, 540)
    assert render_size(width=1280, height=720, window=(1920, 1080)) == (1280, 720)  # not up
    assert render_size(width=720, height=1280, window=(1280, 800)) == (450, 800)


@pytest.mark.slow
def test_a_simulated_live_turn_in_the_lab_window(tmp_path) -> None:
    """--display window: the talker page (Chromium, the file as its microphone) drives the
    avatar in the lab's PsychoPy window, drawn by the offline renderer, the sound on the
    machine's output (ALSA's null device here); the turn is recorded with the window's frame
    log, each frame the one of the sound heard at its flip (or older, late), and the window's
    still is the offline picture of the frame it says it showed."""
    import subprocess

    from PIL import Image

    from facelab.stimuli.render.renderer import Renderer
    from facelab.stimuli.render.scene import settings_for

    talk = tmp_path / "talk.wav"
    sf.write(talk, synthesize("はい、わかりました。すぐに行きます。", sample_rate=24_000).samples,
             24_000, subtype="PCM_16")  # fmt: skip
    out, shot = tmp_path / "live.json", tmp_path / "window.png"
    done = subprocess.run(
        [_facelab(), "live", str(KATO), "--condition", "emphasized",
         "--display", "window", "--windowed", "--size", "960x600", "--simulate", str(talk),
         "--json", str(out), "--screenshot", str(shot), "--session", str(tmp_path / "s"),
         "--playout-ms", "1000"],
        env=_sound_home(tmp_path / "home", device="null"), capture_output=True, text=True,
        timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    record = json.loads(out.read_text())
    assert record["viewer_displays"] == {"1": "window"}
    folder = Path(record["recording"])
    # the window asks for the frame of the flip that will show it (the render takes 30-60 ms
    # here), at most LEAD_MAX_S ahead: a flip sooner than expected shows it that much ahead
    drawn_right(folder, record, ahead_ms=LEAD_MAX_S * 1000)
    track = read_track(folder / "track.bin")
    snapped = record["screenshot_frame"]
    assert 0 <= snapped["frame"] < len(track.values)
    assert snapped["peak"] == pytest.approx(float(track.values[snapped["frame"]].max()), abs=1e-4)
    # the still: the window (960 x 600) with the protocol's 1280 x 720 frame scaled to fit,
    # centred; it is the offline renderer's picture of the frame the window logged
    window = np.asarray(Image.open(shot).convert("RGB"), float)
    assert window.shape == (600, 960, 3)
    shown = window[30:570]
    protocol = load_protocol(KATO)
    avatar = load_avatar(protocol, base_dir=KATO.parent)
    weights = np.zeros(len(avatar.target_names))
    for name, value in zip(track.names, track.values[snapped["frame"]], strict=True):
        weights[avatar.target_names.index(name)] = value
    from dataclasses import replace

    with Renderer(avatar, replace(settings_for(protocol), width=960, height=540)) as r:
        offline, rest = r.frame(weights).astype(float), r.frame(weights * 0).astype(float)
    assert shown.std() > 10  # the avatar, not a uniform picture
    err = np.abs(shown - offline).mean()
    assert err < 3.0, err  # the same picture, the right way up (display rounding only)
    mouth = np.abs(offline - rest).sum(axis=2) > 30  # where the moved mouth differs from rest
    assert mouth.sum() > 50
    assert np.abs(shown - offline)[mouth].mean() < np.abs(shown - rest)[mouth].mean()
