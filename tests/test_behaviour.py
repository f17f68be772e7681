"""Emotional behaviour (seed 003, EMBOS): library rules, eqs. 2-5 against hand-computed
answers, the planner's guarantees (determinism, yoking, ω_l, triggers, blink statistics),
realisation on speech, protocols, clips with event logs, the CLI and the covariate model."""

from __future__ import annotations

import itertools
import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy import stats as sps

from facelab.emotions import EMOTIONS
from facelab.errors import BehaviourError
from facelab.experiment.cli import main
from facelab.protocol import ProtocolError, load_protocol
from facelab.stimuli.avatar import default_head
from facelab.stimuli.behaviour.fit import check_annotations, fit_library, read_annotations
from facelab.stimuli.behaviour.library import (
    LAYERS,
    Library,
    default_library,
    is_speech_channel,
    load_library,
)
from facelab.stimuli.behaviour.plan import (
    EmotionTimeline,
    Plan,
    SpeechCues,
    blend,
    complete_emotion,
    parse_emotion,
    plan_behaviour,
)
from facelab.stimuli.behaviour.realise import apply_to_weights, curve_values, realise

# ------------------------------------------------------------------ the annotation table


def _known_table() -> pd.DataFrame:
    """A table whose eq. 2-3 answers are worked out by hand in the tests below."""
    rows = [
        # postures: joy 60 s annotated (upright 40, tilt 20); anger 40 s (upright 10, chin 30+)
        ("joy", "posture", "upright", 0, 40),
        ("joy", "posture", "tilt", 40, 60),
        ("anger", "posture", "upright", 100, 110),
        ("anger", "posture", "chin", 110, 140),
        ("anger", "posture", "chin", 140, 150),
        # mannerisms: joy glance x3 (1 s); anger glance x1 (2 s), squint x3 (1 s)
        ("joy", "mannerism", "glance", 5, 6),
        ("joy", "mannerism", "glance", 15, 16),
        ("joy", "mannerism", "glance", 25, 26),
        ("anger", "mannerism", "glance", 101, 103),
        ("anger", "mannerism", "squint", 111, 112),
        ("anger", "mannerism", "squint", 121, 122),
        ("anger", "mannerism", "squint", 131, 132),
        # gestures with a tie in share: joy nod x2, shake x2; anger shake x2
        ("joy", "gesture", "nod", 1, 1.5),
        ("joy", "gesture", "nod", 2, 2.5),
        ("joy", "gesture", "shake", 3, 4),
        ("joy", "gesture", "shake", 7, 8),
        ("anger", "gesture", "shake", 104, 105),
        ("anger", "gesture", "shake", 106, 107),
    ]
    return pd.DataFrame(rows, columns=["emotion", "layer", "behaviour", "start_s", "end_s"])


@pytest.fixture(scope="module")
def fitted() -> tuple[Library, pd.DataFrame]:
    return fit_library(check_annotations(_known_table()), alpha=0.3)


def _cell(stats: pd.DataFrame, behaviour: str, emotion: str) -> pd.Series:
    row = stats[(stats["behaviour"] == behaviour) & (stats["emotion"] == emotion)]
    assert len(row) == 1, (behaviour, emotion)
    return row.iloc[0]


def test_posture_intensity_and_wait_by_hand(fitted: tuple[Library, pd.DataFrame]) -> None:
    _, stats = fitted
    # joy: D = 2; share upright 40/60 (r 1), tilt 20/60 (r 2); universality upright 40/50 = 0.8
    # (n 2), tilt 20/20 = 1 (n 1); E(1) = 1, E(2) = 0.5
    up = _cell(stats, "upright", "joy")
    assert up["universality"] == pytest.approx(0.8)
    assert (up["rank_share"], up["rank_universality"]) == (1, 2)
    assert up["intensity"] == pytest.approx(0.3 * 1 + 0.7 * 0.5)
    assert _cell(stats, "tilt", "joy")["intensity"] == pytest.approx(0.3 * 0.5 + 0.7 * 1)
    # anger: chin 40 s of 50 -> r 1, s 1 -> 1; upright share 0.2, s 0.2 -> both rank 2
    assert _cell(stats, "chin", "anger")["intensity"] == pytest.approx(1.0)
    assert _cell(stats, "upright", "anger")["intensity"] == pytest.approx(0.5)
    # eq. 3 with L_e(joy) = 60: upright (60 - 40)/40 * 40 = 20; tilt (60 - 20)/20 * 20 = 40
    assert up["wait_s"] == pytest.approx(20.0)
    assert _cell(stats, "tilt", "joy")["wait_s"] == pytest.approx(40.0)
    # chin in anger: two occurrences (30 s, 10 s): mean 20, total 40, L_e 50 -> (10/40)*20
    chin = _cell(stats, "chin", "anger")
    assert (chin["duration_s"], chin["L_e"]) == (pytest.approx(20.0), pytest.approx(50.0))
    assert chin["wait_s"] == pytest.approx(5.0)


def test_mannerism_and_gesture_intensities_by_hand(fitted: tuple[Library, pd.DataFrame]) -> None:
    library, stats = fitted
    # joy: glance is the only mannerism (D = 1) -> 1; L_w = (60 - 3)/3 * 1 = 19
    g = _cell(stats, "glance", "joy")
    assert (g["intensity"], g["wait_s"]) == (pytest.approx(1.0), pytest.approx(19.0))
    # anger: glance 1 of 4 (share r 2), s = 1/4 (n 2) -> 0.5; squint -> 1; L_w(squint) =
    # (50 - 3)/3 * 1
    assert _cell(stats, "glance", "anger")["intensity"] == pytest.approx(0.5)
    assert _cell(stats, "squint", "anger")["wait_s"] == pytest.approx(47 / 3)
    # ties share the smallest rank: joy nod and shake both 2 of 4 -> r = 1 for both;
    # universality nod 1 (n 1), shake 2/4 (n 2) -> nod 1, shake 0.3 + 0.7 * 0.5
    nod, shake = _cell(stats, "nod", "joy"), _cell(stats, "shake", "joy")
    assert nod["rank_share"] == shake["rank_share"] == 1
    assert nod["intensity"] == pytest.approx(1.0)
    assert shake["intensity"] == pytest.approx(0.65)
    # behaviours not observed in an emotion get 0; the library carries all seven emotions
    unit = library.unit("tilt")
    assert unit.intensity["anger"] == 0.0 and len(unit.intensity) == 7
    assert "anger" not in unit.duration_s
    # continuity from transitions: joy postures upright -> tilt seen once
    assert library.continuity["upright"]["tilt"] == pytest.approx(1.0)


def test_annotation_errors_name_the_row(tmp_path: Path) -> None:
    bad = _known_table()
    bad.loc[3, "emotion"] = "happy"
    with pytest.raises(BehaviourError, match=r"row 4: emotion 'happy'"):
        check_annotations(bad)
    bad = _known_table()
    bad.loc[0, "end_s"] = 0
    with pytest.raises(BehaviourError, match=r"row 1: .*end_s > start_s"):
        check_annotations(bad)
    with pytest.raises(BehaviourError, match="missing column"):
        check_annotations(_known_table().drop(columns=["layer"]))
    no_posture = _known_table()
    no_posture = no_posture[~((no_posture.emotion == "anger") & (no_posture.layer == "posture"))]
    with pytest.raises(BehaviourError, match="'anger' has no posture annotation"):
        fit_library(check_annotations(no_posture))
    with pytest.raises(BehaviourError, match="no such annotation file"):
        read_annotations(tmp_path / "missing.csv")


def test_annotation_tables_as_spreadsheets_save_them(tmp_path: Path) -> None:
    """Excel's "CSV UTF-8" starts with a byte-order mark (refused as a missing emotion column
    before); a TSV reads as the CSV does; a row with a field too many is named by its line."""
    text = _known_table().to_csv(index=False)
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + text.encode("utf-8"))
    pd.testing.assert_frame_equal(read_annotations(bom), check_annotations(_known_table()),
                                  check_dtype=False)  # fmt: skip
    tsv = tmp_path / "ann.tsv"
    tsv.write_text(_known_table().to_csv(index=False, sep="\t"), encoding="utf-8")
    assert len(read_annotations(tsv)) == len(_known_table())
    lines = text.splitlines()
    lines[4] += ",extra"
    (tmp_path / "long.csv").write_text("\n".join(lines), encoding="utf-8")
    with pytest.raises(BehaviourError, match=r"long\.csv:5: 6 fields, the header has 5"):
        read_annotations(tmp_path / "long.csv")
    # pympi's own words ("Unable to parse eaf", a KeyError's 'VERSION') are not the message
    (tmp_path / "bare.eaf").write_text("<ANNOTATION_DOCUMENT></ANNOTATION_DOCUMENT>\n")
    with pytest.raises(BehaviourError, match=r"bare\.eaf: not a readable ELAN file \(an \.eaf "):
        read_annotations(tmp_path / "bare.eaf")


def test_elan_file_reads_like_the_csv(tmp_path: Path) -> None:
    from pympi.Elan import Eaf, to_eaf

    table = _known_table()
    eaf = Eaf(author="facelab test")
    eaf.add_tier("emotion")
    eaf.add_annotation("emotion", 0, 90_000, "joy")
    eaf.add_annotation("emotion", 90_000, 160_000, "anger")
    for layer in ("posture", "mannerism", "gesture"):
        eaf.add_tier(layer)
    for r in table.itertuples():
        eaf.add_annotation(r.layer, round(r.start_s * 1000), round(r.end_s * 1000), r.behaviour)
    path = tmp_path / "ann.eaf"
    to_eaf(str(path), eaf)
    from_eaf = read_annotations(path)
    assert len(from_eaf) == len(table)
    lib_csv, _ = fit_library(check_annotations(table))
    lib_eaf, _ = fit_library(from_eaf)
    assert {u.behaviour: u.intensity for u in lib_csv.units} == {
        u.behaviour: u.intensity for u in lib_eaf.units
    }


# ------------------------------------------------------------------ the library


def test_default_library_loads_with_sources() -> None:
    lib = default_library()
    assert {u.layer for u in lib.units} == set(LAYERS)
    assert len(lib.sources) >= 5 and all(u.source for u in lib.units)
    assert all(u.has_motion for u in lib.units)


def test_speech_channels_are_refused(tmp_path: Path) -> None:
    assert is_speech_channel("jawOpen") and is_speech_channel("mouthPressLeft")
    assert not is_speech_channel("mouthSmileLeft") and not is_speech_channel("mouthDimpleRight")
    data = default_library().model_dump(mode="json")
    data["units"][1]["channels"] = {"mouthPressLeft": 0.4}
    path = tmp_path / "lib.json"
    path.write_text(json.dumps(data))
    with pytest.raises(BehaviourError, match=r"units\.1.*'upright'.*belongs to speech"):
        load_library(path)
    data["units"][1]["channels"] = {"browDownLeft": 0.4}
    data["units"][1]["intensity"]["happy"] = 0.4
    path.write_text(json.dumps(data))
    with pytest.raises(BehaviourError, match="unknown emotion"):
        load_library(path)


def test_library_yaml_is_read_like_protocols(tmp_path: Path) -> None:
    """libyaml's parser (PyYAML's own rejects ``{en: Why?}``) and the protocol's limits."""
    from facelab.protocol_yaml import read_data

    assert read_data("q: {en: How friendly did this face look?}") == {
        "q": {"en": "How friendly did this face look?"}
    }
    bomb = "a: &a [x, x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{c}: &{c} [*{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}]\n"
        for p, c in zip("abcdefgh", "bcdefghi", strict=True)
    )
    path = tmp_path / "bomb.yaml"
    path.write_text(bomb, encoding="utf-8")
    with pytest.raises(BehaviourError, match=r"bomb\.yaml: not readable.*alias"):
        load_library(path)


def test_fitted_library_takes_motions_by_name(fitted: tuple[Library, pd.DataFrame]) -> None:
    library, _ = fitted
    motions = default_library()
    renamed = library.model_copy(
        update={
            "units": [
                u.model_copy(
                    update={
                        "behaviour": {"chin": "chin_up", "tilt": "head_tilt_smile"}.get(
                            u.behaviour, u.behaviour
                        )
                    }
                )
                for u in library.units
            ],
            "continuity": {},
        }
    )
    merged, missing = renamed.with_motions(motions)
    assert missing == ["glance"]
    assert merged.unit("chin_up").channels == motions.unit("chin_up").channels
    assert merged.unit("chin_up").intensity == renamed.unit("chin_up").intensity


# ------------------------------------------------------------------ eqs. 4 and 5


def test_neutral_by_eq4_and_blend_by_eq5() -> None:
    assert complete_emotion({"joy": 0.3, "anger": 0.2})[-1] == pytest.approx(0.5)
    assert complete_emotion({"joy": 0.8, "anger": 0.5})[-1] == 0.0
    assert complete_emotion({"neutral": 0.2})[-1] == 1.0  # a given neutral is replaced
    with pytest.raises(BehaviourError, match="intensities lie in"):
        complete_emotion({"joy": 1.5})
    with pytest.raises(BehaviourError, match="name=value"):
        parse_emotion("happy=1")
    char = complete_emotion({"joy": 0.8})  # neutral 0.2
    w_joy, w_neu = np.exp(-(0.2**2) / 0.25), np.exp(-(0.8**2) / 0.25)
    expected = (w_joy * 2.0 + w_neu * 6.0) / (w_joy + w_neu)
    assert blend({"joy": 2.0, "neutral": 6.0}, char, radius=0.5) == pytest.approx(expected)


# ------------------------------------------------------------------ the planner


def _cues() -> SpeechCues:
    return SpeechCues(
        words=(("いいえ", 0.6, 1.0), ("本当", 3.0, 3.4)),
        accents=tuple(np.arange(0.8, 9.0, 0.7)),
        phrase_ends=(4.0, 9.0),
        speaking=((0.5, 4.0), (4.5, 9.0)),
        pauses=(4.0,),
    )


def test_plan_is_deterministic_and_seeded() -> None:
    lib = default_library()
    emo = EmotionTimeline.constant({"joy": 0.8})
    a = plan_behaviour(lib, emotion=emo, duration_s=12, seed=4, cues=_cues()).to_json()
    b = plan_behaviour(lib, emotion=emo, duration_s=12, seed=4, cues=_cues()).to_json()
    c = plan_behaviour(lib, emotion=emo, duration_s=12, seed=5, cues=_cues()).to_json()
    assert a == b
    assert a["events"] != c["events"]
    again = Plan.from_json(json.loads(json.dumps(a)))
    assert again.to_json() == a


@pytest.mark.parametrize("emotion", ["joy", "anger", "sadness", "fear", "disgust", "surprise"])
def test_plan_respects_layers_channels_and_triggers(emotion: str) -> None:
    lib = default_library()
    cues = _cues()
    plan = plan_behaviour(
        lib, emotion=EmotionTimeline.constant({emotion: 0.8}), duration_s=10, seed=2, cues=cues
    )
    for layer in LAYERS:  # one unit per layer at a time
        ev = sorted((e for e in plan.events if e.layer == layer), key=lambda e: e.start_s)
        assert all(b.start_s >= a.end_s - 1e-9 for a, b in itertools.pairwise(ev))
    for i, a in enumerate(plan.events):  # ω_l: units sharing a channel never overlap
        for b in plan.events[i + 1 :]:
            if a.layer != b.layer and set(a.channels) & set(b.channels):
                assert a.end_s <= b.start_s + 1e-9 or b.end_s <= a.start_s + 1e-9, (a, b)
    triggers = {t for t, _ in cues.trigger_times(lib.unit("nod"))}
    triggers |= {t for t, _ in cues.trigger_times(lib.unit("shake"))}
    triggers |= {t for t, _ in cues.trigger_times(lib.unit("brow_raise"))}
    for e in plan.events:
        if e.layer == "gesture":  # the stroke lands on its trigger (within one step)
            assert e.trigger is not None
            assert min(abs(e.sync["stroke"] - t) for t in triggers) <= lib.step_s + 1e-9
        assert e.end_s <= plan.duration_s + 1e-9 or e.layer == "posture"


def test_emotion_picks_its_units() -> None:
    lib = default_library()
    counts = {}
    for emotion in ("sadness", "joy", "disgust"):
        plan = plan_behaviour(
            lib, emotion=EmotionTimeline.constant({emotion: 1.0}), duration_s=60, seed=3
        )
        posture = {}
        for e in plan.events:
            if e.layer == "posture":
                posture[e.unit] = posture.get(e.unit, 0) + e.end_s - e.start_s
        counts[emotion] = max(posture, key=posture.get)
    assert counts == {"sadness": "head_down", "joy": "head_tilt_smile", "disgust": "turn_away"}


def test_blinks_at_human_rates() -> None:
    lib = default_library()
    neutral = EmotionTimeline.constant({"neutral": 1.0})
    rates, rates_speaking, intervals = [], [], []
    talk = SpeechCues(speaking=((0.0, 600.0),))
    for seed in range(3):
        plan = plan_behaviour(lib, emotion=neutral, duration_s=600, seed=seed, layers=("blink",))
        starts = np.array([e.start_s for e in plan.events])
        rates.append(len(starts) / 10)
        intervals += list(np.diff(starts))
        spk = plan_behaviour(
            lib, emotion=neutral, duration_s=600, seed=seed, cues=talk, layers=("blink",)
        )
        rates_speaking.append(len(spk.events) / 10)
    rest, speaking = float(np.mean(rates)), float(np.mean(rates_speaking))
    assert 14 <= rest <= 20, rest  # Bentivoglio 1997: 17/min at rest
    assert 22 <= speaking <= 30, speaking  # 26/min in conversation
    log_iv = np.log(np.array(intervals) - 0.25 + 1e-3)
    assert np.std(np.array(intervals)) / np.mean(intervals) > 0.35  # irregular, not a clock
    assert abs(float(pd.Series(log_iv).skew())) < 1.0  # roughly log-normal
    curve = lib.unit("blink").curve
    assert curve is not None and curve.phase("relax") < 0.5  # fast close, slow reopen


def test_behaviour_modes_are_yoked_with_composite() -> None:
    from facelab.stimuli.behaviour.clip import layers_for

    lib = default_library()
    emo = EmotionTimeline.constant({"anger": 0.8})

    def plan(mode: str):
        layers, neutral = layers_for(mode)
        return plan_behaviour(
            lib, emotion=emo, duration_s=10, seed=9, cues=_cues(), layers=layers,
            neutral_layers=neutral,
        )  # fmt: skip

    comp, gest, control = plan("composite"), plan("gestures_only"), plan("neutral_composite")
    blinks = [(e.start_s, e.end_s) for e in comp.events if e.layer == "blink"]
    for other in (gest, control):
        assert blinks == [(e.start_s, e.end_s) for e in other.events if e.layer == "blink"]
    # the seed's gesture-only condition: postures and mannerisms do not change at all
    assert {e.layer for e in gest.events} <= {"gesture", "blink"}
    assert any(e.layer == "gesture" for e in gest.events)
    # the control plans them, for a neutral character
    postures = {e.unit for e in control.events if e.layer == "posture"}
    assert postures and "chin_up" not in postures and "chin_up" in {e.unit for e in comp.events}


def test_bml_export_is_xml_with_sync_points() -> None:
    lib = default_library()
    plan = plan_behaviour(
        lib, emotion=EmotionTimeline.constant({"joy": 0.8}), duration_s=8, seed=1, cues=_cues()
    )
    root = ET.fromstring(plan.to_bml(lib).encode())
    assert root.tag.endswith("bml") and len(root) == len(plan.events)
    nods = [el for el in root if el.get("lexeme") == "NOD"]
    assert nods and all(
        float(n.get("start")) < float(n.get("stroke")) < float(n.get("end")) for n in nods
    )


# ------------------------------------------------------------------ realisation


def test_realisation_leaves_speech_channels_and_reports_clamping() -> None:
    avatar = default_head()
    lib = default_library()
    fps, n = 30, 300
    plan = plan_behaviour(
        lib, emotion=EmotionTimeline.constant({"joy": 1.0}), duration_s=n / fps, seed=1,
        cues=_cues(),
    )  # fmt: skip
    frames = realise(plan, lib, fps=fps, n_frames=n)
    rng = np.random.default_rng(0)
    speech = rng.uniform(0, 1, size=(n, len(avatar.target_names))).astype(np.float32)
    out, poses, report = apply_to_weights(
        frames, speech, target_names=avatar.target_names, has_head=True, has_eyes=True
    )
    for j, name in enumerate(avatar.target_names):
        if is_speech_channel(name) or name.startswith("viseme_"):
            np.testing.assert_array_equal(out[:, j], speech[:, j])
    assert out.min() >= 0 and out.max() <= 1
    smile = avatar.target_names.index("mouthSmileLeft")
    assert np.any(out[:, smile] > speech[:, smile])  # the corner channels add to speech
    assert report["clamped_frames"].get("mouthSmileLeft", 0) > 0
    nods = [e for e in plan.events if e.unit == "nod"]
    assert nods and poses[round(nods[0].sync["stroke"] * fps)].pitch > 3
    # an avatar without joints: head motion dropped and said so; gaze through eyeLook*
    _, poses2, report2 = apply_to_weights(
        frames, speech * 0, target_names=avatar.target_names, has_head=False, has_eyes=False
    )
    assert all(p is None or (p.yaw, p.pitch, p.roll) == (0, 0, 0) for p in poses2)
    assert "neck_*/head_*" in report2["dropped"]


def test_curve_is_smooth_between_keys() -> None:
    curve = default_library().unit("nod").curve
    assert curve is not None
    phase = np.linspace(0, 1, 101)
    v = curve_values(curve, phase)
    assert v[0] == 0 and v[-1] == 0 and v.max() == pytest.approx(1.0)
    assert np.max(np.abs(np.diff(v))) < 0.12


# ------------------------------------------------------------------ protocols and clips


def _protocol(tmp_path: Path, **cond: object) -> Path:
    text = f"""
schema_version: 1
study: {{id: beh, title: behaviour test, participants_planned: 2}}
seed: 1
conditions:
  - {{id: none, label: {{en: none}}, method: vowel_blend, behaviour: none}}
  - {{id: comp, label: {{en: composite}}, method: vowel_blend, behaviour: {cond.get("behaviour", "composite")}}}
stimulus_sets:
  - id: s
    stimuli:
      - {{id: joy_a, text: いいえ、本当にそう思います。, emotion: {{joy: 0.9}}}}
tasks:
  - id: which
    type: identify
    question: {{en: Which emotion?}}
    labels: [{{id: joy, text: {{en: joy}}}}, {{id: anger, text: {{en: anger}}}}]
    answers: {{joy_a: joy}}
blocks:
  - {{id: b, stimulus_set: s, sets: 1, presentations_per_condition: 1}}
  - {{id: c, stimulus_set: s, task: which, sets: 1, presentations_per_condition: 1}}
items:
  - {{id: human, question: {{en: human?}}, left_anchor: {{en: not at all}}, right_anchor: {{en: very}}}}
presentation: {{language: en}}
rendering: {{width: 160, height: 120, fps: 15, pad_s: 0.4, msaa: 1}}
simulation:
  effects: {{none: 0, comp: 10}}
  identifier: {{accuracy: 0.8}}
"""  # noqa: E501
    path = tmp_path / "p.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def test_protocol_behaviour_settings_are_validated(tmp_path: Path) -> None:
    p = load_protocol(_protocol(tmp_path))
    assert p.condition("comp").behaviour == "composite"
    task = p.tasks[0]
    assert task.target(condition="comp", stimulus="joy_a") == "joy"
    with pytest.raises(ProtocolError, match="behaviour 'wild'"):
        load_protocol(_protocol(tmp_path, behaviour="wild"))
    with pytest.raises(ProtocolError, match=r"behaviour library .*missing\.json was not found"):
        load_protocol(_protocol(tmp_path, behaviour="missing.json"))


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("behclips")
    proto = _protocol(tmp)
    assert main(["render", str(proto), "--out", str(tmp / "clips"), "--quiet"]) == 0
    return tmp


def test_clips_carry_event_logs_and_yoked_seeds(rendered: Path) -> None:
    clips = rendered / "clips"
    log = json.loads((clips / "s__joy_a__comp.behaviour.json").read_text())
    meta = json.loads((clips / "s__joy_a__comp.json").read_text())
    assert log["mode"] == "composite" and log["events"]
    assert meta["behaviour"]["counts"] == log["counts"]
    assert not (clips / "s__joy_a__none.behaviour.json").exists()
    from facelab.stimuli.render.clip import decode_frames

    a = decode_frames(clips / "s__joy_a__none.mp4", width=160, height=120)
    b = decode_frames(clips / "s__joy_a__comp.mp4", width=160, height=120)
    assert a.shape == b.shape
    per_frame = np.abs(a.astype(int) - b.astype(int)).max(axis=(1, 2, 3))
    assert np.count_nonzero(per_frame > 40) >= 5  # the head visibly moves in many frames
    # rendering again reuses every clip (the plan is deterministic)
    before = (clips / "s__joy_a__comp.mp4").stat().st_mtime_ns
    assert main(["render", str(rendered / "p.yaml"), "--out", str(clips), "--quiet"]) == 0
    assert (clips / "s__joy_a__comp.mp4").stat().st_mtime_ns == before


def test_analysis_uses_behaviour_counts_as_covariates(rendered: Path) -> None:
    proto = rendered / "p.yaml"
    res = rendered / "results"
    assert (
        main(["simulate", str(proto), "--participants", "6", "--sim-seed", "1",
              "--results", str(res)])
        == 0
    )
    assert (
        main(["analyze", str(proto), str(res), "--force", "--clips", str(rendered / "clips")])
        == 0
    )
    folder = res / "beh" / "analysis"
    counts = pd.read_csv(folder / "behaviour_counts.csv")
    assert set(counts["condition"]) == {"comp"} and counts["n_blink"].iloc[0] >= 0
    cov = pd.read_csv(folder / "behaviour_covariates.csv")
    assert "C(condition)[T.comp]" in set(cov["term"])  # against the protocol's first condition
    assert cov["note"].iloc[0].startswith("reference: none")
    # identification answers get the same covariates (one clip per condition here, so each
    # count is fixed by the condition and dropped, and named)
    ident_cov = pd.read_csv(folder / "identification_covariates.csv")
    assert set(ident_cov["term"]) == {"Intercept", "C(condition)[T.comp]"}
    assert "n_blink fixed by condition" in ident_cov["note"].iloc[0]
    ident = pd.read_csv(folder / "identification_summary.csv")
    pooled = ident[ident["participant"] == "pooled"].iloc[0]
    assert pooled["n"] == 12  # scored by the stimulus's answer: 6 participants x 2 clips


def test_covariate_model_condition_test_is_the_paired_analysis() -> None:
    """With the participant x condition intercept, the condition term of the covariate model
    is the paired t test of participant means (balanced, two conditions, covariates that
    only mark the condition dropped): same t, df n - 1, same p."""
    from scipy import stats as sps

    from facelab.analysis.behaviour import covariate_model

    rng = np.random.default_rng(11)
    rows = []
    for p in range(10):
        u = rng.normal(0, 8)
        for cond, effect in (("gestures_only", 0.0), ("composite", 4.0)):
            cell = rng.normal(0, 4)
            for s in range(6):
                rating = 50 + u + effect + cell + rng.normal(0, 10)
                rows.append((f"P{p:02d}", cond, f"s{s}", "human", rating))
    data = pd.DataFrame(rows, columns=["participant", "condition", "stimulus", "item", "rating"])
    data["stimulus_set"] = "set"
    counts = (
        data[["stimulus_set", "stimulus", "condition"]]
        .drop_duplicates()
        .assign(n_posture=lambda d: (d["condition"] == "composite") * 3, n_mannerism=0,
                n_gesture=2, n_blink=5)
    )  # fmt: skip
    model = covariate_model(data, counts, conditions=("gestures_only", "composite"))
    row = model[model["term"] == "C(condition)[T.composite]"].iloc[0]
    means = data.groupby(["participant", "condition"])["rating"].mean().unstack()
    paired = sps.ttest_rel(means["composite"], means["gestures_only"])
    assert row["t"] == pytest.approx(paired.statistic, rel=1e-4)
    assert row["df"] == 9 and row["p"] == pytest.approx(paired.pvalue, rel=1e-3)
    assert "n_posture fixed by condition" in row["note"] and "n_gesture constant" in row["note"]


def _null_count_clips(rng: np.random.Generator, *, n_s: int, sd: float) -> list[tuple]:
    """(stimulus, condition, n_gesture, clip effect) for n_s sentences x 2 conditions: more
    gestures in composite clips, and a clip effect (SD ``sd``) unrelated to the count."""
    return [
        (f"s{s}", c, int(rng.poisson(4 if c == "composite" else 2)), rng.normal(0, sd))
        for c in ("gestures_only", "composite")
        for s in range(n_s)
    ]


def _counts_of(clips: list[tuple]) -> pd.DataFrame:
    """The behaviour-count table of those clips (only n_gesture varies)."""
    return pd.DataFrame(
        [("set", s, c, k, 0, 0, 0) for s, c, k, _e in clips],
        columns=["stimulus_set", "stimulus", "condition", "n_gesture", "n_posture",
                 "n_mannerism", "n_blink"],
    )  # fmt: skip


def _clip_study(rng: np.random.Generator, *, n_p: int = 12, n_s: int = 8, clip_sd: float = 6.0):
    """Ratings of 2 x n_s clips whose n_gesture count has nothing to do with the ratings,
    but whose clips differ (SD ``clip_sd``) for other reasons."""
    clips = _null_count_clips(rng, n_s=n_s, sd=clip_sd)
    rows = []
    for p in range(n_p):
        u, cell = rng.normal(0, 8), {c: rng.normal(0, 4) for c in ("gestures_only", "composite")}
        for s, c, _k, e in clips:
            rows.append((f"P{p:02d}", c, s, "human", 50 + u + cell[c] + e + rng.normal(0, 10)))
    data = pd.DataFrame(rows, columns=["participant", "condition", "stimulus", "item", "rating"])
    data["stimulus_set"] = "set"
    counts = _counts_of(clips)
    return data, counts


def test_covariates_are_tested_between_clips() -> None:
    """A count that does not matter, on clips that differ for other reasons: the by-clip test
    rejects at its nominal rate; in a balanced study its estimate is the mixed model's; the
    covariate rows of covariate_model are the by-clip ones with df = clips - terms."""
    import statsmodels.formula.api as smf

    from facelab.analysis.behaviour import _with_counts, clip_regression, covariate_model

    rng = np.random.default_rng(5)
    rejected = []
    for _ in range(300):
        data, counts = _clip_study(rng)
        merged = _with_counts(data, counts, ("n_gesture",))
        fit = clip_regression(merged, covariates=("n_gesture",))
        t = fit["estimate"]["n_gesture"] / fit["se"]["n_gesture"]
        rejected.append(2 * sps.t.sf(abs(t), fit["df"]) < 0.05)
    assert 0.02 <= np.mean(rejected) <= 0.09
    assert fit["df"] == 16 - 3 and fit["clips"] == 16

    model = covariate_model(data, counts, conditions=("gestures_only", "composite"))
    row = model[model["term"] == "n_gesture"].iloc[0]
    assert row["estimate"] == pytest.approx(fit["estimate"]["n_gesture"], rel=1e-9)
    assert row["df"] == 13 and row["p"] == pytest.approx(2 * sps.t.sf(abs(t), 13), rel=1e-9)
    assert "covariates tested between 16 clips" in row["note"]
    mixed = smf.mixedlm(
        "rating ~ C(condition) + n_gesture", merged, groups=merged["participant"],
        vc_formula={"cell": "0 + C(condition)"},
    ).fit(reml=True)  # fmt: skip
    assert mixed.fe_params["n_gesture"] == pytest.approx(row["estimate"], rel=1e-4)
    assert mixed.bse_fe["n_gesture"] < 0.7 * row["se"]  # it took each rating as evidence
    # the condition term is still the paired analysis of participant means
    cond = model[model["term"] == "C(condition)[T.composite]"].iloc[0]
    assert cond["df"] == 11
    # ... and the same term between clips, for generalising over the sentences
    by_clip = model[model["term"] == "C(condition)[T.composite] (by clip)"].iloc[0]
    key = "C(condition)[T.composite]"
    assert by_clip["df"] == 13 and by_clip["se"] == pytest.approx(fit["se"][key], rel=1e-9)
    assert by_clip["estimate"] == pytest.approx(cond["estimate"], rel=1e-6)

    # two clips per condition and a covariate: 4 clips for 3 terms leave one df; with one
    # clip per condition the covariate is fixed by the condition (dropped, as before)
    few, few_counts = _clip_study(np.random.default_rng(1), n_s=1)
    few_model = covariate_model(few, few_counts, conditions=("gestures_only", "composite"))
    assert "n_gesture fixed by condition" in few_model["note"].iloc[0]
    two, two_counts = _clip_study(np.random.default_rng(2), n_s=2)
    two_counts.loc[0, "n_gesture"] = 7 if two_counts.loc[1, "n_gesture"] != 7 else 8
    two_model = covariate_model(two, two_counts, conditions=("gestures_only", "composite"))
    assert two_model.loc[two_model["term"] == "n_gesture", "df"].iloc[0] == 1


def test_covariates_are_not_tested_with_no_more_clips_than_terms() -> None:
    from facelab.analysis.behaviour import covariate_model

    data, counts = _clip_study(np.random.default_rng(4), n_s=2)
    counts[["n_posture", "n_blink"]] = np.random.default_rng(0).integers(0, 9, size=(4, 2))
    model = covariate_model(data, counts, conditions=("gestures_only", "composite"))
    cov_rows = model[model["term"].isin(["n_gesture", "n_posture", "n_blink"])]
    note = model["note"].iloc[0]
    assert "covariates not tested: 4 clips for" in note
    assert cov_rows["p"].isna().all() and cov_rows["df"].isna().all()
    assert np.isfinite(model.loc[model["term"] == "C(condition)[T.composite]", "p"]).all()


def _identification_study(rng: np.random.Generator, *, n_p: int = 12, clip_sd: float = 0.6):
    """Answers to 2 x 8 clips whose right-answer odds differ from clip to clip (logit SD
    ``clip_sd``) for reasons other than their n_gesture count."""
    clips = _null_count_clips(rng, n_s=8, sd=clip_sd)
    rows = []
    for p in range(n_p):
        u = rng.normal(0, 0.5)
        for s, c, _k, e in clips:
            right = rng.random() < 1 / (1 + np.exp(0.2 - u - e))
            rows.append((f"P{p:02d}", c, s, int(right)))
    trials = pd.DataFrame(rows, columns=["participant", "condition", "stimulus", "correct"])
    trials["stimulus_set"] = "set"
    counts = _counts_of(clips)
    return trials, counts


def test_identification_covariates_are_tested_between_clips() -> None:
    """The by-clip quasi-binomial test of a count unrelated to the answers rejects at about
    its nominal rate when clips differ; the model's covariate row is that test's; condition
    rows stay the GEE's."""
    import statsmodels.api as sm

    from facelab.analysis.behaviour import _with_counts, clip_logit, identification_covariates
    from facelab.analysis.identification import correct_model

    rng = np.random.default_rng(8)
    rejected = []
    conditions = ("gestures_only", "composite")
    for _ in range(300):
        trials, counts = _identification_study(rng)
        merged = _with_counts(trials, counts, ("n_gesture",))
        fit = clip_logit(merged, covariates=("n_gesture",), conditions=conditions)
        t = fit["estimate"]["n_gesture"] / fit["se"]["n_gesture"]
        rejected.append(2 * sps.t.sf(abs(t), fit["df"]) < 0.05)
    assert np.mean(rejected) <= 0.08
    model = identification_covariates(trials, counts, conditions=conditions)
    row = model[model["term"] == "n_gesture"].iloc[0]
    assert row["df"] == 13 and row["t"] == pytest.approx(t, rel=1e-9)
    assert np.isnan(row["se_robust"]) and "between 16 clips" in row["note"]
    parts = row["note"].split("; ")
    assert len(parts) == len(set(parts)) and "n_blink constant" in parts
    # postures only in composite clips: named once (by the GEE), not again
    composite = counts["condition"] == "composite"
    counts.loc[composite, "n_posture"] = np.arange(composite.sum()) % 3
    parts = identification_covariates(trials, counts, conditions=conditions)["note"][0].split("; ")
    assert parts.count("n_posture constant within gestures_only (0)") == 1
    # the estimate is the binomial GLM's on all answers (aggregating changes no estimate)
    x = np.column_stack(
        [np.ones(len(merged)), merged["condition"] == "composite", merged["n_gesture"]]
    ).astype(float)
    glm = sm.GLM(merged["correct"].to_numpy(float), x, family=sm.families.Binomial()).fit()
    assert row["estimate"] == pytest.approx(glm.params[2], rel=1e-6)
    gee = correct_model(merged, covariates=("n_gesture",), conditions=conditions)
    cond = model[model["term"] == "C(condition)[T.composite]"].iloc[0]
    gee_cond = gee[gee["term"] == "C(condition)[T.composite]"].iloc[0]
    assert cond["p"] == pytest.approx(gee_cond["p"], rel=1e-9) and cond["df"] == 9
    over = model[model["term"] == "C(condition)[T.composite] (by clip)"].iloc[0]
    key = "C(condition)[T.composite]"
    assert over["df"] == 13 and over["estimate"] == pytest.approx(fit["estimate"][key])
    assert over["or_ci_low"] < over["odds_ratio"] < over["or_ci_high"]
    assert list(model["term"]).index(key) + 1 == list(model["term"]).index(f"{key} (by clip)")


# ------------------------------------------------------------------ the command line


def test_cli_fit_plan_bml_figure(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ann = tmp_path / "ann.csv"
    _known_table().to_csv(ann, index=False)
    lib = tmp_path / "lib.json"
    assert main(["behaviour", "fit", str(ann), "--out", str(lib)]) == 0
    data = json.loads(lib.read_text())
    assert {"layer", "behaviour", "intensity", "duration_s", "wait_s"} <= set(data["units"][0])
    assert (tmp_path / "lib.report.md").read_text().count("|") > 20
    plan = tmp_path / "plan.json"
    args = ["behaviour", "plan", "--emotion", "joy=0.8", "--text", "はい、本当にそうですね。"]
    args += ["--duration-s", "5", "--seed", "3", "--out", str(plan)]
    args += ["--bml", str(tmp_path / "plan.xml"), "--figure", str(tmp_path / "plan.png")]
    assert main(args) == 0
    events = json.loads(plan.read_text())["events"]
    assert events and {"unit", "layer", "start_s", "end_s", "channels", "scores"} <= set(events[0])
    assert (tmp_path / "plan.png").stat().st_size > 10_000
    ET.parse(tmp_path / "plan.xml")
    assert main(["behaviour", "plan", "--emotion", "happy=1", "--duration-s", "5",
                 "--out", str(plan), "--force"]) == 2  # fmt: skip
    assert "happy=1" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_render_writes_clips_logs_and_keeps_earlier_emotions(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``behaviour render``: one clip per (emotion, mode) with its event log and timeline; a
    second render of another emotion into the folder adds to ``clips.csv``."""
    import csv

    from facelab.stimuli.render.clip import probe

    out = tmp_path / "clips"
    base = ["behaviour", "render", "--text", "はい、そうですね。", "--duration-s", "3",
            "--size", "160x90", "--msaa", "1", "--fps", "15", "--out", str(out)]  # fmt: skip
    assert main([*base, "--emotion", "joy=0.8", "--modes", "none", "composite"]) == 0
    assert main([*base, "--emotion", "sadness=1", "--modes", "composite"]) == 0
    assert "kept 2 clip(s) rendered earlier" in capsys.readouterr().out
    rows = list(csv.DictReader((out / "clips.csv").read_text(encoding="utf-8").splitlines()))
    assert [r["clip_id"] for r in rows] == [
        "joy0.8__none",
        "joy0.8__composite",
        "sadness__composite",
    ]
    for r in rows:
        video = next(s for s in probe(out / r["path"])["streams"] if s["codec_type"] == "video")
        assert int(video["nb_read_frames"]) == 45
        logged = (out / f"{r['clip_id']}.behaviour.json").is_file()
        assert logged == (r["mode"] != "none")
    checks = list(csv.DictReader((out / "stimulus_checks.csv").read_text().splitlines()))
    assert {r["clip"] for r in checks if r["measure"] == "detection_median"} == {
        r["clip_id"] for r in rows
    }  # the second render kept the first one's checks
    assert any(r["measure"] == "gaze_shown_by" for r in checks)
    events = json.loads((out / "sadness__composite.behaviour.json").read_text())
    assert int(rows[2]["n_blink"]) == sum(1 for e in events["events"] if e["layer"] == "blink")


def test_speech_cues_from_openjtalk_words_and_accents() -> None:
    from facelab.stimuli.speech.tts import synthesize

    speech = synthesize("いいえ、私はそう思いません。")
    words = [w for w in speech.words if w.morae]
    assert [w.surface for w in words][:2] == ["いいえ", "私"]
    assert all(a.start < a.end for a in speech.accents)
    assert all(w0.end <= w1.start + 1e-9 for w0, w1 in itertools.pairwise(words))
    cues = SpeechCues.from_speech(speech, offset_s=0.5)
    assert cues.words[0][1] == pytest.approx(words[0].start + 0.5)
    assert len(cues.accents) == len(speech.accents) >= 3
    shake = [t for t, what in cues.trigger_times(default_library().unit("shake"))]
    assert shake and shake[0] < 1.5  # いいえ triggers a shake


def test_the_better_suited_gesture_wins_a_shared_trigger() -> None:
    # いいえ carries an accent: nod (accent) and shake (word) both fit; in disgust the shake
    # is closer to the emotion and must not be pre-empted by the nod's earlier start
    cues = SpeechCues(words=(("いいえ", 0.6, 1.0),), accents=(0.8,), speaking=((0.5, 1.2),))
    lib = default_library()
    for emotion, expected in (("disgust", "shake"), ("joy", "nod")):
        plan = plan_behaviour(
            lib, emotion=EmotionTimeline.constant({emotion: 0.9}), duration_s=3, seed=1,
            cues=cues, layers=("gesture",),
        )  # fmt: skip
        assert [e.unit for e in plan.events] == [expected], emotion


def test_emotion_timelines_in_protocols(tmp_path: Path) -> None:
    """A condition may give the emotion as a timeline of keys; the plan follows it (the
    posture of the first half is sadness's, of the second joy's) and bad keys are named."""
    from facelab.stimuli.behaviour.clip import emotion_timeline

    keys = "[{time_s: 0, sadness: 1.0}, {time_s: 29, sadness: 1.0}, {time_s: 31, joy: 1.0}]"
    p = load_protocol(_protocol(tmp_path, behaviour=f"composite, emotion: {keys}"))
    emotion = p.condition("comp").emotion
    assert isinstance(emotion, list) and emotion[2] == {"time_s": 31, "joy": 1.0}
    timeline = emotion_timeline(emotion)
    assert timeline.at(30.0)[EMOTIONS.index("sadness")] == pytest.approx(0.5, abs=0.01)
    plan = plan_behaviour(default_library(), emotion=timeline, duration_s=60, seed=3)
    assert [k["time_s"] for k in plan.emotion] == [0, 29, 31]
    halves: dict[int, dict[str, float]] = {0: {}, 1: {}}
    for e in plan.events:
        if e.layer == "posture":
            for half, (a, b) in enumerate(((0, 30), (30, 60))):
                overlap = min(e.end_s, b) - max(e.start_s, a)
                if overlap > 0:
                    halves[half][e.unit] = halves[half].get(e.unit, 0) + overlap
    assert max(halves[0], key=halves[0].get) == "head_down"
    assert max(halves[1], key=halves[1].get) == "head_tilt_smile"
    for bad, message in (
        ("[{time_s: 2, joy: 1}, {time_s: 1, anger: 1}]", "after the previous key"),
        ("[{joy: 1}]", "no time_s"),
        ("[{time_s: 0, glee: 1}]", "unknown emotion 'glee'"),
        ("[]", "at least one key"),
    ):
        with pytest.raises(ProtocolError, match=message):
            load_protocol(_protocol(tmp_path, behaviour=f"composite, emotion: {bad}"))


@pytest.mark.slow
def test_covariate_model_keeps_alpha_when_conditions_do_not_differ() -> None:
    """The shipped behaviour protocol with no true VAS difference and random behaviour
    counts per clip, 12 simulated participants: the covariate model's condition test rejects
    in about alpha of studies (a random-intercept-only model rejected in about 15 %)."""
    from facelab.analysis.behaviour import LAYER_COUNTS, covariate_model
    from facelab.analysis.load import frame_from_rows
    from facelab.experiment.simulate import simulated_rows
    from facelab.resources import protocol_path

    protocol = load_protocol(protocol_path("hattori_behaviour"))
    sims, rejected = 100, 0
    for rng in np.random.default_rng(5).spawn(sims):
        rows = [
            row
            for i, child in enumerate(rng.spawn(12))
            for row in simulated_rows(
                protocol, participant=f"P{i + 1:02d}", rng=child,
                effects={"gestures_only": 0.0, "composite": 0.0},
            )
        ]  # fmt: skip
        data = frame_from_rows(rows)
        vas = data[(data["block"] == "rate") & (data["item"] == "human_like")]
        clips = vas[["stimulus_set", "stimulus", "condition"]].drop_duplicates()
        counts = clips.assign(
            **{
                c: rng.poisson(lam, len(clips))
                for c, lam in zip(LAYER_COUNTS, (3, 4, 3, 8), strict=True)
            }
        )
        model = covariate_model(vas, counts, conditions=("gestures_only", "composite"))
        rejected += int(model.loc[model["term"].str.startswith("C("), "p"].iloc[0] < 0.05)
    assert rejected / sims <= 0.05 + 2 * np.sqrt(0.05 * 0.95 / sims)


def test_emotion_timeline_keys_steps_and_bad_times() -> None:
    """Two keys at one time make a step in the order given (they were ordered by their
    values); a NaN or infinite time was accepted."""
    tl = EmotionTimeline.from_keys(
        [(4.0, {"fear": 1.0}), (2.0, {"sadness": 1.0}), (2.0, {"joy": 1.0}), (0.0, {"joy": 0.0})]
    )
    joy, sadness = EMOTIONS.index("joy"), EMOTIONS.index("sadness")
    assert tl.at(1.999)[sadness] == pytest.approx(0.9995, abs=1e-3)  # towards the first key
    assert tl.at(2.001)[joy] == pytest.approx(0.9995, abs=1e-3)  # on from the second
    for t in (float("nan"), float("inf")):
        with pytest.raises(BehaviourError, match="not a finite number"):
            EmotionTimeline.from_keys([(0.0, {"joy": 1.0}), (t, {"fear": 1.0})])
