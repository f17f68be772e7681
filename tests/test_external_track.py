"""method: external_track (issue 49): animations made elsewhere, read from the formats other
tools write (files made by tests/external_track_files.py with known values), resampled to the
clip, aligned by their recording, refused in words when they cannot be used, and played as a
protocol condition beside the built-in methods."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from facelab.errors import StageError
from facelab.stimuli.arkit import ARKIT_NAMES, VISEME_TARGETS
from facelab.stimuli.capture.external_tracks import detect_format, read_capture, resample
from facelab.stimuli.methods.external_track import align_offset_s
from tests.external_track_files import (
    ANGLES,
    arkit_json,
    audio2face_json,
    gltf_animation,
    live_link_face_csv,
    viseme_csv,
)
from tests.protocol_edits import kato_vowels_only


def _truth(fps: float, seconds: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """(times, (T, 52) weights): jawOpen and mouthFunnel rise and fall, the rest 0."""
    t = np.arange(round(seconds * fps)) / fps
    w = np.zeros((len(t), 52))
    w[:, ARKIT_NAMES.index("jawOpen")] = 0.5 - 0.5 * np.cos(2 * np.pi * t / seconds)
    w[:, ARKIT_NAMES.index("mouthFunnel")] = 0.3 * np.sin(np.pi * t / seconds) ** 2
    return t, w


def _at(times: np.ndarray) -> np.ndarray:
    w = np.zeros((len(times), 52))
    w[:, ARKIT_NAMES.index("jawOpen")] = 0.5 - 0.5 * np.cos(2 * np.pi * times / 1.5)
    w[:, ARKIT_NAMES.index("mouthFunnel")] = 0.3 * np.sin(np.pi * times / 1.5) ** 2
    return w


@pytest.mark.parametrize("fmt", ["live_link_face", "audio2face", "arkit_json", "gltf"])
def test_every_arkit_format_reads_to_the_same_motion(tmp_path: Path, fmt: str) -> None:
    fps = {"live_link_face": 60, "audio2face": 30, "arkit_json": 50, "gltf": 24}[fmt]
    t, w = _truth(fps)
    path = {
        "live_link_face": lambda: live_link_face_csv(tmp_path / "a.csv", w, fps=fps),
        "audio2face": lambda: audio2face_json(tmp_path / "a.json", w, fps=fps),
        "arkit_json": lambda: arkit_json(tmp_path / "a.json", t, w),
        "gltf": lambda: gltf_animation(tmp_path / "a.glb", t, w),
    }[fmt]()
    assert detect_format(path) == fmt
    track = read_capture(path)
    assert track.format == fmt
    assert track.times[0] == 0 and track.times[-1] == pytest.approx(t[-1], abs=1e-3)
    grid = np.arange(0, 1.4, 1 / 30)
    got = resample(track, grid)
    want = _at(grid)
    for name in ("jawOpen", "mouthFunnel"):
        k = track.names.index(name)
        assert np.abs(got[:, k] - want[:, ARKIT_NAMES.index(name)]).max() < 0.01, name
    if fmt == "live_link_face":  # a 30 fps timecode read from its rollover, 60 fps capture
        assert track.notes["timecode_fps"] == 30 and track.fps == 60
        assert track.notes["timecode_fps_source"].startswith("from the")
        assert "HeadYaw" in track.angles and "HeadYaw" not in track.names
        assert set(track.names) == set(ARKIT_NAMES)


def test_live_link_face_shorter_than_a_second_needs_its_rate(tmp_path: Path) -> None:
    t, w = _truth(60, seconds=0.5)
    path = live_link_face_csv(tmp_path / "short.csv", w, fps=60, start_s=0)
    guessed = read_capture(path)  # no second rolls over: timecode frame 14 -> 24 fps assumed
    assert guessed.notes["timecode_fps"] == 24
    assert "no second rolls over" in guessed.notes["timecode_fps_source"]
    given = read_capture(path, fps=30)
    assert given.times[-1] == pytest.approx(t[-1], abs=1e-3) and given.fps == 60


def test_viseme_csv_drives_the_viseme_targets(tmp_path: Path) -> None:
    t = np.arange(30) / 30
    w = np.zeros((30, 15))
    w[:, 10] = np.linspace(0, 1, 30)  # aa
    track = read_capture(viseme_csv(tmp_path / "v.csv", t, w))
    assert track.format == "viseme_csv" and track.names == VISEME_TARGETS
    assert resample(track, np.array([0.5]))[0, VISEME_TARGETS.index("viseme_aa")] == (
        pytest.approx(0.5 / (29 / 30), abs=0.01)
    )


def _without_column(text: str, name: str) -> str:
    lines = text.splitlines()
    drop = lines[0].split(",").index(name)
    return "".join(",".join(f for k, f in enumerate(line.split(",")) if k != drop) + "\n"
                   for line in lines)  # fmt: skip


def _with_a_field_too_many(text: str) -> str:
    """The first frame's line with one more value than the header has columns (it was read,
    the value ignored)."""
    header, first, rest = text.split("\n", 2)
    return f"{header}\n{first},0.5\n{rest}"


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        (lambda s: s.replace("JawOpen", "JawOpenWide"),
         "unknown channel(s) JawOpenWide; expected ARKit blendshape names"),
        (lambda s: _without_column(s, "MouthFunnel"), "missing channel(s) mouthFunnel"),
        (lambda s: s.replace(",MouthFunnel", ",BlendShapeCount"),
         ":1: column(s) named twice in the header: BlendShapeCount"),
        (_with_a_field_too_many, ":2: 64 fields, the header has 63"),
        (lambda s: s.replace("00:00:37:05.000", "37:05"), "line 12: Timecode '37:05'"),
        (lambda s: s.replace("0.000000", "x", 1), "line 2, column "),
        (lambda s: s.replace("0.000000", "3.5"), "to 3.5; expected 0-1"),
    ],
    ids=["unknown", "missing", "twice", "extra-field", "timecode", "not-a-number", "range"],
)
def test_unusable_captures_are_refused_in_words(tmp_path: Path, edit, expected: str) -> None:
    _, w = _truth(60)
    path = live_link_face_csv(tmp_path / "a.csv", w, fps=60)
    path.write_text(edit(path.read_text()))
    with pytest.raises(StageError) as err:
        read_capture(path)
    assert str(err.value).startswith(str(path)) and expected in str(err.value)


def test_offset_auto_finds_the_recordings_lag() -> None:
    """A recording that starts 0.37 s after the stimulus audio: the lag is found from the
    loudness envelopes (speech-like bursts), within one 10 ms hop."""
    rng = np.random.default_rng(3)
    rate = 16000
    stim = np.zeros(rate * 3)
    for start in (0.2, 0.7, 1.1, 1.8, 2.3):
        n = int(rng.uniform(0.1, 0.3) * rate)
        stim[int(start * rate): int(start * rate) + n] = rng.normal(0, 0.3, n)
    rec = np.concatenate([np.zeros(int(0.37 * rate)), stim])[: len(stim)]
    rec = rec + rng.normal(0, 0.003, len(rec))
    lag, r = align_offset_s(rec, rate, stim, rate)
    assert lag == pytest.approx(0.37, abs=0.011) and r > 0.8


KATO = Path(__file__).resolve().parents[1] / "protocols" / "kato2021.yaml"
CAPTURED = """  - id: captured
    label: {ja: キャプチャ, en: Captured (Live Link Face)}
    method: external_track
    params: {tracks: captures, offset_ms: OFFSET}
"""


def _vowels_protocol(folder: Path, *, offset: str = "0") -> Path:
    """kato2021, vowels only, with a fourth condition playing Live Link Face captures."""
    text = KATO.read_text(encoding="utf-8")
    text = kato_vowels_only(text)
    text = text.replace("\nstimulus_sets:", CAPTURED.replace("OFFSET", offset) + "\nstimulus_sets:")
    path = folder / "captured.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def _standard_track(path: Path):
    """The standard condition's blendshape track of vowels/aiueo and its speech."""
    from facelab.protocol import load_protocol
    from facelab.stimuli.render.build import _blendshapes
    from facelab.stimuli.render.clipspec import ClipJob
    from facelab.stimuli.render.prepare import speech_for, tracks_for
    from facelab.stimuli.render.scene import load_avatar

    protocol = load_protocol(path)
    stim = protocol.stimulus_set("vowels").stimuli[0]
    speech = speech_for(stim, base_dir=path.parent, sample_rate=48000)
    avatar = load_avatar(protocol, base_dir=path.parent)
    job = ClipJob("", "vowels", stim, "standard")
    bs = _blendshapes(protocol, job, speech, tracks_for(stim, speech), path.parent, avatar)
    return protocol, stim, speech, avatar, bs


def test_a_capture_plays_as_a_condition_validated_and_hashed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A Live Link Face capture of the standard condition's motion at 0.7x, 60 fps, played by
    a fourth condition: its track is the capture resampled (within 0.01), shifted by
    offset_ms; validate names a missing or broken file with its path; the clip spec hash
    follows the file's bytes."""
    from facelab.experiment.cli import main
    from facelab.stimuli.render.build import _blendshapes
    from facelab.stimuli.render.clipspec import ClipJob, clip_spec_hash
    from facelab.stimuli.render.prepare import tracks_for

    path = _vowels_protocol(tmp_path)
    assert main(["validate", str(path)]) == 2  # no capture yet
    err = capsys.readouterr()
    assert "no track for stimulus vowels/aiueo" in err.out + err.err
    protocol, stim, speech, avatar, bs = _standard_track(path)
    fps = 60
    grid = np.arange(0, bs.times[-1], 1 / fps)
    arkit = np.stack([np.interp(grid, bs.times, bs.column(n)) if n in bs.names
                      else np.zeros(len(grid)) for n in ARKIT_NAMES], axis=1)  # fmt: skip
    capture = live_link_face_csv(tmp_path / "captures" / "vowels" / "aiueo.csv", 0.7 * arkit)
    assert main(["validate", str(path)]) == 0
    job = ClipJob("", "vowels", stim, "captured")
    before = clip_spec_hash(protocol, job, base_dir=tmp_path)
    played = _blendshapes(protocol, job, speech, tracks_for(stim, speech), tmp_path, avatar)
    assert played.notes["format"] == "live_link_face" and played.notes["offset_ms"] == 0
    for name in ("jawOpen", "mouthFunnel", "mouthStretchLeft"):
        want = 0.7 * bs.column(name)
        assert np.abs(played.column(name) - want).max() < 0.01, name
    # shifted by 200 ms: the capture's motion comes 0.2 s later
    shifted = _vowels_protocol(tmp_path, offset="200")
    from facelab.protocol import load_protocol

    late = _blendshapes(load_protocol(shifted), job, speech, tracks_for(stim, speech),
                        tmp_path, avatar)  # fmt: skip
    k = int(np.argmax(played.column("jawOpen")))
    j = int(np.argmax(late.column("jawOpen")))
    assert played.times[j] - played.times[k] == pytest.approx(0.2, abs=0.02)
    capture.write_text(capture.read_text().replace("0.000000", "0.000001", 1))
    assert clip_spec_hash(protocol, job, base_dir=tmp_path) != before
    capture.write_text(capture.read_text().replace("JawOpen", "JawOpenMore"))
    assert main(["validate", str(path)]) == 2
    err = capsys.readouterr()
    assert f"{capture}: unknown channel(s) JawOpenMore" in err.out + err.err


def test_a_captures_head_and_eye_angles_turn_the_avatar(tmp_path: Path) -> None:
    """Live Link Face's head and eye angles (radians) play as the clip's head pose in degrees:
    the head turns the mesh; the eye angles are dropped where the capture's eyeLook shapes
    already move the eyes; ``head: false`` and an avatar without a skeleton play none, said in
    the clip's notes."""
    from dataclasses import replace

    from facelab.protocol import load_protocol
    from facelab.stimuli.render.build import _blendshapes
    from facelab.stimuli.render.clip import frame_poses
    from facelab.stimuli.render.clipspec import ClipJob
    from facelab.stimuli.render.prepare import tracks_for

    path = _vowels_protocol(tmp_path)
    protocol, stim, speech, avatar, bs = _standard_track(path)
    grid = np.arange(0, bs.times[-1], 1 / 60)
    arkit = np.zeros((len(grid), len(ARKIT_NAMES)))
    arkit[:, ARKIT_NAMES.index("jawOpen")] = 0.3
    angles = np.zeros((len(grid), len(ANGLES)))
    angles[:, ANGLES.index("HeadYaw")] = 0.3 * np.sin(2 * np.pi * grid / 2.0)  # ±17.2°
    angles[:, ANGLES.index("HeadPitch")] = 0.1  # 5.7° chin down
    angles[:, ANGLES.index("LeftEyeYaw")] = 0.12
    angles[:, ANGLES.index("RightEyeYaw")] = 0.08  # the eyes' mean: 0.1 rad
    capture = tmp_path / "captures" / "vowels" / "aiueo.csv"
    live_link_face_csv(capture, arkit, angles=angles)
    job = ClipJob("", "vowels", stim, "captured")
    tracks = tracks_for(stim, speech)
    played = _blendshapes(protocol, job, speech, tracks, tmp_path, avatar)
    assert played.poses is not None and avatar.skeleton is not None
    yaw, pitch, _roll, eye_yaw, _eye_pitch = played.poses.T
    want = np.degrees(0.3 * np.sin(2 * np.pi * np.clip(played.times, 0, grid[-1]) / 2.0))
    assert np.abs(yaw - want).max() < 0.3  # within the 60 fps capture's sampling
    assert pitch == pytest.approx(np.degrees(0.1), abs=0.01)
    assert eye_yaw == pytest.approx(np.degrees(0.1), abs=0.01)
    assert played.notes["angles_played"] and played.notes["angle_unit"] == "radians"
    # the pose turns the head: at the yaw peak the mesh moves by centimetres
    poses = frame_poses(played, fps=30, n_frames=90, pad_s=0.0)
    assert poses is not None
    k = int(np.argmax([abs(q.yaw) for q in poses]))
    rest = avatar.deform(np.zeros(len(avatar.target_names), np.float32))
    turned = avatar.deform(np.zeros(len(avatar.target_names), np.float32), pose=poses[k])
    assert np.linalg.norm(turned - rest, axis=1).max() > 0.01
    # eyeLook shapes moving in the capture: the eye angles would turn the eyes twice
    arkit[:, ARKIT_NAMES.index("eyeLookInLeft")] = 0.2 * (grid > 1.0)
    live_link_face_csv(capture, arkit, angles=angles)
    both = _blendshapes(protocol, job, speech, tracks, tmp_path, avatar)
    assert "eyeLookInLeft" in avatar.targets
    assert np.all(both.poses[:, 3:] == 0) and "eyeLook" in both.notes["eye_angles"]
    assert np.abs(both.poses[:, 0] - yaw).max() < 1e-9  # the head still turns
    # head: false, and an avatar without a skeleton: no pose, and the notes say why
    off = load_protocol(_vowels_protocol(tmp_path, offset="0, head: false"))
    still = _blendshapes(off, job, speech, tracks, tmp_path, avatar)
    assert still.poses is None and still.notes["angles_not_played"] == "head: false"
    boneless = replace(avatar, skeleton=None)
    flat = _blendshapes(protocol, job, speech, tracks, tmp_path, boneless)
    assert flat.poses is None and flat.notes["angles_not_played"] == "the avatar has no skeleton"


@pytest.mark.slow
def test_a_captured_reference_is_played_tracked_and_compared(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """kato2021's vowels with a fourth condition playing a Live Link Face capture (the standard
    motion at 0.7x, 60 fps) as the analysis reference: rendered and checked by the real face
    tracker (its tracked aperture follows the capture: the standard clip's aperture
    correlates > 0.9 with it at lag 0), simulated, analysed into objective.csv and
    objective_vs_ratings.csv."""
    import csv

    from facelab.experiment.cli import main

    path = _vowels_protocol(tmp_path)
    path.write_text(path.read_text(encoding="utf-8") + "\nanalysis: {reference: captured}\n",
                    encoding="utf-8")  # fmt: skip
    _, _, _, _, bs = _standard_track(path)
    grid = np.arange(0, bs.times[-1], 1 / 60)
    arkit = np.stack([np.interp(grid, bs.times, bs.column(n)) if n in bs.names
                      else np.zeros(len(grid)) for n in ARKIT_NAMES], axis=1)  # fmt: skip
    live_link_face_csv(tmp_path / "captures" / "vowels" / "aiueo.csv", 0.7 * arkit)
    clips = tmp_path / "clips"
    assert main(["render", str(path), "--out", str(clips), "--size", "480x270", "--quiet"]) == 0
    tracking = list(csv.DictReader((clips / "face_tracking.csv").open(encoding="utf-8")))
    conditions = ("baseline", "standard", "emphasized", "captured")
    assert {r["clip"] for r in tracking} == {f"vowels__aiueo__{c}" for c in conditions}
    results = tmp_path / "results"
    assert main(["simulate", str(path), "--participants", "4", "--sim-seed", "2",
                 "--results", str(results)]) == 0  # fmt: skip
    out = tmp_path / "analysis"
    assert main(["analyze", str(path), str(results), "--clips", str(clips), "--out", str(out),
                 "--force"]) == 0  # fmt: skip
    rows = list(csv.DictReader((out / "objective.csv").open(encoding="utf-8")))
    value = {(r["condition"], r["measure"], r["channel"]): float(r["value"] or "nan")
             for r in rows}  # fmt: skip
    assert {r["reference"] for r in rows} == {"captured"}
    assert value["standard", "aperture_correlation", "tracked"] > 0.9
    assert abs(value["standard", "lag_ms", "tracked"]) <= 34  # within a frame at 30 fps
    assert value["standard", "correlation", "jawOpen"] > 0.99  # the capture is 0.7x standard
    assert value["standard", "rmse", "jawOpen"] > 0.005
    assert ("baseline", "correlation", "jawOpen") not in value  # visemes: no shared channel
    assert ("baseline", "aperture_correlation", "tracked") in value
    related = list(csv.DictReader((out / "objective_vs_ratings.csv").open(encoding="utf-8")))
    assert {r["condition"] for r in related} == {"baseline", "standard", "emphasized"}
    assert "objective comparison with 'captured'" in (out / "report.md").read_text("utf-8")
    # the tracked measures as per-stimulus covariates: one row per item and measure, a slope
    # or the reason it cannot be estimated (few simulated participants, two stimuli)
    covariate = list(csv.DictReader((out / "objective_covariate.csv").open(encoding="utf-8")))
    assert {r["measure"] for r in covariate} == {"aperture_correlation", "aperture_error"}
    assert all(r["estimate"] or r["procedure"] == "not estimable" for r in covariate)
    assert "objective_covariate.csv" in (out / "report.md").read_text("utf-8")
