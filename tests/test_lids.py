"""Closed eyes stay closed: a blink mixed with a squint, a smile's cheek raise or a downward
look shuts the default head's eye without driving one lid through the other."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from facelab.stimuli.avatar import Avatar, default_head
from facelab.stimuli.avatar.lids import close_lids, lid_model
from facelab.stimuli.avatar.rig import HeadPose
from facelab.stimuli.behaviour.library import ROTATIONS
from facelab.stimuli.behaviour.realise import BehaviourFrames, apply_to_weights


@pytest.fixture(scope="module")
def head() -> Avatar:
    return default_head()


def _gaps(head: Avatar, verts: np.ndarray, side: str) -> np.ndarray:
    """Metres between each upper-lid margin vertex and the lower one nearest across, over
    the whole opening (corners included)."""
    upper, lower = head.parts[f"lid_upper_{side}"], head.parts[f"lid_lower_{side}"]
    x = head.neutral[:, 0]
    across = lower[np.argmin(np.abs(x[lower][None, :] - x[upper][:, None]), axis=1)]
    return verts[upper, 1] - verts[across, 1]


MIXES = (
    {"eyeSquint": 1.0},
    {"cheekSquint": 1.0},
    {"eyeSquint": 1.0, "cheekSquint": 1.0},
    {"eyeSquint": 0.3, "cheekSquint": 0.45},  # the impression synth's smile
    {"eyeLookDown": 1.0},
)


@pytest.mark.parametrize("mix", MIXES, ids=lambda m: "+".join(m))
@pytest.mark.parametrize("side", ["left", "right"])
def test_a_blink_in_a_squint_or_smile_closes_the_eye_without_crossing(
    head: Avatar, mix: dict[str, float], side: str
) -> None:
    """Along the whole opening no pair of margin vertices closes further than the blink alone
    closes it (that is the rig's shut eye; its corners overlap by up to 0.7 mm by
    themselves), where linear addition drives the upper lid 2-8 mm through the lower; the
    eye is shut (under 1 mm) within 4 mm of the pupil, and the smile keeps its weights."""
    name = side.title()
    weights = {f"eyeBlink{name}": 1.0, **{f"{k}{name}": v for k, v in mix.items()}}
    raw = head.weight_vector(weights)[None]
    limited, n = close_lids(raw, lid_model(head))
    shut = _gaps(head, head.deform(head.weight_vector({f"eyeBlink{name}": 1.0})), side)
    assert (_gaps(head, head.deform(raw[0]), side) - shut).min() < -0.002
    gaps = _gaps(head, head.deform(limited[0]), side)
    mid = np.abs(head.neutral[head.parts[f"lid_upper_{side}"], 0]) - 0.033  # from the pupil
    assert n == 1 and (gaps - shut).min() > -3e-4  # 0.3 mm: corner pairs the rule does not see
    assert gaps[np.abs(mid) < 0.004].max() < 0.001
    names = head.target_names
    for k, v in mix.items():
        if k != "eyeLookDown":
            assert limited[0, names.index(f"{k}{name}")] == pytest.approx(v, abs=1e-6)
    assert 0 < limited[0, names.index(f"eyeBlink{name}")] < 1


def test_a_blink_alone_and_a_squint_alone_are_left_as_they_are(head: Avatar) -> None:
    model = lid_model(head)
    alone = {"eyeBlinkLeft": 1.0, "eyeBlinkRight": 0.6}
    other_eye = {"eyeSquintLeft": 1.0, "cheekSquintLeft": 1.0, "eyeBlinkRight": 1.0}
    for weights in (alone, other_eye):
        raw = head.weight_vector(weights)[None]
        out, n = close_lids(raw, model)
        assert n == 0
        np.testing.assert_array_equal(out, raw)


def test_an_avatar_without_lid_landmarks_keeps_its_own_shapes(head: Avatar) -> None:
    bare = head.replace(
        landmarks={k: v for k, v in head.landmarks.items() if "lid" not in k}
    )  # fmt: skip
    assert lid_model(bare) is None
    raw = head.weight_vector({"eyeBlinkLeft": 1.0, "eyeSquintLeft": 1.0})[None]
    np.testing.assert_array_equal(close_lids(raw, None)[0], raw)


def test_behaviour_on_the_weights_limits_the_lids_and_reports_it(head: Avatar) -> None:
    """A smile held over three frames with a blink in the middle one: that frame's blink gives
    way, the report counts it; without the lid model the weights are only clamped."""
    n = 3
    frames = BehaviourFrames(
        np.arange(n) / 30.0,
        {"eyeSquintLeft": np.full(n, 0.3), "cheekSquintLeft": np.full(n, 0.45),
         "eyeBlinkLeft": np.array([0.0, 1.0, 0.0])},
        np.zeros((n, len(ROTATIONS))),
    )  # fmt: skip
    speech = np.zeros((n, len(head.target_names)), np.float32)
    kw = dict(target_names=head.target_names, has_head=True, has_eyes=True)
    out, _, report = apply_to_weights(frames, speech, lids=lid_model(head), **kw)
    plain, _, plain_report = apply_to_weights(frames, speech, **kw)
    blink = head.target_names.index("eyeBlinkLeft")
    assert report["lid_limited_frames"] == 1 and plain_report["lid_limited_frames"] == 0
    assert out[1, blink] < 0.9 and plain[1, blink] == 1.0
    np.testing.assert_array_equal(np.delete(out, blink, axis=1), np.delete(plain, blink, axis=1))


def test_a_behaviour_clips_cache_key_covers_what_realising_its_plan_drew(head: Avatar) -> None:
    """`facelab render` reuses a behaviour clip when its key matches; the key holds the
    realised weights and poses, not only the plan, so a change in how a plan is drawn (as the
    lid limit was) renders the clip again instead of keeping frames drawn the old way."""
    from dataclasses import replace

    from facelab.stimuli.behaviour.clip import behaviour_for_clip
    from facelab.stimuli.render.build import _behaviour_hash
    from facelab.stimuli.speech.tts import synthesize

    speech = synthesize("こんにちは。")
    n = 60
    beh = behaviour_for_clip(
        setting="composite", emotion={"joy": 0.9}, base_dir=Path("."), seed=4, speech=speech,
        pad_s=0.2, fps=30, n_frames=n,
        weights=np.zeros((n, len(head.target_names)), np.float32), avatar=head,
    )  # fmt: skip
    assert beh is not None
    key = _behaviour_hash(beh)
    assert _behaviour_hash(replace(beh, weights=beh.weights.copy())) == key
    moved = beh.weights.copy()
    moved[n // 2, head.target_names.index("eyeBlinkLeft")] += 0.25
    assert _behaviour_hash(replace(beh, weights=moved)) != key
    turned = [HeadPose(yaw=1.0), *beh.poses[1:]]
    assert _behaviour_hash(replace(beh, poses=turned)) != key
