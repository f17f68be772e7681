"""A condition's modality (issue 52.1): audiovisual, visual_only (muted, for lip-reading) and
audio_only (the voice with a still face, or none). Made into the clips, hashed, and measured by
the stimulus checks - a promise a clip does not keep fails."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from facelab.stimuli.checks.clip_checks import modality_rows
from facelab.stimuli.checks.face_tracker import ClipTracking
from tests.protocol_edits import kato_vowels_only

ROOT = Path(__file__).resolve().parents[1]
EXTRA = """  - {id: standard_v, label: {ja: 標準・無音, en: Standard muted}, method: vowel_blend,
     params: {z: standard}, modality: visual_only}
  - {id: standard_a, label: {ja: 音声のみ, en: Audio only}, method: vowel_blend,
     params: {z: standard}, modality: audio_only}
"""


def _tracking(aperture: np.ndarray, detection: float = 0.9) -> ClipTracking:
    n = len(aperture)
    return ClipTracking(
        "x.mp4", np.full(n, detection), np.zeros((n, 4)), aperture, np.full(n, 0.3),
        np.full(n, 0.5), "test", np.zeros((n, 2, 2), np.uint8),
    )  # fmt: skip


def _failed(rows) -> set[str]:
    return {r.measure for r in rows if r.passed is False}


def test_each_modality_promise_fails_when_the_clip_breaks_it() -> None:
    rng = np.random.default_rng(1)
    voice = 0.1 * rng.standard_normal(48_000)
    moving = 0.03 + 0.03 * np.sin(np.linspace(0, 20, 60))
    still = np.full(60, 0.006)
    kw = {"clip": "c", "condition": "x"}
    assert _failed(modality_rows(_tracking(moving), voice, modality="visual_only",
                                 face="still", **kw)) == {"audio_peak"}  # fmt: skip
    assert not _failed(modality_rows(_tracking(moving), np.zeros(48_000),
                                     modality="visual_only", face="still", **kw))  # fmt: skip
    assert _failed(modality_rows(_tracking(moving), voice, modality="audio_only",
                                 face="still", **kw)) == {"aperture_spread"}  # fmt: skip
    assert _failed(modality_rows(_tracking(still), np.zeros(48_000), modality="audio_only",
                                 face="still", **kw)) == {"audio_rms"}  # fmt: skip
    assert _failed(modality_rows(_tracking(still), voice, modality="audio_only", face="none",
                                 **kw)) == {"face_detection_max"}  # fmt: skip
    assert modality_rows(_tracking(moving), voice, modality="audiovisual", face="still",
                         **kw) == []  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("face", ["still", "none"])
def test_muted_and_audio_only_clips_are_made_and_measured(tmp_path: Path, face: str) -> None:
    """kato2021's vowels with a muted and an audio-only twin of the standard condition: the
    muted clip has the standard clip's face motion and no sound; the audio-only clip has its
    sound and a face that does not move (or none); the checks pass and say so; the clip spec
    hash tells the twins apart."""
    import csv

    from facelab.experiment.cli import main
    from facelab.protocol import load_protocol
    from facelab.stimuli.render.clipspec import ClipJob, clip_spec_hash

    text = kato_vowels_only((ROOT / "protocols" / "kato2021.yaml").read_text(encoding="utf-8"))
    text = text.replace("\nstimulus_sets:", "\n" + EXTRA + "stimulus_sets:", 1)
    if face == "none":
        text = text.replace("\nrendering:\n", "\nrendering:\n  audio_only_face: none\n", 1)
        assert "audio_only_face: none" in text
    path = tmp_path / "modality.yaml"
    path.write_text(text, encoding="utf-8")
    out = tmp_path / "clips"
    assert main(["render", str(path), "--out", str(out), "--size", "320x180", "--fps", "15",
                 "--quiet", "--accept-check", "av_sync"]) == 0  # fmt: skip
    rows = list(csv.DictReader((out / "stimulus_checks.csv").open(encoding="utf-8")))
    modality = {(r["condition"], r["measure"]): r for r in rows if r["check"] == "modality"}
    assert modality["standard_v", "audio_peak"]["passed"] == "true"
    assert float(modality["standard_v", "audio_peak"]["value"]) == 0.0
    assert modality["standard_a", "audio_rms"]["passed"] == "true"
    shown = "face_detection_max" if face == "none" else "aperture_spread"
    assert modality["standard_a", shown]["passed"] == "true"
    # the muted twin is not an "identical clip" of the audiovisual one, and it is articulated
    assert not [r for r in rows if r["check"] == "difference" and r["passed"] == "false"]
    assert any(r["check"] == "articulation" and r["condition"] == "standard_v" for r in rows)
    assert not any(r["condition"] == "standard_a" and r["check"] in ("articulation", "av_sync")
                   for r in rows)  # fmt: skip
    tracking: dict[str, list[float]] = {}
    for r in csv.DictReader((out / "face_tracking.csv").open(encoding="utf-8")):
        tracking.setdefault(r["clip"], []).append(float(r["aperture"] or "nan"))
    standard, muted = (
        np.array(tracking[f"vowels__aiueo__{c}"]) for c in ("standard", "standard_v")
    )
    assert np.nanmax(np.abs(standard - muted)) < 0.005  # the same face motion
    protocol = load_protocol(path)
    stim = protocol.stimulus_set("vowels").stimuli[0]
    hashes = {c: clip_spec_hash(protocol, ClipJob("", "vowels", stim, c), base_dir=tmp_path)
              for c in ("standard", "standard_v", "standard_a")}  # fmt: skip
    assert len(set(hashes.values())) == 3
