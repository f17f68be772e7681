"""Avatars users bring (skinned glTF, Ready Player Me, VRM 0.x / 1.0) and the rig API.

The files are written by :mod:`facelab.stimuli.avatar.samples` the way those exporters write
them (skins with rest rotations and inverse bind matrices, several meshes sharing target
names, a texture, VRM extensions, VRM 0.x facing -z), then read back by ``avatar.load``.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from facelab.errors import AvatarError
from facelab.experiment.cli import main
from facelab.stimuli.avatar import default_head, load, save
from facelab.stimuli.avatar.rig import HeadPose, euler_matrix, gaze_weights, match_roles, skin
from facelab.stimuli.avatar.samples import (
    HAIR_RGB,
    HEAD_CENTRE,
    HEAD_JOINT_Y,
    HEAD_RADII,
    KINDS,
    MOUTH_Y,
    write_sample,
)


@pytest.fixture(scope="module")
def samples(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("avatars")
    out = {k: write_sample(folder / f"{k}.glb", kind=k) for k in KINDS}
    out["vrm0_vrm"] = write_sample(folder / "model.vrm", kind="vrm0")
    out["rpm_gltf"] = write_sample(folder / "rpm.gltf", kind="rpm")
    return out


@pytest.mark.parametrize("kind", KINDS)
def test_sample_files_load_in_the_rest_pose_facing_the_camera(samples, kind: str) -> None:
    a = load(samples[kind])
    assert a.source["kind"] == ("gltf" if kind == "skinned" else kind)
    head_mesh = a.parts["Wolf3D_Head" if kind == "rpm" else ("Face" if "vrm" in kind else "head")]
    v = a.neutral[head_mesh]
    # the skinned mesh node's own translation (5 m) is ignored; rest pose = intended geometry
    np.testing.assert_allclose((v.min(0) + v.max(0)) / 2, HEAD_CENTRE, atol=2e-3)
    np.testing.assert_allclose((v.max(0) - v.min(0)) / 2, HEAD_RADII, rtol=0.02)
    # the eyes are in front (+z): VRM 0.x (facing -z in the file) was turned round
    for part in [p for p in a.parts if "eye" in p.lower()]:
        assert a.neutral[a.parts[part], 2].mean() > 0.05
    sk = a.skeleton
    assert sk is not None and set(sk.roles) == {"neck", "head", "eye_left", "eye_right"}
    np.testing.assert_allclose(sk.pivots[sk.roles["head"]], [0, HEAD_JOINT_Y, 0], atol=1e-5)
    assert sk.pivots[sk.roles["eye_left"], 0] > 0 > sk.pivots[sk.roles["eye_right"], 0]
    assert len(a.textures) == 1 and a.uv is not None


def test_formats_are_recognised_from_any_container(samples) -> None:
    assert load(samples["vrm0_vrm"]).source["kind"] == "vrm0"
    rpm = load(samples["rpm_gltf"])
    assert rpm.source["kind"] == "rpm"
    assert {"jawOpen", "viseme_aa", "viseme_PP"} <= set(rpm.targets)
    assert len(set(rpm.targets)) == 52 + 15


@pytest.mark.parametrize("kind", ["skinned", "rpm"])
def test_one_target_name_drives_every_mesh_that_has_it(samples, kind: str) -> None:
    a = load(samples[kind])
    teeth = a.parts["Wolf3D_Teeth" if kind == "rpm" else "teeth"]
    moved = a.deform({"jawOpen": 1.0}) - a.neutral
    lower = teeth[a.neutral[teeth, 1] < MOUTH_Y]
    assert np.all(moved[lower, 1] < -0.009)  # the lower teeth drop with the jaw
    head = a.parts["Wolf3D_Head" if kind == "rpm" else "head"]
    assert moved[head, 1].min() < -0.005


def test_vrm_presets_become_facelab_targets(samples) -> None:
    v0, v1 = load(samples["vrm0"]), load(samples["vrm1"])
    for a in (v0, v1):
        assert {"viseme_aa", "viseme_ih", "viseme_ou", "viseme_E", "viseme_oh"} <= set(a.targets)
        assert {"eyeBlinkLeft", "eyeBlinkRight", "vrm_happy"} <= set(a.targets)
        teeth = a.parts["teeth"]
        # aa binds the head and the teeth meshes: both move
        assert np.abs(a.targets["viseme_aa"][teeth]).max() > 0.005
        assert a.source["presets"]["viseme_aa"] == "aa"
        # a left blink moves only the avatar's left (+x) side
        left = a.targets["eyeBlinkLeft"]
        moving = np.linalg.norm(left, axis=1) > 1e-4
        assert moving.any() and np.all(a.neutral[moving, 0] > 0)
    # VRM 0.x has one both-eyes blink; split by side and recorded as such
    assert v0.source["presets"]["eyeBlinkLeft"] == "blink (one side)"
    assert v1.source["presets"]["eyeBlinkLeft"] == "blinkLeft"
    # the same preset in both versions gives the same shape (after VRM 0.x is turned round)
    np.testing.assert_allclose(v0.targets["viseme_oh"], v1.targets["viseme_oh"], atol=1e-6)


def test_head_turn_is_a_rotation_about_the_head_and_neck_pivots(samples) -> None:
    a = load(samples["skinned"])
    sk = a.skeleton
    head = a.parts["head"]
    rigid = head[a.neutral[head, 1] > 1.61]  # weight 1 on the head joint
    p_head, p_neck = sk.pivots[sk.roles["head"]], sk.pivots[sk.roles["neck"]]
    # all on the head joint
    posed = a.deform({}, pose=HeadPose(yaw=30, pitch=-10, roll=5, neck_share=0.0))
    r = euler_matrix(30, -10, 5)
    np.testing.assert_allclose(posed[rigid], (a.neutral[rigid] - p_head) @ r.T + p_head, atol=1e-5)
    # shared with the neck: neck rotation about its pivot, then the head's about its own
    pose = HeadPose(yaw=30, neck_share=0.4)
    posed = a.deform({}, pose=pose)
    rn, rh = euler_matrix(12, 0, 0), euler_matrix(18, 0, 0)
    expect = (((a.neutral[rigid] - p_head) @ rh.T + p_head) - p_neck) @ rn.T + p_neck
    np.testing.assert_allclose(posed[rigid], expect, atol=1e-5)
    # the rigid hat (a child of the head joint, not skinned) turns with the head
    hat = a.parts["hat"]
    np.testing.assert_allclose(
        posed[hat],
        ((((a.neutral[hat] - p_head) @ rh.T + p_head) - p_neck) @ rn.T + p_neck),
        atol=1e-5,
    )
    # the torso stays
    torso = a.parts["torso"]
    np.testing.assert_array_equal(posed[torso], a.neutral[torso])
    # the eyes turn about their own centres, after the head
    eye = a.parts["eye_left"]
    gaze = a.deform({}, pose=HeadPose(eye_yaw=20))
    c = a.neutral[eye].mean(axis=0)
    front = eye[np.argmax(a.neutral[eye, 2])]
    turned = gaze[front] - c
    assert np.degrees(np.arctan2(turned[0], turned[2])) == pytest.approx(20, abs=0.5)


def test_default_head_has_a_rig_that_turns_head_neck_and_eyes() -> None:
    h = default_head()
    sk = h.skeleton
    assert sk is not None and set(sk.roles) == {"neck", "head", "eye_left", "eye_right"}
    np.testing.assert_allclose(sk.weights.sum(axis=1), 1.0, atol=1e-6)
    nose = h.landmarks["nose_tip"]
    posed = h.deform({}, pose=HeadPose(yaw=20))
    assert posed[nose, 0] - h.neutral[nose, 0] > 0.02  # towards the avatar's left (+x)
    np.testing.assert_array_equal(posed[h.parts["torso"]], h.neutral[h.parts["torso"]])
    neck = h.parts["neck"]
    bottom = neck[h.neutral[neck, 1] < -0.205]  # where the neck meets the torso
    np.testing.assert_allclose(posed[bottom], h.neutral[bottom], atol=1e-7)
    # nodding: chin down and back
    chin = h.landmarks["chin"]
    nod = h.deform({}, pose=HeadPose(pitch=15))
    assert nod[chin, 1] < h.neutral[chin, 1] and nod[chin, 2] < h.neutral[chin, 2]
    # gaze: the pupil (front pole of the eyeball) moves left and up
    for side in ("left", "right"):
        eye = h.parts[f"eye_{side}"]
        pole = eye[np.argmax(h.neutral[eye, 2])]
        look = h.deform({}, pose=HeadPose(eye_yaw=15, eye_pitch=-10))
        assert look[pole, 0] > h.neutral[pole, 0] + 0.002 and look[pole, 1] > h.neutral[pole, 1]
    # morph targets and pose combine: the jaw opens on a turned head
    both = h.deform({"jawOpen": 1.0}, pose=HeadPose(yaw=20))
    np.testing.assert_allclose(
        both, skin(h.deform({"jawOpen": 1.0}), sk, HeadPose(yaw=20)), atol=1e-6
    )


def test_skeleton_round_trips_through_gltf(tmp_path: Path) -> None:
    h = default_head()
    save(h, tmp_path / "head.glb")
    back = load(tmp_path / "head.glb")
    assert back.skeleton is not None
    assert back.skeleton.roles == h.skeleton.roles
    pose = HeadPose(yaw=-25, pitch=8, roll=-4, eye_yaw=10)
    np.testing.assert_allclose(back.deform({}, pose=pose), h.deform({}, pose=pose), atol=1e-6)


def test_pose_without_skeleton_is_a_clear_error(samples) -> None:
    h = default_head().replace(skeleton=None)
    with pytest.raises(AvatarError, match="no skeleton"):
        h.deform({}, pose=HeadPose(yaw=10))
    assert np.array_equal(h.deform({}, pose=HeadPose()), h.neutral)


def test_joint_names_of_common_rigs_map_to_roles() -> None:
    assert match_roles(["Hips", "Neck", "Head", "LeftEye", "RightEye"]) == {
        "neck": 1, "head": 2, "eye_left": 3, "eye_right": 4,
    }  # fmt: skip
    assert match_roles(["mixamorig:Neck", "mixamorig:Head"]) == {"neck": 0, "head": 1}
    assert match_roles(["J_Bip_C_Neck", "J_Bip_C_Head", "J_Adj_L_FaceEye", "J_Adj_R_FaceEye"]) == {
        "neck": 0, "head": 1, "eye_left": 2, "eye_right": 3,
    }  # fmt: skip
    assert match_roles(["neck_01", "head", "FACIAL_L_Eye", "FACIAL_R_Eye"]) == {
        "neck": 0, "head": 1, "eye_left": 2, "eye_right": 3,
    }  # fmt: skip
    assert match_roles(["spine", "forehead_bone"]) == {}


def test_gaze_weights_for_avatars_without_eye_joints() -> None:
    w = gaze_weights(12.5, -25)
    assert w["eyeLookOutLeft"] == w["eyeLookInRight"] == 0.5
    assert w["eyeLookUpLeft"] == w["eyeLookUpRight"] == 1.0
    assert w["eyeLookInLeft"] == w["eyeLookDownLeft"] == 0.0


def test_broken_skin_is_reported_not_a_traceback(samples, tmp_path: Path) -> None:
    doc = json.loads(Path(samples["rpm_gltf"]).read_text())
    doc["skins"][0]["joints"] = [999]
    bad = tmp_path / "bad.gltf"
    bad.write_text(json.dumps(doc))
    with pytest.raises(AvatarError, match=r"bad\.gltf"):
        load(bad)


@pytest.mark.slow
def test_render_frames_the_head_of_a_full_body_avatar_with_its_texture(samples) -> None:
    from facelab.stimuli.render.renderer import Renderer, RenderSettings

    a = load(samples["rpm"])
    with Renderer(a, RenderSettings(width=320, height=320)) as r:
        img = r.frame(a.weight_vector({}))
        turned = r.frame(a.weight_vector({}), pose=HeadPose(yaw=30))
        centre = r.project(np.array([HEAD_CENTRE]))[0]
    assert abs(centre[0] - 160) < 16 and abs(centre[1] - 160) < 40
    # the texture: hair colour at the top of the head, skin lower down (glTF uv orientation)
    top = img[int(centre[1]) - 70, 150:170].astype(float).mean(axis=0)
    low = img[int(centre[1]) + 60, 150:170].astype(float).mean(axis=0)
    assert np.linalg.norm(top - HAIR_RGB) < np.linalg.norm(top - (225, 180, 150))
    assert low.mean() > top.mean() + 40
    assert np.abs(turned.astype(int) - img.astype(int)).mean() > 2


@pytest.mark.slow
@pytest.mark.parametrize(("kind", "vroid"), [("vrm1", False), ("vrm0", True)])
def test_vowel_condition_on_a_vrm_plays_the_vowel_presets(
    tmp_path: Path, kato_text: str, kind: str, vroid: bool
) -> None:
    """kato2021's vowels render on a VRM 1.0 sample and on a VRM 0.x one in VRoid Studio's
    layout (several primitives, sparse targets, MToon, masked lashes, texture atlas)."""
    write_sample(tmp_path / "model.vrm", kind=kind, vroid=vroid)
    text = (
        kato_text.replace(
            "  - id: sentences\n    stimulus_set: sentences\n",
            "  - id: sentences2\n    stimulus_set: vowels\n",
        )
        .replace(
            "practice: {stimulus_set: sentences, stimulus: passage, condition: standard}",
            "practice: {stimulus_set: vowels, stimulus: aiueo, condition: standard}",
        )
        .replace("  avatar: default", "  avatar: model.vrm")
    )
    proto = tmp_path / "vrm.yaml"
    proto.write_text(text, encoding="utf-8")
    out = tmp_path / "clips"
    argv = ["render", str(proto), "--out", str(out), "--size", "160x120", "--fps", "10", "--quiet"]
    # the sample is an egg with a slit for a mouth: the face detector rightly doubts it, and at
    # 160x120 its slit changes by under 2 grey levels between conditions (6.7 at 640x360)
    assert main(argv) == 2
    accept = ["--accept-check", "face_visible", "--accept-check", "conditions_differ"]
    assert main([*argv, *accept]) == 0
    rows = list(csv.DictReader((out / "clips.csv").read_text(encoding="utf-8").splitlines()))
    assert len(rows) == 3
    # Z acts through the presets: the three conditions are three different clips
    assert len({r["sha256"] for r in rows}) == 3
    meta = {r["condition"]: json.loads((out / (r["clip_id"] + ".json")).read_text()) for r in rows}
    assert "vowel shapes" in meta["standard"]["stand_in"]
    assert meta["standard"]["avatar_kind"] == kind
    assert "no shape for" in meta["baseline"]["stand_in"]


def test_avatar_inspect_command(
    samples, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    assert main(["avatar", "inspect", str(samples["vrm0"])]) == 0
    out = capsys.readouterr().out
    assert "vrm0" in out and "vowel shapes" in out and "head=J_Bip_C_Head" in out
    assert main(["avatar", "inspect", "default", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["arkit_targets"] == "52/52" and report["viseme_targets"] == "15/15"
    assert report["methods"]["vowel_blend"].startswith("yes")
    assert main(["avatar", "inspect", str(tmp_path / "missing.glb")]) == 2
    assert main(["avatar", "sample", "--kind", "vrm1", "--out", str(tmp_path / "a.vrm")]) == 0
    assert main(["avatar", "sample", "--kind", "vrm1", "--out", str(tmp_path / "a.vrm")]) == 2


@pytest.mark.slow
def test_bench_render_runs_on_a_skinned_50k_vertex_avatar() -> None:
    from facelab.stimuli.bench import bench_render

    # the bench's code path on a 50k-vertex skinned avatar; its figures at 720p are the README's
    result = bench_render(runs=1, quick=True, msaa=1, avatar="skinned50k", size=(320, 180))
    assert result["avatar"] == "skinned50k" and result["vertices"] >= 45_000
    assert result["textures"] == 1
    for fps in (30, 60):
        entry = result[f"fps_{fps}"]
        assert entry["rtf"] > 0 and entry["clip_frames"] == entry["frames"]
        assert entry["stages_ms_per_frame"]["deform_ms"] > 0


@pytest.mark.slow
def test_framing_without_a_skeleton_uses_the_head_mesh(samples) -> None:
    from facelab.stimuli.render.renderer import Renderer, RenderSettings

    a = load(samples["rpm"]).replace(skeleton=None)
    with Renderer(a, RenderSettings(width=320, height=320)) as r:
        centre = r.project(np.array([HEAD_CENTRE]))[0]
    assert abs(centre[0] - 160) < 16 and abs(centre[1] - 160) < 40


def test_skinning_blends_each_influence_by_its_weight() -> None:
    """Rows with several influences (as exporters write them) are the weighted sum of each
    joint's transform of the vertex, the formula written out per vertex."""
    from facelab.stimuli.avatar.rig import Skeleton

    rng = np.random.default_rng(3)
    n = 200
    weights = rng.dirichlet(np.ones(3), size=n).astype(np.float32)
    weights = np.column_stack([weights, np.zeros(n, np.float32)])
    weights[:20] = 0.0  # unweighted rows stay where they are
    weights[20:80] = [0.0, 1.0, 0.0, 0.0]  # rows bound to the head alone (the fast path)
    weights[80:100] = [0.0, 0.0, 1.0, 0.0]  # ... and to the eye alone
    joints = np.tile([0, 1, 2, 0], (n, 1))
    sk = Skeleton(
        names=("neck", "head", "eye"),
        parents=np.array([-1, 0, 1]),
        pivots=np.array([[0, 1.5, 0], [0, 1.6, 0], [0.03, 1.7, 0.08]]),
        joints=joints,
        weights=weights,
        roles={"neck": 0, "head": 1, "eye_left": 2},
    )
    verts = rng.normal([0, 1.65, 0], 0.1, size=(n, 3)).astype(np.float32)
    pose = HeadPose(yaw=25, pitch=-8, roll=4, neck_share=0.3, eye_yaw=10)
    mats = sk.matrices(sk.pose_rotations(pose))
    expect = np.array(
        [
            sum(w * (mats[j, :3, :3] @ v + mats[j, :3, 3]) for j, w in zip(js, ws, strict=True))
            if ws.sum() > 0
            else v
            for v, js, ws in zip(verts.astype(float), joints, weights.astype(float), strict=True)
        ]
    )
    np.testing.assert_allclose(skin(verts, sk, pose), expect, atol=2e-6)
    # the same rows shuffled: rows bound to one joint are no longer one run of indices
    order = rng.permutation(n)
    shuffled = Skeleton(
        names=sk.names, parents=sk.parents, pivots=sk.pivots, joints=joints[order],
        weights=weights[order], roles=sk.roles,
    )  # fmt: skip
    np.testing.assert_allclose(skin(verts[order], shuffled, pose), expect[order], atol=2e-6)


def _eyes_pivoting_behind(head, depth_m: float):
    """The default head with its eye joints moved ``depth_m`` behind the eyeballs' centres
    (a VRoid export's eyes turn about a point 73 mm behind the iris)."""
    sk = head.skeleton
    pivots = sk.pivots.copy()
    for role in ("eye_left", "eye_right"):
        pivots[sk.roles[role], 2] -= depth_m
    return head.replace(
        skeleton=type(sk)(sk.names, sk.parents, pivots, sk.joints, sk.weights, sk.roles)
    )


def test_gaze_map_keeps_the_iris_in_the_eye(tmp_path: Path) -> None:
    """Eye joints at the eyeball's centre turn by the planned gaze; joints far behind the
    eye give way to the avatar's eyeLook shapes, or - without usable shapes - are scaled to
    the safe turn; a VRM's lookAt range map is used as the file says; the audit judges the
    turn each avatar's largest planned gaze gets."""
    from facelab.stimuli.avatar.gaze import GAZE_RANGE_DEG, gaze_map, safe_eye_angle
    from facelab.stimuli.checks.avatar_checks import eye_rows

    def played(avatar) -> list[tuple[str, bool | None, float]]:
        return [(r.measure, r.passed, r.value) for r in eye_rows(avatar, severity="error")
                if r.measure.startswith("gaze_played")]  # fmt: skip

    head = default_head()
    assert gaze_map(head).mode == "joints" and gaze_map(head).joint_angles(20, -10) == (20, -10)
    assert [p for _, p, _ in played(head)] == [True, True]

    behind = _eyes_pivoting_behind(head, 0.06)
    safe = safe_eye_angle(behind, "eye_left")[0]
    assert safe < 12
    shapes = gaze_map(behind)
    assert shapes.mode == "shapes"
    assert shapes.shape_weights(12.5, 25) == {
        "eyeLookOutLeft": 0.5, "eyeLookInRight": 0.5, "eyeLookDownLeft": 1.0,
        "eyeLookDownRight": 1.0,
    }  # fmt: skip
    assert played(behind) == []  # shapes: no joint turn to judge

    no_shapes = behind.replace(
        targets={k: v for k, v in behind.targets.items() if not k.startswith("eyeLook")}
    )
    scaled = gaze_map(no_shapes)
    assert scaled.mode == "joints"
    yaw, _ = scaled.joint_angles(GAZE_RANGE_DEG, 0)
    assert yaw == pytest.approx(safe, abs=0.01)
    assert [p for _, p, _ in played(no_shapes)] == [True, True]

    vrm = load(write_sample(tmp_path / "a.vrm", kind="vrm1"))
    look = gaze_map(vrm)
    assert look.source == "the file's VRM lookAt, bone type"
    assert look.joint_angles(45, -90) == pytest.approx((5.0, -10.0))
    vrm0 = load(write_sample(tmp_path / "b.vrm", kind="vrm0", vroid=True))
    assert gaze_map(vrm0).joint_angles(-90, 9) == pytest.approx((-10.0, 1.0))


def test_the_behaviour_layer_shows_gaze_through_the_gaze_map() -> None:
    """A planned gaze on eyes that pivot far behind becomes eyeLook weights, not a joint
    turn; on the default head it stays a joint turn of the planned angle."""
    from facelab.stimuli.behaviour.realise import BehaviourFrames, apply_to_weights, avatar_traits

    head = default_head()
    rot = np.zeros((2, 8))
    rot[1, 6] = 10.0  # eye_yaw 10 deg to the avatar's left on the second frame
    frames = BehaviourFrames(np.array([0.0, 0.04]), {}, rot)
    speech = np.zeros((2, len(head.target_names)), np.float32)
    _, poses, report = apply_to_weights(frames, speech, **avatar_traits(head))
    assert poses[1].eye_yaw == 10.0 and "joints" in report["gaze"]
    behind = _eyes_pivoting_behind(head, 0.06)
    w, poses, report = apply_to_weights(frames, speech, **avatar_traits(behind))
    names = behind.target_names
    assert poses[1] is None and "shapes" in report["gaze"]
    assert w[1, names.index("eyeLookOutLeft")] == pytest.approx(0.4)
    assert w[1, names.index("eyeLookInRight")] == pytest.approx(0.4)
    assert w[0].sum() == 0
