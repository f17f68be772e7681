"""Rendering (EGL offscreen), clips with synchronized audio, and the render stage with caching."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from facelab.experiment.cli import main
from facelab.stimuli.avatar import default_head
from facelab.stimuli.checks.face_tracker import picture_keys
from facelab.stimuli.methods import DriveInput, drive
from facelab.stimuli.render import clip as clip_module
from facelab.stimuli.render.clip import (
    av_offset_ms,
    decode_audio,
    decode_audios,
    decode_frames,
    encode,
    frame_weights,
    padded_audio,
    probe,
    remux,
    remux_many,
    shifted_audio,
)
from facelab.stimuli.render.renderer import Renderer, RenderSettings
from facelab.stimuli.speech.analyser import analyze
from facelab.stimuli.speech.tts import synthesize

pytestmark = pytest.mark.slow
SMALL = RenderSettings(width=320, height=240, distance_m=0.5)


def _mouth_darkness(img: np.ndarray, centre: np.ndarray) -> float:
    c, r = int(centre[0]), int(centre[1])
    roi = img[r + 2 : r + 8, c - 6 : c + 6].astype(float)  # just below the upper lip
    return float(255 - roi.mean())


def test_frames_show_the_face_and_the_mouth_opens() -> None:
    head = default_head()
    with Renderer(head, SMALL) as r:
        rest = r.frame(head.weight_vector({}))
        open_ = r.frame(head.weight_vector({"jawOpen": 1.0}))
        lips = r.project(head.neutral[[head.landmarks["upper_lip"]]])[0]
    assert rest.shape == (240, 320, 3) and rest.dtype == np.uint8
    background = np.array([127, 127, 127])
    assert np.abs(rest[5, 5].astype(int) - background).max() <= 2  # corner: background
    centre = rest[100:140, 140:180]
    assert np.abs(centre.astype(int) - background).max() > 40  # centre: the face, not empty
    assert 0 < lips[0] < 320 and 0 < lips[1] < 240
    assert (
        _mouth_darkness(open_, lips) > _mouth_darkness(rest, lips) + 25
    )  # interior darker than lips


@pytest.fixture(scope="module")
def clip(tmp_path_factory: pytest.TempPathFactory) -> dict:
    out = tmp_path_factory.mktemp("clip") / "c.mp4"
    speech = synthesize("あいうえお、おはようございます。")
    track = analyze(speech.samples, sample_rate=speech.sample_rate).compensated()
    bs = drive("vowel_blend", DriveInput(track=track), {"z": "emphasized"})
    head = default_head()
    audio = padded_audio(speech, pad_s=0.3)
    fps = 30
    n = round(audio.duration_s * fps)
    weights = frame_weights(bs, head, fps=fps, n_frames=n, pad_s=0.3)
    with Renderer(head, SMALL) as r:
        neutral = r.frame(head.weight_vector({}))
        info = encode(
            (r.frame(w) for w in weights),
            audio=audio,
            out=out,
            fps=fps,
            width=320,
            height=240,
            n_frames=n,
        )
    return {"info": info, "audio": audio, "n": n, "weights": weights, "neutral": neutral}


def test_clip_frame_count_duration_and_codecs(clip: dict) -> None:
    meta = probe(clip["info"].path)
    video = next(s for s in meta["streams"] if s["codec_type"] == "video")
    audio = next(s for s in meta["streams"] if s["codec_type"] == "audio")
    assert (video["codec_name"], audio["codec_name"]) == ("h264", "aac")
    assert int(video["nb_read_frames"]) == clip["n"] == round(clip["audio"].duration_s * 30)
    assert abs(float(audio["duration"]) - clip["audio"].duration_s) < 1 / 30


def test_clip_audio_equals_the_input(clip: dict) -> None:
    decoded = decode_audio(clip["info"].path, sample_rate=clip["audio"].sample_rate)
    ref = clip["audio"].samples
    n = min(len(decoded), len(ref))
    assert abs(len(decoded) - len(ref)) < clip["audio"].sample_rate / 30
    lags = range(-200, 201, 1)
    a, b = decoded[:n].astype(float), ref[:n].astype(float)
    best = max(
        lags,
        key=lambda k: float(np.dot(a[max(0, k) : n + min(0, k)], b[max(0, -k) : n - max(0, k)])),
    )
    assert best == 0  # no delay between input and decoded audio
    snr = 10 * np.log10(np.sum(b**2) / np.sum((a - b) ** 2))
    assert snr > 25  # AAC is lossy; the waveform is otherwise the input's


def test_many_sounds_on_one_picture_are_the_bytes_of_one_at_a_time(
    clip: dict, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """remux_many (one ffmpeg for several sounds, in batches) writes for each sound the file
    remux writes alone; decode_audios (one ffmpeg for several clips) gives what decode_audio
    gives, a broken file an empty sound without spoiling the others; picture_keys is equal
    for the clips sharing a picture and differs for another picture."""
    info, audio = clip["info"], clip["audio"]
    fps, n = 30, clip["n"]
    sounds = [audio, shifted_audio(audio, offset_ms=40), shifted_audio(audio, offset_ms=-120)]
    alone = [remux(video=info.path, audio=a, out=tmp_path / f"alone{k}.mp4", fps=fps, n_frames=n)
             for k, a in enumerate(sounds)]  # fmt: skip
    monkeypatch.setattr(clip_module, "REMUX_BATCH", 2)  # two processes: 2 + 1 outputs
    outputs = [(a, tmp_path / "many" / f"m{k}.mp4") for k, a in enumerate(sounds)]
    many = remux_many(video=info.path, fps=fps, n_frames=n, outputs=outputs)
    assert [m.sha256 for m in many] == [a.sha256 for a in alone]
    assert len({a.sha256 for a in alone}) == 3  # the sounds differ, so do the files
    assert not list((tmp_path / "many").glob("facelab-remux-*"))  # nothing half-written left

    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"not a clip")
    other = tmp_path / "other.mp4"  # another picture: the rest face throughout
    encode((clip["neutral"] for _ in range(n)), audio=audio, out=other, fps=fps, width=320,
           height=240, n_frames=n)  # fmt: skip
    paths = [m.path for m in many] + [broken, info.path]
    decoded = decode_audios(paths, sample_rate=16_000, batch=3)
    assert len(decoded) == 5 and len(decoded[3]) == 0
    for path, got in zip(paths, decoded, strict=True):
        if path != broken:
            assert np.array_equal(got, decode_audio(path, sample_rate=16_000)), path
    keys = picture_keys([info.path, *(m.path for m in many), broken, other], batch=4)
    assert len(set(keys[:4])) == 1 and keys[0] is not None
    assert keys[4] is None and keys[5] not in (None, keys[0])


def test_clip_starts_and_ends_neutral_and_is_in_sync(clip: dict) -> None:
    frames = decode_frames(clip["info"].path, width=320, height=240)
    for k in (0, len(frames) - 1):
        assert np.abs(frames[k].astype(int) - clip["neutral"].astype(int)).mean() < 3
    assert not np.any(clip["weights"][0]) and not np.any(clip["weights"][-1])
    sync = av_offset_ms(clip["info"].path, fps=30)
    assert abs(sync["offset_ms"]) < 1000 / 30 and sync["correlation"] > 0.3


def test_render_stage_writes_clips_csv_and_reuses_unchanged_clips(
    tmp_path: Path, kato_text: str, capsys: pytest.CaptureFixture[str]
) -> None:
    proto = tmp_path / "p.yaml"
    # a small study: only the vowel block, so the test renders 3 short clips
    text = kato_text.replace(
        "  - id: sentences\n    stimulus_set: sentences\n",
        "  - id: sentences2\n    stimulus_set: vowels\n",
    )
    text = text.replace(
        "practice: {stimulus_set: sentences, stimulus: passage, condition: standard}",
        "practice: {stimulus_set: vowels, stimulus: aiueo, condition: standard}",
    )
    proto.write_text(text, encoding="utf-8")
    out = tmp_path / "clips"
    argv = ["render", str(proto), "--out", str(out), "--size", "160x120", "--fps", "10", "--quiet"]
    assert main(argv) == 0
    rows = list(csv.DictReader((out / "clips.csv").read_text(encoding="utf-8").splitlines()))
    assert [r["condition"] for r in rows] == ["baseline", "standard", "emphasized"]
    # DESIGN.md's columns first, then the hash of the clip's declared inputs (stale-clip check),
    # then the animation track and its hash, then the stimulus checks' verdict on the clip
    assert list(rows[0]) == [
        "clip_id",
        "stimulus_set",
        "stimulus",
        "condition",
        "path",
        "duration_s",
        "fps",
        "width",
        "height",
        "sha256",
        "spec_sha256",
        "track_file",
        "track_sha256",
        "stimulus_checks",
    ]
    assert {r["stimulus_checks"] for r in rows} == {"passed"}
    assert (out / "stimulus_checks.csv").is_file()
    from facelab.hashing import sha256_file

    for r in rows:
        assert sha256_file(out / r["path"]) == r["sha256"] and (r["width"], r["height"]) == (
            "160",
            "120",
        )
    mtimes = {r["path"]: (out / r["path"]).stat().st_mtime_ns for r in rows}
    capsys.readouterr()
    assert main(argv) == 0
    assert "(0 rendered, 3 reused)" in capsys.readouterr().out
    assert {r["path"]: (out / r["path"]).stat().st_mtime_ns for r in rows} == mtimes
    # a changed method parameter re-renders only that condition's clip
    proto.write_text(
        text.replace("params: {z: emphasized, gain: 1.0}", "params: {z: emphasized, gain: 1.2}"),
        encoding="utf-8",
    )
    assert main(argv) == 0
    changed = {p for p, t in mtimes.items() if (out / p).stat().st_mtime_ns != t}
    assert changed == {"vowels__aiueo__emphasized.mp4"}
    meta = json.loads((out / "vowels__aiueo__emphasized.json").read_text())
    assert meta["params"]["gain"] == 1.2
    assert meta["track_source"].startswith("words") and "analysis_warp" not in meta
    # analysed from its audio instead: the clip names the warp the analysis chose
    line = "text: あ。い。う。え。お。\n"
    audio_only = text.replace(line, line + "        track_from: audio\n", 1)
    proto.write_text(audio_only, encoding="utf-8")
    assert main(argv) == 0
    meta = json.loads((out / "vowels__aiueo__standard.json").read_text())
    assert meta["track_source"].startswith("audio analysis")
    assert 0.7 <= meta["analysis_warp"] <= 1.4


def test_msaa_beyond_what_opengl_offers_is_a_clear_error() -> None:
    from facelab.errors import StageError

    settings = RenderSettings(width=64, height=64, msaa=64)
    with (
        pytest.raises(StageError, match=r"rendering\.msaa is 64.*set rendering\.msaa to 1 or 2"),
        Renderer(default_head(), settings),
    ):
        pass


def test_renderer_reports_the_samples_the_driver_gave() -> None:
    head = default_head()
    for msaa in (1, 2, 4):
        with Renderer(head, RenderSettings(width=64, height=64, msaa=msaa)) as r:
            r.frame(np.zeros(len(head.target_names), np.float32))
            assert r.samples is not None and r.samples >= msaa
            assert (r.samples == 1) == (msaa == 1)


def test_encode_keeps_each_frame_though_the_caller_reuses_its_buffer(tmp_path: Path) -> None:
    """Frames wait in a queue for the writer thread: a producer that fills one buffer again
    and again must still get every frame as it was when yielded."""
    from facelab.errors import StageError
    from facelab.stimuli.speech.audio import Speech

    n, fps = 24, 24
    audio = Speech(np.zeros(48000, np.float32), 48000)
    buf = np.zeros((48, 64, 3), np.uint8)

    def frames(count: int, bad_at: int | None = None):
        for k in range(count):
            buf[:] = 10 * k
            yield buf if k != bad_at else buf[:, :32]

    encode(frames(n), audio=audio, out=tmp_path / "a.mp4", fps=fps, width=64, height=48, n_frames=n)
    means = decode_frames(tmp_path / "a.mp4", width=64, height=48).reshape(n, -1).mean(axis=1)
    np.testing.assert_allclose(means, 10 * np.arange(n), atol=3)
    with pytest.raises(StageError, match=r"frame of shape \(48, 32, 3\)"):
        encode(
            frames(n, bad_at=5), audio=audio, out=tmp_path / "b.mp4", fps=fps, width=64,
            height=48, n_frames=n,
        )  # fmt: skip
    assert not (tmp_path / "b.mp4").exists()


def test_pipelined_frames_equal_frame_by_frame() -> None:
    """Renderer.frames (CPU work of frame k + 1 during the rasterisation of frame k) draws
    exactly what frame() draws, pose by pose."""
    from facelab.stimuli.avatar.rig import HeadPose

    head = default_head()
    weights = [head.weight_vector({"jawOpen": 0.1 * k, "eyeBlinkLeft": 0.2 * k}) for k in range(5)]
    poses = [HeadPose(yaw=4.0 * k, eye_pitch=-2.0 * k) for k in range(5)]
    with Renderer(head, SMALL) as r:
        one_by_one = [r.frame(w, pose=p) for w, p in zip(weights, poses, strict=True)]
        piped = list(r.frames(weights, poses))
        still = list(r.frames(weights[:2]))
    assert len(piped) == 5 and all(
        np.array_equal(a, b) for a, b in zip(one_by_one, piped, strict=True)
    )
    assert not np.array_equal(piped[0], piped[4])  # the frames differ: the head moved
    assert len(still) == 2


def test_a_frame_like_the_one_before_is_shown_again_not_drawn() -> None:
    """Frames whose weights and pose equal the frame before's (the still padding, an
    audio-only face) are that frame's picture, not drawn again; a change of either alone is
    drawn: the pictures are those frame() draws, in order."""
    from facelab.stimuli.avatar.rig import HeadPose

    head = default_head()
    shut, half = head.weight_vector({}), head.weight_vector({"jawOpen": 0.5})
    weights = [shut, shut, shut, half, half, half, shut]
    poses = [None, None, None, None, None, HeadPose(yaw=20.0), None]
    poses[2] = HeadPose()  # the rest pose, equal to none in pixels, but another pose: drawn
    with Renderer(head, SMALL) as r:
        one_by_one = [r.frame(w, pose=p) for w, p in zip(weights, poses, strict=True)]
        r.times = type(r.times)()
        piped = list(r.frames(weights, poses))
        drawn, repeated = r.times.frames, r.times.repeated
        r.times = type(r.times)()
        still = list(r.frames([shut] * 4))
    assert len(piped) == 7
    assert all(np.array_equal(a, b) for a, b in zip(one_by_one, piped, strict=True))
    assert (drawn, repeated) == (5, 2)  # frames 2 and 5 repeat the frame before theirs
    assert not np.array_equal(piped[4], piped[5])  # the head turned
    assert (len(still), r.times.frames, r.times.repeated) == (4, 1, 3)
    assert all(np.array_equal(f, one_by_one[0]) for f in still)


def test_renderers_open_at_once_each_keep_drawing_when_another_closes() -> None:
    """Several renderers may be open in one process (the render stage's cached one, a contact
    sheet's, the live view's): closing one must leave the others drawing the same pictures.
    pyrender alone terminates the shared EGL display on every close."""
    head = default_head()
    open_mouth = head.weight_vector({"jawOpen": 0.8})
    with Renderer(head, SMALL) as a:
        before = a.frame(open_mouth)
        with Renderer(head, RenderSettings(width=96, height=96)) as b:
            in_b = b.frame(open_mouth)
            with Renderer(head, SMALL) as c:
                assert np.array_equal(c.frame(open_mouth), before)
            assert np.array_equal(a.frame(open_mouth), before)  # c closed, a still draws
            assert np.array_equal(b.frame(open_mouth), in_b)
        frames = list(a.frames([open_mouth, open_mouth]))  # b closed
        assert all(np.array_equal(f, before) for f in frames)
    with Renderer(head, SMALL) as d:  # and a new one after all were closed
        assert np.array_equal(d.frame(open_mouth), before)


def test_resolving_only_the_heads_rectangle_changes_no_pixel() -> None:
    """Frames are resolved (and turned top row first) only inside the avatar's screen
    rectangle (and the previous frame's): bit for bit what resolving the whole frame gives,
    also when the head swings (its old place must be replaced), moves out of the picture and
    comes back, or a frame is drawn and never read back, with and without multisampling."""
    from facelab.stimuli.avatar.rig import HeadPose
    from facelab.stimuli.render.renderer import _union

    head = default_head()
    weights = [head.weight_vector({"jawOpen": 0.15 * (k % 5)}) for k in range(10)]
    poses = [HeadPose(yaw=(-35.0, 35.0)[k % 2], pitch=8.0 * (k % 3)) for k in range(10)]
    settings = RenderSettings(width=320, height=240, distance_m=1.0, msaa=4)
    for s in (settings, RenderSettings(width=320, height=240, distance_m=1.0, msaa=1)):
        with Renderer(head, s) as boxed:
            drawn = list(boxed.frames(weights, poses))
            boxes = [
                boxed._screen_box(head.deform(w, pose=p))
                for w, p in zip(weights, poses, strict=True)
            ]
            # the head moved away: far to the side, the rectangle is empty; then it returns
            away = head.deform(weights[0]) + np.array([5.0, 0.0, 0.0], np.float32)
            assert boxed._screen_box(away)[2] == 0
            boxed._upload(away, np.zeros_like(away))
            boxed._draw(boxed._screen_box(away))
            empty = boxed._collect()
            back = boxed.frame(weights[0], pose=poses[0])
            # a frame drawn and never read back (an error mid-clip), the head moved aside: the
            # next frame there must still replace what the last one read back left
            aside = head.deform(weights[0]) + np.array([0.25, 0.0, 0.0], np.float32)
            last = boxed._screen_box(head.deform(weights[0], pose=poses[0]))
            moved = boxed._screen_box(aside)
            assert moved is not None and last is not None
            # the head moved right, and the last frame read back lies partly outside its box
            assert moved[0] > last[0] and _union(moved, last) != moved
            for _ in range(2):  # drawn twice, read back once
                boxed._upload(aside, boxed._lit(aside))
                boxed._draw(moved)
            after = boxed._collect()
        with Renderer(head, s) as whole:
            whole._screen_box = lambda verts: None  # type: ignore[method-assign]
            reference = list(whole.frames(weights, poses))
            reference_back = whole.frame(weights[0], pose=poses[0])
            whole._upload(aside, whole._lit(aside))
            whole._draw(None)
            reference_after = whole._collect()
        assert all(b is not None and b[2] * b[3] < 0.8 * 320 * 240 for b in boxes)
        assert all(np.array_equal(a, b) for a, b in zip(drawn, reference, strict=True))
        assert np.all(empty == empty[0, 0])  # nothing of the head left behind
        assert np.array_equal(back, reference_back)
        assert np.array_equal(after, reference_after)


def test_a_shape_the_avatar_lacks_is_passed_over_only_when_the_track_holds_it_at_zero() -> None:
    """A real ARKit export often lacks one of the 52 shapes (tongueOut); the shipped Z
    matrices never move it, so such an avatar renders: the channel is left out. A channel
    the track does move is refused, naming it and what to do."""
    from facelab.errors import StageError
    from facelab.stimuli.methods.types import BlendshapeTrack
    from facelab.stimuli.render.clip import weights_at

    head = default_head()
    times = np.array([0.0, 0.5, 1.0])
    track = BlendshapeTrack(times=times, weights=np.array([[0, 0], [0.8, 0], [0, 0]]),
                            names=("jawOpen", "noSuchShape"))  # fmt: skip
    weights = frame_weights(track, head, fps=10, n_frames=12, pad_s=0.1)
    assert weights[:, head.target_names.index("jawOpen")].max() == pytest.approx(0.8)
    assert weights_at(track, head, t=0.5)[head.target_names.index("jawOpen")] == 0.8
    moved = BlendshapeTrack(times=times, weights=np.array([[0, 0], [0.8, 0.1], [0, 0]]),
                            names=("jawOpen", "noSuchShape"))  # fmt: skip
    with pytest.raises(StageError, match="lacks targets the track moves: noSuchShape"):
        frame_weights(moved, head, fps=10, n_frames=12, pad_s=0.1)
