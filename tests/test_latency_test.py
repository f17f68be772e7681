"""facelab latency-test (issue 51, part 5): the photodiode/microphone test clip lights and
sounds together in the file; a recording of it is measured to the millisecond (simulated here
from the decoded clip: a panel's rise, a line input's DC block, an inverted photodiode, room
sound, hum and noise - no photodiode is attached to this machine); bad recordings are said; the
clip plays in the lab window through the study's player."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
from scipy.signal import butter, lfilter

from facelab.analysis.latency_recording import channel_onsets, measure_latency
from facelab.errors import StageError
from facelab.experiment.cli import main
from facelab.stimuli.render.clip import decode_audio, decode_frames
from facelab.stimuli.render.latency_test_clip import (
    LatencyTestClip,
    event_frames,
    write_latency_test_clip,
)
from tests.conftest import KATO

EXE = str(Path(sys.executable).with_name("facelab"))
SR = 48_000


@pytest.fixture(scope="module")
def clip(tmp_path_factory: pytest.TempPathFactory) -> tuple[LatencyTestClip, Path]:
    plan = LatencyTestClip.plan(fps=60, width=320, height=180, events=6, period_s=0.5)
    out = tmp_path_factory.mktemp("latency") / "test.mp4"
    write_latency_test_clip(plan, out=out)
    return plan, out


def test_the_clip_lights_and_sounds_together(clip: tuple[LatencyTestClip, Path]) -> None:
    """Decoded from the mp4: the patch is white on exactly the scheduled frames (and nowhere
    else in the picture changes), each tone burst starts within 0.5 ms of its flash."""
    plan, path = clip
    assert LatencyTestClip.read(path.with_suffix(".json")) == plan
    frames = decode_frames(path, width=plan.width, height=plan.height).astype(np.float32)
    assert len(frames) == plan.n_frames
    left, top, side, _ = plan.patch_px
    patch = frames[:, top + 2 : top + side - 2, left + 2 : left + side - 2].mean(axis=(1, 2, 3))
    assert np.array_equal(patch > 128, event_frames(plan)), np.round(patch)
    assert patch[event_frames(plan)].min() > 230 and patch[~event_frames(plan)].max() < 20
    rest = frames.copy()
    rest[:, max(0, top - 12) : top + side + 12, max(0, left - 12) : left + side + 12] = 0
    assert np.ptp(rest, axis=0).max() < 12  # only the patch flashes
    audio = decode_audio(path, sample_rate=SR)
    onsets = channel_onsets(audio, sample_rate=SR, min_gap_s=plan.period_s / 2)
    assert len(onsets) == plan.events
    assert np.abs(onsets - np.array(plan.onsets_s)).max() < 0.0005, onsets


def _recording(
    plan: LatencyTestClip, path: Path, *, display_ms: float, sound_ms: float,
    late_frame_event: int | None = None, seed: int = 3, pwm_hz: float = 0.0,
    dc_coupled: bool = False, lead_in_s: float = 0.0, hum: tuple[float, ...] = (0.05,),
    click_before: int | None = None,
) -> np.ndarray:
    """A photodiode and microphone recording of the clip played with the picture
    ``display_ms`` and the sound ``sound_ms`` late (one event's flash a frame late; the
    backlight flickering at ``pwm_hz``, half on)."""
    frames = decode_frames(path, width=plan.width, height=plan.height)
    left, top, side, _ = plan.patch_px
    lum = frames[:, top : top + side, left : left + side].mean(axis=(1, 2, 3)) / 255
    if late_frame_event is not None:  # that flash shown one frame late (and one shorter)
        k = round(plan.onsets_s[late_frame_event] * plan.fps)
        lum[k] = lum[k - 1]
    audio = decode_audio(path, sample_rate=SR)
    n = len(audio) + SR // 2 + round(lead_in_s * SR)
    t = np.arange(n) / SR
    shown = np.floor((t - lead_in_s - display_ms / 1000) * plan.fps).astype(int)
    light = np.where(shown >= 0, lum[np.clip(shown, 0, len(lum) - 1)], lum[0])
    if lead_in_s:  # a grey window on the screen before the clip (lighter than its black)
        light = np.where(shown < 0, 0.5, light)
    a = np.exp(-1 / (0.002 * SR))  # the panel's 2 ms rise
    light = lfilter([1 - a], [1, -a], light, zi=[a * light[0]])[0]  # steady from the start
    if pwm_hz:
        light = light * ((t * pwm_hz) % 1 < 0.5)
    b, den = butter(1, 10 / (SR / 2), "high")  # a line input's DC block
    rng = np.random.default_rng(seed)
    if not dc_coupled:
        light = lfilter(b, den, light)
    diode = -0.4 * light + 0.003 * rng.standard_normal(n)  # inverted
    mic = np.zeros(n)
    d = round((sound_ms / 1000 + lead_in_s) * SR)
    if d >= 0:
        mic[d : d + len(audio)] = 0.3 * audio[: n - d]
    else:  # the sound ahead of the picture
        mic[: len(audio) + d] = 0.3 * audio[-d:]
    if click_before is not None:  # a 1 ms click 100 ms before one burst
        k = d + round((plan.onsets_s[click_before] - 0.1) * SR)
        mic[k : k + SR // 1000] += 0.4
    room = np.exp(-np.arange(2400) / 400) * rng.standard_normal(2400) * 0.005
    mic = mic + np.convolve(mic, room)[:n]
    for h, level in enumerate(hum):  # mains hum (and its harmonics)
        mic += level * np.sin(2 * np.pi * 50 * (2 * h + 1) * t)
    mic += 0.004 * rng.standard_normal(n)
    return np.stack([diode, mic], axis=1)


@pytest.mark.parametrize(
    "display_ms, sound_ms, pwm_hz", [(37.0, 12.0, 0.0), (5.0, 60.0, 240.0), (20.0, 20.0, 1000.0)]
)
def test_a_recording_is_measured_to_the_millisecond(
    clip: tuple[LatencyTestClip, Path], display_ms: float, sound_ms: float, pwm_hz: float
) -> None:
    """Within 1 ms, with mains hum on the microphone and a PWM backlight on the light (a
    flash that starts while the backlight is off is seen when it comes on: at 240 Hz and
    above that is under 2.1 ms, and this schedule's onsets meet it switched on)."""
    plan, path = clip
    rec = _recording(plan, path, display_ms=display_ms, sound_ms=sound_ms, pwm_hz=pwm_hz)
    got = measure_latency(rec, sample_rate=SR, photodiode=0, mic=1, period_s=plan.period_s,
                          expected=plan.events)  # fmt: skip
    s = got.summary
    assert s["pairs"] == s["flashes_found"] == s["tone_bursts_found"] == plan.events
    assert s["offset_ms_mean"] == pytest.approx(sound_ms - display_ms, abs=1.0), s
    assert s["offset_ms_sd"] < 0.3 and s["flashes_missing"] == 0
    assert s["light_interval_error_ms_max"] < 1.0
    assert list(got.events.columns) == ["event", "light_s", "sound_s", "offset_ms",
                                        "light_interval_ms"]  # fmt: skip


@pytest.mark.parametrize(
    "case",
    ["dc_coupled_after_a_grey_screen", "sound_ahead", "a_click_before_a_burst", "hum_harmonics"],
)
def test_awkward_recordings_are_measured_too(clip: tuple[LatencyTestClip, Path], case) -> None:
    """A DC-coupled photodiode that saw a grey window for most of the recording; the sound
    35 ms ahead of the light; a click 100 ms before one burst; hum at 50, 150 and 250 Hz
    (-4, -10, -16 dB against the tone)."""
    plan, path = clip
    kw: dict = {"display_ms": 30.0, "sound_ms": 12.0}
    truth = -18.0
    if case == "dc_coupled_after_a_grey_screen":
        kw |= {"dc_coupled": True, "lead_in_s": 6.0}
    elif case == "sound_ahead":
        kw |= {"display_ms": 40.0, "sound_ms": 5.0}
        truth = -35.0
    elif case == "a_click_before_a_burst":
        kw |= {"click_before": 3}
    else:
        kw |= {"hum": (0.1, 0.05, 0.025)}
    rec = _recording(plan, path, **kw)
    got = measure_latency(rec, sample_rate=SR, photodiode=0, mic=1, period_s=plan.period_s,
                          tone_hz=plan.tone_hz, expected=plan.events)  # fmt: skip
    s = got.summary
    assert s["pairs"] == plan.events and s["warnings"] == [], s
    assert s["offset_ms_mean"] == pytest.approx(truth, abs=1.0) and s["offset_ms_sd"] < 0.5, s


def test_a_sound_later_than_half_a_period_and_two_playings_are_warned_about(
    clip: tuple[LatencyTestClip, Path],
) -> None:
    plan, path = clip
    late = _recording(plan, path, display_ms=10.0, sound_ms=10.0 + 0.6 * 1000 * plan.period_s)
    got = measure_latency(late, sample_rate=SR, photodiode=0, mic=1, period_s=plan.period_s,
                          expected=plan.events)  # fmt: skip
    assert any("paired with the wrong flash" in w for w in got.summary["warnings"])
    once = _recording(plan, path, display_ms=10.0, sound_ms=10.0)
    twice = np.concatenate([once, once])
    got = measure_latency(twice, sample_rate=SR, photodiode=0, mic=1, period_s=plan.period_s,
                          expected=plan.events)  # fmt: skip
    assert any("record one playing per measurement" in w for w in got.summary["warnings"])


def test_a_flash_shown_a_frame_late_shows_in_its_offset_and_intervals(
    clip: tuple[LatencyTestClip, Path],
) -> None:
    plan, path = clip
    rec = _recording(plan, path, display_ms=30.0, sound_ms=10.0, late_frame_event=2)
    got = measure_latency(rec, sample_rate=SR, photodiode=0, mic=1, period_s=plan.period_s,
                          expected=plan.events)  # fmt: skip
    offsets = got.events["offset_ms"].to_numpy()
    frame_ms = 1000 / plan.fps
    assert offsets[2] == pytest.approx(-20.0 - frame_ms, abs=1.0)
    assert np.delete(offsets, 2) == pytest.approx(-20.0, abs=1.0)
    assert got.summary["light_interval_error_ms_max"] == pytest.approx(frame_ms, abs=1.0)


def test_a_missing_flash_is_counted_and_a_recording_without_one_is_refused(
    clip: tuple[LatencyTestClip, Path],
) -> None:
    plan, path = clip
    rec = _recording(plan, path, display_ms=20.0, sound_ms=20.0)
    cut = round((plan.onsets_s[1] + plan.period_s / 2) * SR)
    got = measure_latency(rec[cut:], sample_rate=SR, photodiode=0, mic=1,
                          period_s=plan.period_s, expected=plan.events)  # fmt: skip
    assert got.summary["flashes_missing"] == 2 and got.summary["pairs"] == plan.events - 2
    dark = rec.copy()
    dark[:, 0] = 0.003 * np.random.default_rng(1).standard_normal(len(rec))
    with pytest.raises(StageError, match=r"0 flashes found on channel 0 .*photodiode"):
        measure_latency(dark, sample_rate=SR, photodiode=0, mic=1, period_s=plan.period_s)
    with pytest.raises(StageError, match=r"has 2 channels .*microphone channel 2"):
        measure_latency(rec, sample_rate=SR, photodiode=0, mic=2, period_s=plan.period_s)


def test_the_commands_write_measure_and_refuse_clearly(
    clip: tuple[LatencyTestClip, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plan, path = clip
    rec = tmp_path / "rec.wav"
    sf.write(rec, _recording(plan, path, display_ms=40.0, sound_ms=15.0).astype(np.float32), SR,
             subtype="PCM_24")  # fmt: skip
    schedule = str(path.with_suffix(".json"))
    out = tmp_path / "m"
    done = subprocess.run([EXE, "latency-test", "measure", str(rec), "--schedule", schedule,
                           "--out", str(out)], capture_output=True, text=True)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "6 of 6 events measured" in done.stdout
    summary = json.loads((out / "latency_summary.json").read_text())
    assert summary["offset_ms_mean"] == pytest.approx(-25.0, abs=1.0)
    def facelab(*args: str) -> tuple[int, str]:  # the refusals in this process: faster
        code = main(["latency-test", *args])
        return code, capsys.readouterr().err

    code, again = facelab("measure", str(rec), "--schedule", schedule, "--out", str(out))
    assert code == 2 and "exists; choose another file or pass --force" in again
    mono = tmp_path / "mono.wav"
    sf.write(mono, np.zeros(SR, np.float32), SR)
    code, bad = facelab("measure", str(mono), "--schedule", schedule)
    assert code == 2
    assert "has 1 channel (0 to 0); the microphone channel 1 is not one of them" in bad
    not_json = tmp_path / "x.json"
    not_json.write_text("flashes: 3")
    code, not_schedule = facelab("measure", str(rec), "--schedule", str(not_json))
    assert code == 2 and "not a latency test schedule" in not_schedule
    code, short = facelab("clip", "--out", str(tmp_path / "c.mp4"), "--fps", "120",
                          "--flash-frames", "1")  # fmt: skip
    assert code == 2
    assert "--flash-frames 1: a flash of 8 ms is too short at 120 frames/s" in short
    assert not (tmp_path / "c.mp4").exists() and not (tmp_path / "c.json").exists()
    for text in (bad, again, not_schedule, short):
        assert "Traceback" not in text and "Error:" not in text


@pytest.mark.slow
def test_the_clip_plays_in_the_lab_window(
    clip: tuple[LatencyTestClip, Path], tmp_path: Path
) -> None:
    """Through the study's player (PsychoPy under Xvfb, sound to a null device): every frame
    of the clip shown, twice."""
    if not os.environ.get("DISPLAY"):
        pytest.fail("no DISPLAY: run the tests with the README's test command (xvfb-run)")
    plan, path = clip
    home = tmp_path / "home"
    home.mkdir()
    (home / ".asoundrc").write_text("pcm.!default {\n  type null\n}\n")
    env = {**os.environ, "SDL_AUDIODRIVER": "dummy", "HOME": str(home)}
    shown = tmp_path / "shown.json"
    done = subprocess.run([EXE, "latency-test", "play", str(KATO), str(path), "--windowed",
                           "--size", "640x400", "--repeat", "2", "--json", str(shown)],
                          env=env, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    record = json.loads(shown.read_text())
    assert "llvmpipe" in record["gl_renderer"] and record["paced_hz"] == 60.0  # Xvfb's GL
    played = record["playings"]
    assert [p["playing"] for p in played] == [1, 2]
    for p in played:
        assert p["frames_expected"] == plan.n_frames
        assert p["flips"] >= plan.n_frames * 0.5
        assert p["frames_dropped"] <= plan.n_frames * 0.5  # Xvfb's software GL, loaded
