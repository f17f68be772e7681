"""Speech in noise (issue 52.2): ``protocols/kato2021_srt.yaml`` mixes six words with
speech-shaped noise at -18 .. 0 dB SNR, heard with the voice alone and with kato2021's three
methods. The mix keeps the speech level and puts the noise where asked; simulated listeners
with the protocol's stated thresholds are recovered (each participant's SRT interval covers
the truth at the nominal rate, for constant stimuli and for a staircase), and the protocol's
checks refuse noise the clips cannot carry."""

from __future__ import annotations

import itertools
import re

import numpy as np
import pandas as pd
import pytest

from facelab.analysis import srt
from facelab.experiment.simulate import simulated_rows
from facelab.intelligibility_function import p_correct
from facelab.protocol import load_protocol, load_protocol_text
from facelab.resources import protocol_path
from facelab.stimuli.speech.noise import (
    active_level_db,
    long_term_spectrum,
    mix_at_snr,
    noise_rng,
    rms_db,
    shaped_noise,
)
from tests.protocol_edits import protocol_problems

SERIES = ["audio", "baseline", "standard", "emphasized"]
SNRS = [-18.0, -15.0, -12.0, -9.0, -6.0, -3.0, 0.0]
RATE = 16_000


def _text() -> str:
    return protocol_path("kato2021_srt").read_text(encoding="utf-8")


def _problems(text: str, tmp_path) -> str:
    return protocol_problems(text, tmp_path, "srt.yaml")


def _voice(seconds: float = 0.6) -> np.ndarray:
    """A vowel-like voice: harmonics of 120 Hz under a slow envelope, silence either side."""
    t = np.arange(int(seconds * RATE)) / RATE
    voice = sum(np.sin(2 * np.pi * 120 * h * t) / h for h in range(1, 30))
    voice *= np.sin(np.pi * t / seconds) ** 2
    pad = np.zeros(int(0.3 * RATE))
    return np.concatenate([pad, 0.1 * voice, pad]).astype(np.float32)


def test_the_protocol_interleaves_four_series_at_seven_snrs() -> None:
    protocol = load_protocol(protocol_path("kato2021_srt"))
    by_series: dict[str, list[float]] = {}
    for c in protocol.conditions:
        assert c.noise is not None and c.level == c.noise.snr_db  # the level is the SNR
        by_series.setdefault(c.series_id, []).append(c.noise.snr_db)
    assert by_series == {s: SNRS for s in SERIES}
    assert srt.audio_only_series(protocol) == "audio"
    assert {c.modality for c in protocol.conditions if c.series_id == "audio"} == {"audio_only"}
    task = protocol.tasks[0]
    assert srt.is_noise_task(protocol, task) and len(task.labels) == 6


def test_a_noise_token_is_the_documented_synthesis_and_has_the_speech_spectrum() -> None:
    """A noise token is complex Gaussian bins shaped by the spectrum at the next fast length,
    cut to the clip (numpy's own FFT gives the same numbers), and its long-term spectrum is
    the speech's: within 1.5 dB over the bins carrying the voice, at a prime length and at a
    length shorter than one Welch segment."""
    from scipy.fft import next_fast_len

    from facelab.stimuli.speech.noise import NPERSEG

    spectrum = long_term_spectrum([_voice()], sample_rate=RATE)
    for n in (24_989, 700):  # prime; shorter than a segment
        made = shaped_noise(spectrum, n=n, rng=noise_rng("study", "set", "word", "-6"))
        rng = noise_rng("study", "set", "word", "-6")
        length = next_fast_len(max(n, NPERSEG), real=True)
        bins = np.fft.rfftfreq(length)
        shape = np.interp(bins, np.linspace(0.0, 0.5, len(spectrum)), spectrum)
        z = rng.standard_normal((2, len(bins)))
        x = np.fft.irfft(shape * (z[0] + 1j * z[1]), n=length)[:n]
        assert made.shape == (n,) and np.allclose(made, x / np.sqrt(np.mean(x**2)), rtol=1e-9,
                                                  atol=1e-12)  # fmt: skip
        assert np.sqrt(np.mean(made**2)) == pytest.approx(1.0, rel=1e-9)
    long = shaped_noise(spectrum, n=RATE * 20, rng=noise_rng("study", "set", "long", "0"))
    heard = long_term_spectrum([long], sample_rate=RATE)
    edges = np.linspace(0, len(spectrum), 17).astype(int)  # 16 bands of 500 Hz

    def bands_db(s: np.ndarray) -> np.ndarray:
        return 10 * np.log10([np.sum(s[a:b] ** 2) for a, b in itertools.pairwise(edges)])

    voiced = bands_db(spectrum) > bands_db(spectrum).max() - 30  # the voice's bands
    gap = (bands_db(heard) - bands_db(spectrum))[voiced]  # the RMS sets the level: a constant
    assert voiced.sum() >= 5 and gap.max() - gap.min() < 1.0, gap


def test_a_clips_noise_is_made_once_and_stays_the_same_numbers(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The clips of one stimulus at one SNR (one per modality, and the stimulus checks'
    copy) share their noise from a bounded cache: the numbers the generator makes, read-only,
    and the oldest dropped when the cache is full."""
    from facelab.stimuli.render import sound

    spectrum = long_term_spectrum([_voice()], sample_rate=RATE)
    from facelab.bounded_memo import BoundedMemo

    monkeypatch.setattr(sound, "_noises", BoundedMemo(max_bytes=sound.NOISE_CACHE_BYTES,
                                                      size_of=lambda x: x.nbytes))  # fmt: skip
    parts = ("study", "set", "word", "-6")
    first = sound._speech_shaped_noise(spectrum, n=24_989, parts=parts)
    again = sound._speech_shaped_noise(spectrum, n=24_989, parts=parts)
    assert again is first and not first.flags.writeable
    assert np.array_equal(first, shaped_noise(spectrum, n=24_989, rng=noise_rng(*parts)))
    other = sound._speech_shaped_noise(spectrum, n=24_989, parts=(*parts[:3], "-3"))
    assert not np.array_equal(other, first)
    assert not np.array_equal(sound._speech_shaped_noise(spectrum, n=20_000, parts=parts),
                              first[:20_000])  # fmt: skip
    sound._noises.max_bytes = 2 * first.nbytes  # room for two of these: the oldest goes
    sound._speech_shaped_noise(spectrum, n=24_989, parts=(*parts[:3], "0"))
    assert len(sound._noises) == 2 and sum(x.nbytes for x in sound._noises.values()) <= (
        2 * first.nbytes)


@pytest.mark.parametrize("guess", [0.0, 0.1, 1 / 6])
def test_the_srt_fits_gradient_is_the_likelihoods_derivative(guess: float) -> None:
    """The analytic gradient the SRT fit hands L-BFGS-B (SRT, log slope, lapse) equals
    central differences of the log-likelihood of :func:`p_correct`, at random counts and
    parameters, for open and closed sets."""
    import math

    from facelab.analysis.srt import _loglik_and_gradient
    from facelab.intelligibility_function import p_correct

    x = np.arange(-16.0, 1.0, 2.0)
    n = np.full(len(x), 10.0)
    rng = np.random.default_rng(7)

    def loglik(t: np.ndarray, k: np.ndarray) -> float:
        p = np.clip(p_correct(x, srt=t[0], slope=math.exp(t[1]), guess=guess, lapse=t[2]),
                    1e-9, 1 - 1e-9)  # fmt: skip
        return float(np.sum(k * np.log(p) + (n - k) * np.log1p(-p)))

    for _ in range(8):
        k = rng.integers(0, 11, len(x)).astype(float)
        th = np.array([rng.uniform(-14, -2), math.log(rng.uniform(0.03, 0.3)),
                       rng.uniform(0.0, 0.2)])  # fmt: skip
        value, grad = _loglik_and_gradient(th, x=x, n=n, k=k, guess=guess)
        assert value == pytest.approx(loglik(th, k), rel=1e-12)
        for i in range(3):
            h = np.eye(3)[i] * 1e-6
            numeric = (loglik(th + h, k) - loglik(th - h, k)) / 2e-6
            assert grad[i] == pytest.approx(numeric, rel=1e-5, abs=1e-5), (i, grad, numeric)


@pytest.mark.parametrize("snr", [-18.0, -6.0, 0.0, 6.0])
def test_the_mix_keeps_the_speech_level_and_sets_the_noise_below_it(snr: float) -> None:
    voice = _voice()
    noise = shaped_noise(long_term_spectrum([voice], sample_rate=RATE), n=len(voice),
                         rng=noise_rng("test", str(snr)))  # fmt: skip
    mix, record = mix_at_snr(voice, noise, sample_rate=RATE, snr_db=snr, speech_level_dbfs=-35,
                             ramp_s=0.05, source="speech_shaped")  # fmt: skip
    ramp = round(0.05 * RATE)
    speech = voice * 10 ** ((-35 - active_level_db(voice, sample_rate=RATE)) / 20)
    rest = (mix - speech)[ramp:-ramp]
    assert abs(active_level_db(speech, sample_rate=RATE) + 35) < 1e-6
    assert abs(rms_db(rest) - (-35 - snr)) < 0.01  # the noise's RMS between its fades
    assert abs(record.measured_snr_db - snr) < 0.01 and record.peak_dbfs < 0
    assert abs(mix[0]) < 1e-3 and abs(mix[-1]) < 1e-3  # faded in and out
    # speech-shaped: the noise's spectrum follows the voice's (low harmonics dominate)
    f = np.fft.rfftfreq(len(noise), 1 / RATE)
    power = np.abs(np.fft.rfft(noise)) ** 2
    assert power[(f > 100) & (f < 600)].mean() > 30 * power[(f > 5000) & (f < 7000)].mean()


def test_a_mix_that_would_clip_is_refused() -> None:
    voice = _voice()
    noise = np.random.default_rng(1).normal(size=len(voice))
    with pytest.raises(ValueError, match="would clip"):
        mix_at_snr(voice, noise, sample_rate=RATE, snr_db=-30, speech_level_dbfs=-10,
                   ramp_s=0.05, source="x")  # fmt: skip


def test_the_noise_rows_measure_the_clip_not_the_promise() -> None:
    """The check finds the mix where it was put and the noise at its level; a clip carrying
    another SNR's mix, or the voice a frame late, fails."""
    from facelab.stimuli.checks.clip_checks import noise_rows

    voice = _voice()
    noise = shaped_noise(long_term_spectrum([voice], sample_rate=RATE), n=len(voice),
                         rng=noise_rng("check"))  # fmt: skip
    quiet = voice == 0
    ramp = round(0.05 * RATE)
    quiet[:ramp], quiet[-ramp:] = False, False

    def mixed(snr: float) -> np.ndarray:
        return mix_at_snr(voice, noise, sample_rate=RATE, snr_db=snr, speech_level_dbfs=-35,
                          ramp_s=0.05, source="x")[0]  # fmt: skip

    def failed(sound: np.ndarray, snr: float = -9.0) -> set[str]:
        rows = noise_rows(sound, mixed(snr), quiet=quiet, sample_rate=RATE, snr_db=snr,
                          noise_dbfs=-35 - snr, fps=30, clip="c", condition="x")  # fmt: skip
        return {r.measure for r in rows if r.passed is False}

    assert failed(mixed(-9.0)) == set()
    assert failed(mixed(-6.0)) == {"mix_error_db", "noise_level_error"}
    late = np.concatenate([np.zeros(RATE // 20, np.float32), mixed(-9.0)])[: len(voice)]
    assert "speech_lag_ms" in failed(late)


def test_noise_the_clips_cannot_carry_is_refused_with_its_key(tmp_path) -> None:
    text = _text()
    at = "noise: {snr_db: -9}, method: viseme_baseline,"
    muted = text.replace(at, at + " modality: visual_only,")
    assert "conditions[10].noise: noise is mixed with the voice: this condition is visual_only" in (
        _problems(muted, tmp_path))  # fmt: skip
    missing = text.replace("noise: {snr_db: -9}, method: viseme_baseline,",
                           "noise: {snr_db: -9, source: cafe.wav}, method: viseme_baseline,")
    assert "conditions[10].noise.source: noise file not found" in _problems(missing, tmp_path)
    truth = text.replace("    standard: {srt_db: -8.0", "    standard_m6: {srt_db: -8.0")
    assert "unknown condition series 'standard_m6'" in _problems(truth, tmp_path)


def test_noise_no_threshold_or_clip_could_come_from_is_refused(tmp_path) -> None:
    text = _text()
    two = re.sub(r"      - \{id: (saru|ushi|kuma|shika), text: \{ja: .*\n", "", text)
    two = re.sub(r"      - \{id: (saru|ushi|kuma|shika), text: \S+。\}\n", "", two)
    two = re.sub(r"      - \{id: neko, text: \{ja: .*\n", "", two)
    two = re.sub(r"answers: \{.*\}", "answers: {inu: inu, neko: inu}", two)
    two = two.replace("      - {id: inu, text: {ja: いぬ, en: inu}}\n",
                      "      - {id: inu, text: {ja: いぬ, en: inu}}\n"
                      "      - {id: other, text: {ja: ほか, en: other}}\n")  # fmt: skip
    assert "words in noise need three or more labels" in _problems(two, tmp_path)
    loud = text.replace("noise: {snr_db: -18}, method: viseme_baseline,",
                        "noise: {snr_db: -30}, method: viseme_baseline,")  # fmt: skip
    assert "the noise would be at -5 dBFS RMS and clip" in _problems(loud, tmp_path)
    short = text.replace("rendering: {width: 640, height: 360, fps: 30}",
                         "rendering: {width: 640, height: 360, fps: 30, pad_s: 0.1}")  # fmt: skip
    assert "leaves no noise without the voice beyond the 0.05 s fades" in _problems(short, tmp_path)


def test_a_fixed_snr_design_is_compared_per_condition_not_thresholded(tmp_path) -> None:
    """One SNR per series: no threshold can be fitted, so the task keeps the identification
    models (per-condition accuracy and the GEE) instead of an SRT."""
    block = "    task: word\n"
    text = _text().replace(block, block + "    conditions: [audio_m9, standard_m9, "
                           "emphasized_m9]\n")  # fmt: skip
    path = tmp_path / "fixed.yaml"
    path.write_text(text, encoding="utf-8")
    protocol = load_protocol_text(text, path=path, base_dir=tmp_path)
    assert not srt.is_noise_task(protocol, protocol.tasks[0])
    assert srt.is_noise_task(load_protocol(protocol_path("kato2021_srt")),
                             load_protocol(protocol_path("kato2021_srt")).tasks[0])  # fmt: skip


def test_a_threshold_is_recovered_from_answers_drawn_from_it() -> None:
    x = np.repeat(SNRS, 300)
    p = p_correct(x, srt=-8.0, slope=0.1, guess=1 / 6, lapse=0.02)
    y = (np.random.default_rng(3).random(len(x)) < p).astype(int)
    fit = srt.fit_srt(pd.DataFrame({"snr_db": x, "correct": y}), guess=1 / 6)
    assert fit.note == "" and abs(fit.srt_db + 8) < 0.4 and abs(fit.slope_per_db - 0.1) < 0.02
    assert fit.srt_ci_low < -8 < fit.srt_ci_high and fit.srt_ci_high - fit.srt_ci_low < 1.0


def _study(protocol, *, participants: int, seed: int) -> pd.DataFrame:
    rows = []
    for k in range(participants):
        rows += simulated_rows(protocol, participant=f"P{k + 1:03d}",
                               rng=np.random.default_rng([seed, k]))  # fmt: skip
    frame = pd.DataFrame(rows)
    return frame[frame["screen"] == "identify"]


def test_thresholds_and_benefits_are_recovered_through_the_session_pipeline() -> None:
    protocol = load_protocol(protocol_path("kato2021_srt"))
    rows = _study(protocol, participants=12, seed=4)
    table = srt.srt_table(rows, protocol, protocol.tasks[0])
    assert list(table["condition"].unique()) == SERIES and (table["n"] == 42).all()
    assert table.loc[table["condition"] == "audio", "benefit_db"].isna().all()
    summary, tests = srt.srt_tests(table, reference="audio")
    truth = protocol.simulation.srt
    for r in summary.itertuples():
        # one listener effect (SD 1.5 dB) moves every series of a participant alike: the
        # means share it, so each is held within 1.5 times its 95 % half-width (about 3 SE)
        half = (r.srt_db_ci_high - r.srt_db_ci_low) / 2
        assert abs(r.srt_db_mean - truth[r.condition].srt_db) <= 1.5 * half, r
        if r.condition != "audio":  # the same tolerance for the benefit (its coverage at
            want = truth["audio"].srt_db - truth[r.condition].srt_db  # the nominal rate is
            half = (r.benefit_db_ci_high - r.benefit_db_ci_low) / 2  # the slow tests' job)
            assert abs(r.benefit_db_mean - want) <= 1.5 * half, r
    assert {"srt_db", "benefit_db"} <= set(tests["measure"])


def _truths(protocol, **srt_db: float):
    truths = {s: t.model_copy(update={"srt_db": srt_db.get(s, t.srt_db)})
              for s, t in protocol.simulation.srt.items()}  # fmt: skip
    return protocol.model_copy(update={"simulation": protocol.simulation.model_copy(
        update={"srt": truths})})  # fmt: skip


def test_a_series_beyond_the_snrs_tested_keeps_its_row_and_is_named() -> None:
    """A listener whose threshold lies beyond the SNRs rendered (audio far above, emphasized
    far below) gets no falsely precise SRT: the rows stay, their note says the answers bound
    the threshold; a series answered at one SNR keeps its row too; the enhancement is not
    estimated from a slope on its bound; the other series are still compared."""
    protocol = _truths(load_protocol(protocol_path("kato2021_srt")), audio=30.0,
                       emphasized=-40.0)  # fmt: skip
    rows = _study(protocol, participants=4, seed=5)
    table = srt.srt_table(rows, protocol, protocol.tasks[0])
    assert list(table["condition"].unique()) == SERIES  # no series vanishes
    audio = table[table["condition"] == "audio"]
    assert audio["note"].str.contains("the SRT lies above them").all(), audio["note"].tolist()
    emph = table[table["condition"] == "emphasized"]
    assert emph["note"].str.contains("the SRT lies below them").all(), emph["note"].tolist()
    assert table["benefit_db"].isna().all()  # no determined audio-only SRT to measure from
    summary, tests = srt.srt_tests(table, reference="audio")
    assert set(summary.set_index("condition").loc[["audio", "emphasized"], "determined"]) == {0}
    base = summary.set_index("condition").loc["baseline"]  # each mean says what it is over
    assert base["srt_db_n"] == 4 and base["benefit_db_n"] == 0
    pairs = tests[(tests["measure"] == "srt_db") & (tests["a"] != "all")]
    assert {(r.a, r.b) for r in pairs.itertuples()} == {("baseline", "standard")}
    # one SNR only: a track that never left the easy end
    audio_conds = [c.id for c in protocol.conditions if c.series_id == "audio"]
    one = rows[~rows["condition"].isin(audio_conds[:-1])]
    table = srt.srt_table(one, protocol, protocol.tasks[0])
    audio = table[table["condition"] == "audio"]
    assert len(audio) == 4 and audio["srt_db"].isna().all()
    said = r"every answer at one SNR \(0 dB, [0-2] of 6 scored units right\): the SRT lies above"
    assert audio["note"].str.match(said).all(), audio["note"].tolist()  # 1/6 guess
    # a slope on its bound: the enhancement away from the SRT is not known
    steep = srt.srt_table(_study(_fixed(load_protocol(protocol_path("kato2021_srt"))),
                                 participants=12, seed=4), protocol, protocol.tasks[0])  # fmt: skip
    on_bound = np.isclose(steep["slope_per_db"], srt.SLOPE_BOUND[1])
    assert steep.loc[on_bound, "visual_enhancement"].isna().all()
    inside = ~on_bound & steep["benefit_db"].notna()
    assert inside.any() and steep.loc[inside, "visual_enhancement"].notna().all()


def test_healthy_answers_raise_no_note_of_a_series_left_out() -> None:
    """At the shipped truths nothing is left out of the tests but what the notes name: the
    audio-only reference has no benefit by definition and is not called 'left out'."""
    from facelab.analysis.tasks import analyze_tasks

    protocol = load_protocol(protocol_path("kato2021_srt"))
    rows = _study(protocol, participants=8, seed=4)
    res = analyze_tasks(rows, protocol, rng=np.random.default_rng(0), n_boot=0)
    assert not [n for n in res.notes if "audio left out" in n], res.notes
    assert "srt_tests" in res.tables and len(res.tables["srt_tests"])


def _coverage(protocol, *, participants: int, seed: int) -> dict[str, float]:
    rows = _study(protocol, participants=participants, seed=seed)
    table = srt.srt_table(rows, protocol, protocol.tasks[0])
    out = {}
    for series, part in table.groupby("condition"):
        want = protocol.simulation.srt[series].srt_db
        out[series] = float(((part["srt_ci_low"] <= want) & (want <= part["srt_ci_high"])).mean())
    return out


def _fixed(protocol):
    truths = {s: t.model_copy(update={"srt_sd_db": 0.0})
              for s, t in protocol.simulation.srt.items()}  # fmt: skip
    return protocol.model_copy(update={"simulation": protocol.simulation.model_copy(
        update={"srt": truths})})  # fmt: skip


@pytest.mark.slow
def test_each_participants_srt_interval_covers_the_truth() -> None:
    """Constant stimuli as shipped (42 trials per series): coverage of the 95 % profile
    intervals over 150 simulated participants - reported, and held to 0.90-0.98."""
    coverage = _coverage(_fixed(load_protocol(protocol_path("kato2021_srt"))), participants=150,
                         seed=41)  # fmt: skip
    print(f"SRT interval coverage, constant stimuli: {coverage}")
    assert all(0.90 <= v <= 0.98 for v in coverage.values()), coverage


STAIRCASE_BLOCKS = """blocks:
  - {id: audio, stimulus_set: words, task: word, sets: 1, presentations_per_condition: 1,
     conditions: [audio_m18, audio_m15, audio_m12, audio_m9, audio_m6, audio_m3, audio_0],
     design: staircase, staircase: {rule: up_down, up: 1, down: 1, start: audio_0, trials: 30}}
  - {id: emphasized, stimulus_set: words, task: word, sets: 1, presentations_per_condition: 1,
     conditions: [emphasized_m18, emphasized_m15, emphasized_m12, emphasized_m9, emphasized_m6,
                  emphasized_m3, emphasized_0],
     design: staircase,
     staircase: {rule: up_down, up: 1, down: 1, start: emphasized_0, trials: 30}}

presentation:"""


@pytest.mark.slow
def test_a_one_up_one_down_staircase_per_series_gives_covered_thresholds(tmp_path) -> None:
    """The same words with a 1-up-1-down staircase per series (tracking 50 % right, 30
    trials): the SNRs come from the rule, and the thresholds fitted to them cover the truth."""
    text = _text()
    text = text[: text.index("blocks:")] + STAIRCASE_BLOCKS + text[text.index(
        "presentation:") + len("presentation:"):]  # fmt: skip
    path = tmp_path / "srt_staircase.yaml"
    path.write_text(text, encoding="utf-8")
    protocol = _fixed(load_protocol_text(text, path=path, base_dir=tmp_path))
    coverage = _coverage(protocol, participants=150, seed=43)
    print(f"SRT interval coverage, 1-up-1-down staircase: {coverage}")
    assert set(coverage) == {"audio", "emphasized"}
    assert all(0.90 <= v <= 0.98 for v in coverage.values()), coverage


@pytest.mark.slow
def test_noisy_clips_share_one_picture_and_carry_their_mix(tmp_path, capsys) -> None:
    """One method and the voice alone at -15, -6 and 0 dB SNR for one word: two pictures are
    rendered, four clips re-mux them with their own mix; the checks find every mix where it
    was put, as made, with the noise at its level; the speech level is the same in all."""
    import csv
    import json

    from facelab.experiment.cli import main

    block = "    task: word\n"
    text = _text().replace(block, block + "    conditions: [audio_m15, audio_m6, audio_0, "
                           "standard_m15, standard_m6, standard_0]\n")  # fmt: skip
    text = re.sub(r"      - \{id: (neko|saru|ushi|kuma|shika), text: \S+。\}\n", "", text)
    text = re.sub(r"answers: \{.*\}", "answers: {inu: inu}", text)
    path = tmp_path / "srt.yaml"
    path.write_text(text, encoding="utf-8")
    out = tmp_path / "clips"
    assert main(["render", str(path), "--out", str(out), "--size", "320x180", "--quiet"]) == 0
    assert "(2 rendered, 4 re-muxed" in capsys.readouterr().out
    rows = [r for r in csv.DictReader((out / "clips.csv").open(encoding="utf-8"))
            if r["stimulus"] == "inu"]  # fmt: skip
    mixes = {r["condition"]: json.loads((out / f"{r['clip_id']}.json").read_text())["noise"]
             for r in rows}  # fmt: skip
    assert {c: m["snr_db"] for c, m in mixes.items()} == {
        "audio_m15": -15, "audio_m6": -6, "audio_0": 0, "standard_m15": -15, "standard_m6": -6,
        "standard_0": 0}  # fmt: skip
    assert all(abs(m["speech_level_dbfs"] + 35) < 0.01 for m in mixes.values())
    checks = [r for r in csv.DictReader((out / "stimulus_checks.csv").open(encoding="utf-8"))
              if r["check"] == "noise" and "__inu__" in r["clip"]]  # fmt: skip
    assert len(checks) == 3 * 6 and all(r["passed"] == "true" for r in checks)


@pytest.mark.slow
def test_a_words_in_noise_session_online_in_chromium_is_exported_and_thresholded(
    tmp_path,
) -> None:
    """The words-in-noise task served in headless Chromium (the voice alone and one method,
    three SNRs, two words): every trial answered with a word, exported as the lab's files and
    analysed into srt.csv."""
    import json

    from facelab.experiment.cli import main
    from tests.task_protocols import one_online_session, short_task_protocol

    edits = {r"    task: word\n": "    task: word\n    conditions: [audio_m12, audio_m6, audio_0, "
             "standard_m12, standard_m6, standard_0]\n",
             r"      - \{id: (saru|ushi|kuma|shika), text: \S+。\}\n": "",
             r"answers: \{.*\}": "answers: {inu: inu, neko: neko}"}  # fmt: skip
    path = short_task_protocol("kato2021_srt", tmp_path, edits)
    server, rows = one_online_session(path, tmp_path)
    assert (tmp_path / "shots" / "identify.png").exists()
    assert len(rows) == 12 == len(server.study.planned("P0001"))
    assert all(r["correct"] in (0, 1) for r in rows)
    out = tmp_path / "results"
    assert main(["export", "--db", f"sqlite:///{tmp_path / 'db.sqlite'}", "--results",
                 str(out)]) == 0  # fmt: skip
    assert json.loads(next(out.rglob("*_session.json")).read_text())["mode"] == "online"
    report = tmp_path / "report"
    assert main(["analyze", str(path), str(out), "--force", "--out", str(report)]) == 0
    table = pd.read_csv(report / "srt.csv")
    assert list(table["condition"]) == ["audio", "standard"] and (table["n"] == 6).all()
    assert (report / "fig_srt_word.png").exists()
