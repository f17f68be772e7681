"""Live 3D and VR presentation (presentation.display: live3d | webxr): the avatar and camera
the server hands the browser, the checks before serving, and - in real headless Chromium with
SwiftShader WebGL - the fidelity of live frames to the offline clip, a whole kato2021 session
in VR with an emulated headset (IWER) whose head turns during clips, a tab closed mid-trial in
VR, and the fallback to live3d where a browser has no headset. Frame timing measured headless
is not a device figure: these tests check that it is logged, never how fast it is."""

from __future__ import annotations

import base64
import io
import json
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from sqlalchemy import select
from sqlalchemy.orm import Session

from facelab.errors import ProtocolError, SessionError
from facelab.experiment.cli import main
from facelab.experiment.online.browser import (
    RECENTRE_YAW_DEG,
    SimulatedBrowser,
    chromium,
    simulated_token,
)
from facelab.experiment.online.db import Action, Event, Participant, PlaybackRecord, Response
from facelab.experiment.online.export import export_sessions
from facelab.experiment.online.serve import BackgroundServer, prepare_server
from facelab.formats import read_manifest
from facelab.protocol import Protocol, load_protocol
from facelab.stimuli.avatar import default_head, load
from facelab.stimuli.avatar.gltf import live_glb
from facelab.stimuli.avatar.samples import write_sample
from facelab.stimuli.render.scene import camera_json, framing, settings_for
from tests.protocol_edits import kato_short
from tests.shared_renders import rendered_clips
from tests.test_word_matrix import SHORT as MATRIX_SHORT

ROOT = Path(__file__).resolve().parents[1]
KATO = ROOT / "protocols" / "kato2021.yaml"


def _short(text: str) -> str:
    """kato2021 with one set per block and short sentences (the online tests' study)."""
    return kato_short(text)


def _load(text: str, folder: Path, name: str = "p.yaml") -> Protocol:
    (folder / name).write_text(text, encoding="utf-8")
    return load_protocol(folder / name)


def _with_display(text: str, block: str) -> str:
    out = text.replace("presentation:\n", "presentation:\n" + block, 1)
    assert out != text
    return out


# --------------------------------------------------------------------------- fast: pure parts


def test_the_display_keys_are_checked(tmp_path: Path) -> None:
    text = KATO.read_text(encoding="utf-8")
    assert load_protocol(KATO).presentation.display == "video"  # the default
    live = _load(_with_display(text, "  display: webxr\n  vr:\n    fallback: live3d\n"), tmp_path)
    assert live.presentation.display == "webxr" and live.presentation.vr.fallback == "live3d"
    assert live.presentation.vr.avatar_distance_m == 1.0
    for bad, words in (
        ("  display: hologram\n", "display"),
        ("  vr:\n    avatar_distance_m: 0\n", "avatar_distance_m"),
        ("  vr:\n    fallback: video\n", "fallback"),
    ):
        with pytest.raises(ProtocolError, match=words):
            _load(_with_display(text, bad), tmp_path)


def test_a_side_by_side_comparison_needs_the_video_display(tmp_path: Path) -> None:
    shutil.copy(ROOT / "protocols" / "horii_friendly_model.json", tmp_path)
    side = (ROOT / "protocols" / "horii_impression_side.yaml").read_text(encoding="utf-8")
    _load(side, tmp_path)  # as shipped: video
    with pytest.raises(ProtocolError, match=r"side_by_side.*display: video"):
        _load(_with_display(side, "  display: live3d\n"), tmp_path)


def test_the_live_avatar_is_the_offline_one_with_its_roles_and_linear_colours(
    tmp_path: Path,
) -> None:
    head = default_head()
    path = tmp_path / "live.glb"
    path.write_bytes(live_glb(head))
    back = load(path)
    assert set(back.target_names) == set(head.target_names)  # the tracks' channels
    assert np.allclose(back.targets["jawOpen"], head.targets["jawOpen"], atol=1e-6)
    assert np.allclose(back.neutral, head.neutral, atol=1e-6)
    assert np.allclose(back.colors, np.asarray(head.colors) ** 2, atol=1e-6)  # linear light
    raw = path.read_bytes()
    doc = json.loads(raw[20 : 20 + int.from_bytes(raw[12:16], "little")])
    roles = doc["meshes"][0]["extras"]["facelab"]["roles"]
    assert head.skeleton is not None
    assert roles == {r: head.skeleton.names[j] for r, j in head.skeleton.roles.items()}
    assert {"head", "neck"} <= set(roles)


def test_the_live_camera_is_the_offline_framing() -> None:
    protocol = load_protocol(KATO)
    head = default_head()
    settings = settings_for(protocol)
    cam = camera_json(head, settings)
    centre, distance = framing(head, settings)
    assert cam["target"] == pytest.approx(centre.tolist(), abs=1e-6)
    assert cam["eye"][2] - cam["target"][2] == pytest.approx(distance, abs=1e-6)
    assert (cam["width"], cam["height"], cam["fov_deg"]) == (1280, 720, 30.0)


def test_vr_anchors_at_the_avatars_eyes_and_voices_at_its_mouth() -> None:
    """The points a VR view places and hears: between the eye joints (the default head's
    eyes), the middle of the inner lips; an avatar without eyes falls back to the aim point."""
    head = default_head()
    cam = camera_json(head, settings_for(load_protocol(KATO)))
    sk = head.skeleton
    assert sk is not None
    eyes = 0.5 * (sk.pivots[sk.roles["eye_left"]] + sk.pivots[sk.roles["eye_right"]])
    assert cam["eyes"] == pytest.approx(eyes.tolist(), abs=1e-6)
    assert cam["eyes"][1] - cam["target"][1] > 0.02  # the face centre is below the eyes
    lips = head.neutral[[head.landmarks[k] for k in ("upper_lip", "lower_lip")]]
    assert cam["mouth"][1] == pytest.approx(float(lips[:, 1].mean()), abs=0.005)
    assert cam["mouth"][1] < cam["eyes"][1] - 0.05
    blind = replace(head, skeleton=None, landmarks={
        k: v for k, v in head.landmarks.items() if "lid" not in k})  # fmt: skip
    assert camera_json(blind, settings_for(load_protocol(KATO)))["eyes"] is None


def test_vr_texts_name_no_keys_and_validate_says_which_do(tmp_path: Path, capsys) -> None:
    """kato2021 in VR: its instructions speak of clicking and its break of the space key;
    validate says so, the break gets facelab's VR wording, and the protocol's own VR wording
    replaces the instructions (sent beside the 2D text: the page picks it in the headset)."""
    from facelab.experiment.timeline import BrowserContext, TextScreen, vr_texts

    text = KATO.read_text(encoding="utf-8")
    path = tmp_path / "vr.yaml"
    path.write_text(_with_display(text, "  display: webxr\n"), encoding="utf-8")
    assert main(["validate", str(path)]) == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if "speaks of" in line]
    assert len(notes) == 2
    assert "presentation.instructions" in notes[0] and "クリック" in notes[0]
    assert "presentation.break_text" in notes[1] and "スペース" in notes[1]
    protocol = load_protocol(path)
    texts = vr_texts(protocol)
    assert set(texts) == {"break", "resume"} and "スペース" not in texts["break"] + texts["resume"]
    own = "コントローラーで線を指して回答してください。"
    vr_block = f"  display: webxr\n  vr:\n    instructions: {{ja: {own}, en: Point at the line.}}\n"
    path.write_text(_with_display(text, vr_block), encoding="utf-8")
    assert main(["validate", str(path)]) == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if "speaks of" in line]
    assert len(notes) == 1 and "break_text" in notes[0]
    texts = vr_texts(load_protocol(path))
    assert texts["instructions"] == own
    ctx = BrowserContext(lang="ja", clip_json=dict, vr_texts=texts)
    shown = TextScreen(role="instructions", text="2D").browser(ctx)
    assert shown == {"kind": "text", "role": "instructions", "text": "2D", "vr_text": own}
    assert TextScreen(role="practice", text="2D").browser(ctx)["vr_text"] == ""  # the 2D one
    assert vr_texts(load_protocol(KATO)) == {}  # the video display has no VR texts
    # a break text that names no key (a monkey is not a key) is the protocol's own in VR too
    calm = text.replace("準備ができたらスペースキーを押してください。", "猿（monkey）を見ます。")
    calm = calm.replace("Press space when you are ready.", "Look at a monkey.")
    path.write_text(_with_display(calm, vr_block), encoding="utf-8")
    assert "break" not in vr_texts(load_protocol(path))


def test_the_emulated_headsets_options_need_simulated_participants_in_vr(
    tmp_path: Path, capsys
) -> None:
    """--simulate-headset-off and --simulate-vr-input gaze say what they need (simulated
    participants, a webxr protocol) instead of being ignored; nothing is written."""
    results = tmp_path / "results"
    base = ["serve", str(KATO), "--results", str(results)]
    for asked in ("gaze", "controller"):  # either, said explicitly
        assert main([*base, "--simulate-vr-input", asked]) == 2
        err = capsys.readouterr().err
        assert "--simulate-vr-input: only with --simulate-participants N" in err
    assert main([*base, "--simulate-participants", "1", "--simulate-headset-off", "2"]) == 2
    err = capsys.readouterr().err
    assert "--simulate-headset-off: the simulated participants wear a headset only when" in err
    assert "presentation.display is webxr" in err and "has video" in err
    # the simulated browsers' window: only for them, and a size
    assert main([*base, "--simulate-window", "640x400"]) == 2
    assert "--simulate-window: only with --simulate-participants N" in capsys.readouterr().err
    for bad, said in (("big", "expected WIDTHxHEIGHT"), ("", "expected WIDTHxHEIGHT"),
                      ("641x400", "width and height must be even and >= 64"),
                      ("20000x400", "expected at most 7680x4320")):  # fmt: skip
        assert main([*base, "--simulate-participants", "1", "--simulate-window", bad]) == 2
        err = capsys.readouterr().err
        assert f"--simulate-window {bad!r}" in err and said in err, err
        assert "Traceback" not in err
    assert not results.exists()


# --------------------------------------------------------------------------- Chromium

slow = pytest.mark.slow
#: the emulated headset's browser window: both eyes are drawn into it on the CPU, so a quarter
#: of the default 1280x800 brings XR frames sooner (a session in ~60 % of the time); panel
#: layouts, rays and poses do not depend on it
VR_WINDOW = (640, 400)


@pytest.fixture(scope="module")
def study(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The short kato2021 rendered once (320x180, 15 fps), with live3d and webxr variants."""
    root = tmp_path_factory.mktemp("live3d")
    text = _short(KATO.read_text(encoding="utf-8"))
    (root / "live.yaml").write_text(_with_display(text, "  display: live3d\n"), "utf-8")
    (root / "vr.yaml").write_text(
        _with_display(text, "  display: webxr\n  vr:\n    avatar_distance_m: 1.2\n"), "utf-8"
    )
    (root / "vr_fallback.yaml").write_text(
        _with_display(text, "  display: webxr\n  vr:\n    fallback: live3d\n"), "utf-8"
    )
    rendered_clips(tmp_path_factory, text=text, into=root, name="video.yaml", size="320x180",
                   fps="15")  # fmt: skip
    # a textured, skinned avatar file (Ready Player Me's layout: ARKit + visemes)
    write_sample(root / "rpm.glb", kind="rpm")
    rpm = _with_display(text, "  display: live3d\n")
    rpm = rpm.replace("  avatar: default", "  avatar: rpm.glb")
    # the sample is a stand-in: one shape serves all nine consonant visemes, and its face is
    # not one a face detector takes for a face - the checks say so, the test accepts it
    accept = ["--accept-check", "avatar_audit", "--accept-check", "face_visible"]
    rendered_clips(tmp_path_factory, text=rpm, into=root, name="rpm.yaml", size="320x180",
                   fps="15", files={"rpm.glb": (root / "rpm.glb").read_bytes()}, extra=accept,
                   clips="rpm_clips")  # fmt: skip
    # the same in VR: the sessions that test a VR flow (a resume, a stop from the panel) run
    # with this light avatar (7k triangles: the default head's 52k with 67 morph targets took
    # ~360 ms a frame in software, the emulated headset's frames came 3 a second)
    (root / "vr_rpm.yaml").write_text(
        _with_display(text, "  display: webxr\n  vr:\n    avatar_distance_m: 1.2\n").replace(
            "  avatar: default", "  avatar: rpm.glb"), "utf-8")  # fmt: skip
    assert "  avatar: rpm.glb" in (root / "vr_rpm.yaml").read_text("utf-8")
    return root


def _server(study: Path, name: str, db: Path, clips: str = "clips"):
    protocol = load_protocol(study / name)
    server, _ = prepare_server(
        protocol, protocol_path=study / name, clips_dir=study / clips,
        db_url=f"sqlite:///{db}", results=db.parent, admin_secret="s" * 20,
    )  # fmt: skip
    return server


def _rows(server) -> list[dict]:
    with Session(server.engine) as db:
        return [r.row for r in db.scalars(select(Response))]


def _clicked_equals_stored(server) -> int:
    """Every planned response stored once and equal to the click; returns how many."""
    rows = _rows(server)
    keys = [(r["participant"], r["trial_index"], r["item"]) for r in rows]
    assert len(keys) == len(set(keys))
    with Session(server.engine) as db:
        pk = {p.pk: p.participant for p in db.scalars(select(Participant))}
        clicks = {
            (pk[a.participant_pk], a.record["trial_index"], a.record["item"]): a.record["value"]
            for a in db.scalars(select(Action))
        }
    assert set(keys) == set(clicks)
    for r in rows:  # a ray hits a texel of the panel: within half a scale point
        assert abs(r["rating"] - clicks[(r["participant"], r["trial_index"], r["item"])]) < 0.5
    return len(rows)


@slow
def test_serving_a_live_display_needs_tracks_of_the_same_avatar(
    study: Path, tmp_path: Path
) -> None:
    clips = tmp_path / "clips"
    shutil.copytree(study / "clips", clips)
    rows = read_manifest(clips)
    (clips / rows[0]["track_file"]).write_bytes(b"FLTRACK1 changed")
    protocol = load_protocol(study / "live.yaml")
    with pytest.raises(SessionError, match=r"animation track of clip .* changed"):
        prepare_server(
            protocol, protocol_path=study / "live.yaml", clips_dir=clips,
            db_url=f"sqlite:///{tmp_path / 'db.sqlite'}", results=tmp_path,
            admin_secret="s" * 20,
        )  # fmt: skip
    # the video display does not need them
    prepare_server(
        load_protocol(study / "video.yaml"), protocol_path=study / "video.yaml",
        clips_dir=clips, db_url=f"sqlite:///{tmp_path / 'db2.sqlite'}", results=tmp_path,
        admin_secret="s" * 20,
    )  # fmt: skip


def _mouth_darkness(img: np.ndarray, box: tuple[int, int, int, int]) -> float:
    """How dark the mouth box is (255 - its mean grey level): rises as the mouth opens onto
    its dark inside (a count of dark pixels is too coarse at 320x180)."""
    x0, y0, x1, y1 = box
    return float(255.0 - img[y0:y1, x0:x1].astype(float).mean())


def _open_stage(server, bg, k: int):
    """Headless Chromium on the session page of a simulated participant ``k``, once the
    live view (window.FacelabLive) is up."""
    d = chromium()
    _, token = server.join(recruitment=f"still-{k}", source="simulated", simulated=True,
                           token=simulated_token(server, k))  # fmt: skip
    d.get(f"{bg.url}/run#t={token}")
    for _ in range(300):
        if d.execute_script("return !!window.FacelabLive"):
            break
        time.sleep(0.1)
    return d


def _still(d, server, row: dict[str, str], k: int) -> np.ndarray:
    """Frame ``k`` of a clip (its manifest ``row``) as the page draws it from the track (the
    served copies of the clip and track)."""
    copy = server.served.main[(row["stimulus_set"], row["stimulus"], row["condition"])]
    url = d.execute_async_script(
        "const [clip, track, k, done] = arguments;"
        "FacelabLive.clip({clip, track}).then("
        "(c) => done(FacelabLive.still(c.track, k)), (e) => done('ERR ' + e));",
        copy.clip, copy.track, k,
    )  # fmt: skip
    assert url.startswith("data:image/png"), url
    png = base64.b64decode(url.split(",", 1)[1])
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


@slow
def test_live_frames_match_the_offline_clip_at_the_same_instants(
    study: Path, tmp_path: Path
) -> None:
    """Every 3rd frame of every clip drawn by the browser from the track (at the offline size)
    against the offline mp4's frame: mean absolute difference over the face, and the mouth's
    opening (dark pixels inside the lips) frame by frame."""
    from facelab.stimuli.render.clip import decode_frames
    from facelab.stimuli.render.renderer import Renderer, RenderSettings

    server = _server(study, "live.yaml", tmp_path / "db.sqlite")
    server.config.live.camera.update(width=320, height=180)  # the clips' size
    head = default_head()
    with Renderer(head, RenderSettings(width=320, height=180)) as r:
        lm = head.landmarks
        pts = r.project(head.neutral[[lm["mouth_left"], lm["mouth_right"], lm["upper_lip"],
                                      lm["lower_lip"]]])  # fmt: skip
    xl, xr = int(pts[:, 0].min()), int(pts[:, 0].max())  # mouth corners (viewer's left, right)
    yu, yl = int(pts[2:, 1].min()), int(pts[2:, 1].max())  # the lips at rest
    mouth = (xl - 2, yu - 4, xr + 3, yl + 12)
    face = (xl - 40, yu - 70, xr + 40, yl + 40)
    diffs, live_open, off_open = [], [], []
    with BackgroundServer(server) as bg:
        d = _open_stage(server, bg, 99)
        try:
            for row in read_manifest(study / "clips"):
                frames = decode_frames(study / "clips" / row["path"], width=320, height=180)
                for k in range(0, len(frames), 3):
                    live = _still(d, server, row, k)
                    x0, y0, x1, y1 = face
                    diffs.append(
                        np.abs(live[y0:y1, x0:x1].astype(int) - frames[k][y0:y1, x0:x1]).mean()
                    )
                    live_open.append(_mouth_darkness(live, mouth))
                    off_open.append(_mouth_darkness(frames[k], mouth))
                    if k == 12:
                        Image.fromarray(np.concatenate([frames[k], live], axis=1)).save(
                            tmp_path / f"{row['condition']}_{k}.png"
                        )
            pose_mad = _head_poses_match(d, tmp_path)
        finally:
            d.quit()
    assert max(pose_mad) < 4.0, pose_mad  # out of 255, whole frame
    diffs_a, lo, oo = np.array(diffs), np.array(live_open), np.array(off_open)
    figures = {
        "frames": len(diffs_a),
        "face_mad_mean": round(float(diffs_a.mean()), 2),
        "face_mad_max": round(float(diffs_a.max()), 2),
        "mouth_open_r": round(float(np.corrcoef(lo, oo)[0, 1]), 3),
        # the live mouth box is darker by about the same on every frame (its lower face is
        # shaded a little darker): that offset, the frame-by-frame difference about it, and
        # how far the live mouth opens per unit of the offline one
        "mouth_open_offset": round(float(np.mean(lo - oo)), 2),
        "mouth_open_mad": round(float(np.abs(lo - oo - np.mean(lo - oo)).mean()), 2),
        "mouth_open_gain": round(float(np.polyfit(oo, lo, 1)[0]), 3),
        "mouth_open_range": round(float(np.ptp(oo)), 2),
    }
    print("fidelity", json.dumps(figures))
    assert figures["face_mad_max"] < 6.0, figures  # out of 255, over the face
    assert np.ptp(oo) > 10  # the mouth opens and closes in these clips
    assert figures["mouth_open_r"] > 0.9, figures  # the live mouth opens when the offline one does
    assert 0.75 < figures["mouth_open_gain"] < 1.33, figures  # and as far
    assert figures["mouth_open_mad"] < 0.2 * np.ptp(oo), figures  # frame by frame
    assert abs(figures["mouth_open_offset"]) < 6.0, figures  # shading: as the face's MAD


@slow
def test_a_textured_skinned_avatar_file_looks_the_same_live(study: Path, tmp_path: Path) -> None:
    """The protocol's own avatar file (textured, skinned: the sample in Ready Player Me's
    layout) drawn live at frames of every clip against the offline clip."""
    from facelab.stimuli.render.clip import decode_frames

    protocol = load_protocol(study / "rpm.yaml")
    server, _ = prepare_server(
        protocol, protocol_path=study / "rpm.yaml", clips_dir=study / "rpm_clips",
        db_url=f"sqlite:///{tmp_path / 'db.sqlite'}", results=tmp_path, admin_secret="s" * 20,
    )  # fmt: skip
    server.config.live.camera.update(width=320, height=180)
    mads = []
    with BackgroundServer(server) as bg:
        d = _open_stage(server, bg, 98)
        try:
            for row in read_manifest(study / "rpm_clips"):
                frames = decode_frames(study / "rpm_clips" / row["path"], width=320, height=180)
                for k in (0, len(frames) // 2):
                    live = _still(d, server, row, k)
                    mads.append(float(np.abs(live.astype(int) - frames[k]).mean()))
        finally:
            d.quit()
    print("textured avatar MAD", [round(m, 2) for m in mads])
    # an untextured (white) head would differ by ~14/255 over the frame: the texture is drawn
    assert len(mads) == 12 and max(mads) < 3.0, mads


def _head_poses_match(d, folder: Path) -> list[float]:
    """A track of turned heads (yaw, pitch, roll, eyes, neck share) drawn by the page and by
    the offline renderer: mean absolute difference per pose (the rig's conventions agree)."""
    from facelab.formats import encode_track
    from facelab.stimuli.avatar.rig import HeadPose
    from facelab.stimuli.render.renderer import Renderer

    head = default_head()
    poses = np.array(
        [[0, 0, 0, 0, 0, 0.4], [-20, 0, 0, 0, 0, 0.4], [12, 8, 0, 10, 0, 0.4],
         [5, -6, 7, 0, -8, 0.3]], np.float32,
    )  # fmt: skip
    weights = np.array([[0.0], [0.3], [0.6], [0.1]], np.float32)
    data = encode_track(
        clip_id="poses", fps=30, blendshapes=["jawOpen"], weights=weights, poses=poses,
        sample_rate=24000, speech_start_s=0.0, avatar_sha256=head.content_hash(),
    )  # fmt: skip
    settings = replace(settings_for(load_protocol(KATO)), width=320, height=180, msaa=1)
    out = []
    with Renderer(head, settings) as r:
        for k, pose in enumerate(poses):
            offline = r.frame(
                head.weight_vector({"jawOpen": float(weights[k, 0])}),
                pose=HeadPose(*map(float, pose)),  # yaw, pitch, roll, eye yaw/pitch, share
            )
            url = d.execute_script(
                "const b = Uint8Array.from(atob(arguments[0]), (c) => c.charCodeAt(0));"
                "return FacelabLive.still(FacelabTrack.parse(b.buffer), arguments[1]);",
                base64.b64encode(data).decode(), k,
            )  # fmt: skip
            live = np.asarray(
                Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1]))).convert("RGB")
            )
            out.append(float(np.abs(live.astype(int) - offline).mean()))
            Image.fromarray(np.concatenate([offline, live], axis=1)).save(folder / f"pose{k}.png")
    print("poses", [round(x, 2) for x in out])
    return out


def _every_screen_is_a_whole_vr_panel(protocol_file: Path, shots: Path) -> None:
    """Each VR screen of the session was shot with its panel's layout: the recentre step, the
    instructions, the practice notice, the ratings and the end (take off the headset); every
    text on a panel is drawn whole (its lines join to the text) and inside the panel - the
    VAS end labels too, however long."""
    protocol = load_protocol(protocol_file)
    layouts = {
        p.name.removesuffix(".panel.json"): json.loads(p.read_text("utf-8"))
        for p in shots.glob("*.panel.json")
    }
    rated = {f"vr-vas-{item.id}" for item in protocol.items}  # items_layout: sequential
    assert {"vr-recentre", "vr-text-instructions", "vr-text-practice", "vr-end"} | rated <= set(
        layouts
    ), sorted(layouts)
    for name, lay in layouts.items():
        assert not lay["overflow"], name
        for block in lay["blocks"]:
            drawn = "".join(block["lines"]).replace(" ", "")
            assert drawn == "".join(block["source"].split()), (name, block)
    for item in protocol.items:  # the question and both end labels, whole
        sources = {b["source"] for b in layouts[f"vr-vas-{item.id}"]["blocks"]}
        assert {item.question["ja"], item.left_anchor["ja"], item.right_anchor["ja"]} <= sources
    instructions = {b["source"] for b in layouts["vr-text-instructions"]["blocks"]}
    assert protocol.presentation.instructions["ja"] in instructions
    end = {b["source"] for b in layouts["vr-end"]["blocks"]}
    assert "ヘッドセットを外して、パソコンの画面をご覧ください。" in end


_HEADSET_OFF_PAGE_JS = """
const done = arguments[0];
// a loaded machine: the page draws a frame only every 1.5 s (timers still run between)
window.requestAnimationFrame = (cb) => setTimeout(() => cb(performance.now()), 1500);
(async () => {
  const session = await navigator.xr.requestSession('immersive-vr');
  const gl = document.getElementById('c').getContext('webgl', {xrCompatible: true});
  session.updateRenderState({ baseLayer: new XRWebGLLayer(session, gl) });
  const seen = [];
  session.addEventListener('visibilitychange',
    () => seen.push([session.visibilityState, performance.now()]));
  window.FacelabLive = { playing: { trial_index: 3 }, session, onFrame: null };
  const t0 = performance.now();
  const frame = () => {
    if (performance.now() - t0 > 20000 || seen.length >= 2) { done(seen); return; }
    session.requestAnimationFrame(frame);
  };
  session.requestAnimationFrame(frame);
})().catch((e) => done(e.message));
"""


@pytest.mark.slow
def test_the_emulated_headset_comes_back_on_after_it_is_taken_off_on_a_slow_page(
    tmp_path: Path,
) -> None:
    """--simulate-headset-off: the emulated participant takes the headset off during the
    trial's clip and puts it on again a second after the page saw it off, with XR frames
    seconds apart (CI at f9f983b: "visible" asked before "hidden" took effect was dropped, the
    headset stayed off and the session never finished)."""
    import functools
    import http.server
    import threading

    from facelab.experiment.online.browser import emulator_js

    (tmp_path / "index.html").write_text("<canvas id=c></canvas>", encoding="utf-8")
    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args: object) -> None:  # no request lines in the test output
            pass

    handler = functools.partial(Quiet, directory=str(tmp_path))
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    d = chromium(size=VR_WINDOW)
    try:
        d.execute_cdp_cmd(
            "Page.addScriptToEvaluateOnNewDocument", {"source": emulator_js(headset_off_at=3)}
        )
        d.get(f"http://127.0.0.1:{srv.server_address[1]}/index.html")
        d.set_script_timeout(60)
        seen = d.execute_async_script(_HEADSET_OFF_PAGE_JS)
    finally:
        d.quit()
        srv.shutdown()
        srv.server_close()
    assert isinstance(seen, list), seen  # else the page's error
    assert [s for s, _ in seen] == ["hidden", "visible"], seen
    assert seen[1][1] - seen[0][1] >= 1000  # off for a second at least, as the page saw it


@slow
def test_a_kato2021_session_in_vr_with_a_head_turn_stores_every_rating_once(
    study: Path, tmp_path: Path
) -> None:
    """facelab serve --simulate-participants drives the webxr display with an emulated
    headset; the scripted head turn is in the logged poses; every rating once; exported."""
    db = tmp_path / "vr.sqlite"
    shots = tmp_path / "shots"
    args = ["serve", str(study / "vr.yaml"), "--clips", str(study / "clips"),
            "--db", f"sqlite:///{db}", "--results", str(tmp_path), "--port", "0",
            "--simulate-participants", "1", "--screenshots", str(shots),
            "--simulate-headset-off", "3", "--simulate-window", "640x400"]  # fmt: skip
    assert main(args) == 0
    assert {"enter_vr.png", "vr-vas-naturalness.png", "complete.png", "vr-clip.png"} <= {
        p.name for p in shots.glob("*.png")
    }
    # the talking avatar as the headset showed it, both eyes: the page's own still of a clip
    # faded in (a page screenshot caught the fade from black), the face lit in each eye
    still = np.asarray(Image.open(shots / "vr-clip.png").convert("L"), dtype=float)
    print("vr-clip still: mean", still.mean().round(1), "eyes", [
        half.mean().round(1) for half in np.array_split(still, 2, axis=1)])  # fmt: skip
    assert all(half.mean() > 20 for half in np.array_split(still, 2, axis=1))
    server = _server(study, "vr.yaml", db)
    assert _clicked_equals_stored(server) == 18
    with Session(server.engine) as s:
        records = [r.record for r in s.scalars(select(PlaybackRecord))]
        shown = [e.detail for e in s.scalars(select(Event).where(Event.kind == "display"))]
        recentred = [e.detail for e in s.scalars(select(Event).where(Event.kind == "recentre"))]
        headset = [e.detail for e in s.scalars(select(Event).where(Event.kind == "headset"))]
    # the headset taken off for a second during trial 3's clip: logged off and on again; the
    # clip stopped and played again from the start, its record of the whole second playing
    assert [(e["state"], e["during"], e["trial_index"]) for e in headset] == [
        ("hidden", "clip", 3), ("visible", "screen", None)]  # fmt: skip
    stopped = {r["trial_index"]: r["interruptions"] for r in records}
    assert stopped[3] == 1 and all(v == 0 for k, v in stopped.items() if k != 3), stopped
    assert shown and all(e["ran"] == "webxr" for e in shown)
    assert all(e["input"] == "controller" and e["reference_space"] for e in shown)
    _every_screen_is_a_whole_vr_panel(study / "vr.yaml", shots)
    # the recentre step: the emulated participant sat turned 15 deg to the left; the avatar's
    # eyes were placed 1.2 m (vr.yaml) along that direction, at their eye height
    start = [e for e in recentred if e["why"] == "start"]
    assert len(start) == 1 and start[0]["yaw_deg"] == pytest.approx(RECENTRE_YAW_DEG, abs=0.5)
    ahead = np.array(start[0]["avatar_eyes_m"]) - np.array(start[0]["viewer_m"])
    assert np.hypot(ahead[0], ahead[2]) == pytest.approx(1.2, abs=0.005)
    assert np.degrees(np.arctan2(-ahead[0], -ahead[2])) == pytest.approx(RECENTRE_YAW_DEG, abs=0.5)
    assert ahead[1] == pytest.approx(0.0, abs=0.002)
    for rec in records:  # the voice from the avatar's mouth, a little below its eyes
        assert rec["spatial_audio"] is True
        mouth = np.array(rec["audio_source_m"])
        viewer = np.array(rec["viewer_poses"][0][1:4])
        assert np.linalg.norm(mouth - viewer) == pytest.approx(1.2, abs=0.1)
        assert mouth[1] < start[0]["avatar_eyes_m"][1] - 0.03
    assert len(records) == 9
    for rec in records:
        assert rec["display"] == "webxr" and rec["frames_expected"] > 0
        assert rec["presented_frames"] == len(rec["audio_times"]) > 0
        assert rec["audio_times"] == sorted(rec["audio_times"])  # the audio clock runs on
        assert rec["viewer_poses"] and rec["head_yaw_range_deg"] is not None
        assert all(abs(pose[4]) <= 20.5 for pose in rec["viewer_poses"])  # the script's bound
        assert rec["avatar_distance_m"] == pytest.approx(1.2, abs=0.05)
        # both emulated controllers at every logged frame, within reach of the head
        heads = {pose[0]: np.array(pose[1:4]) for pose in rec["viewer_poses"]}
        hands = rec["controller_poses"]
        assert sorted((h[0], h[1]) for h in hands) == sorted(
            (t, hand) for t in heads for hand in (0.0, 1.0)
        ), (hands, sorted(heads))
        assert all(np.linalg.norm(np.array(h[2:5]) - heads[h[0]]) < 1.0 for h in hands)
        # within a frame of the sound wherever a frame fell inside the track (a loaded machine
        # may draw a short clip's only frames after its end: then there is nothing to measure)
        assert rec["av_offset_ms"] is None or abs(rec["av_offset_ms"]) < 1000 / 15
    # the scripted +-20 deg turn is in the logged poses: the emulated head moves in the XR
    # frame loop by at most an eighth of its cycle per frame, on from clip to clip, so however
    # sparse headless frames are (150-500 ms apart; two per short clip with the machine busy)
    # the poses of the session hold it
    # (how many clips get a frame inside their track depends on the load: 3 of 9 in a
    # fresh-clone CI run at 80e3480; the rule below needs one)
    assert any(rec["av_offset_ms"] is not None for rec in records)
    yaws = [pose[4] for rec in records for pose in rec["viewer_poses"]]
    print("yaw per logged frame, per clip:",
          [[round(pose[4], 1) for pose in rec["viewer_poses"]] for rec in records])  # fmt: skip
    assert max(yaws) - min(yaws) > 30, (min(yaws), max(yaws))
    # and it moves in six degrees of freedom: nods, tilts, leans
    every = np.array([pose for rec in records for pose in rec["viewer_poses"]])
    spread = np.ptp(every[:, 1:], axis=0)  # x, y, z (m), yaw, pitch, roll (deg)
    print("pose ranges x, y, z, yaw, pitch, roll:", spread.round(3).tolist())
    assert spread[4] > 5 and spread[5] > 2 and spread[2] > 0.01, spread
    # each clip's yaw range is that of the poses it logged (how many frames a clip gets - and
    # so how much of the turn it holds - depends on the machine's load: one frame per clip was
    # seen under the full suite, so no per-clip amount of turning is asserted)
    for rec in records:
        logged = [pose[4] for pose in rec["viewer_poses"]]
        assert rec["head_yaw_range_deg"] == pytest.approx(max(logged) - min(logged), abs=0.02)
    out = tmp_path / "results"
    export_sessions(server.engine, results=out)
    session = json.loads(next(out.rglob("*_session.json")).read_text("utf-8"))
    assert session["display"]["ran"] == "webxr"
    lines = next(out.rglob("*_playback.jsonl")).read_text("utf-8").splitlines()
    first = json.loads(lines[0])
    assert first["display"] == "webxr" and first["head_yaw_range_deg"] is not None
    # the poses at the record's top level, as the README documents them (not under browser)
    assert first["viewer_poses"] and "viewer_poses" not in first.get("browser", {})
    assert first["controller_poses"] and "controller_poses" not in first.get("browser", {})
    # the poses while each panel waited for an answer: head and both controllers per frame,
    # under the screen's trial, kind and item (a panel answered before the headless headset
    # drew a frame has none: frames come every 150-500 ms here)
    waited = [json.loads(x) for x in next(out.rglob("*_screen_poses.jsonl")).read_text(
        "utf-8").splitlines()]  # fmt: skip
    rated = [w for w in waited if w["screen"] == "vas" and w["trial_index"]]
    items = {item.id for item in load_protocol(study / "vr.yaml").items}
    assert rated and {w["item"] for w in rated} <= items
    assert len(rated) >= len(records), (len(rated), len(records))  # most of the 18 VAS screens
    assert {w["screen"] for w in waited} >= {"vas", "text"}
    for w in waited:
        times = [v[0] for v in w["viewer_poses"]]
        assert times == sorted(times) and w["shown"] <= times[0] + 1e-3
        assert sorted((c[0], c[1]) for c in w["controller_poses"]) == sorted(
            (t, hand) for t in times for hand in (0.0, 1.0))
    report = tmp_path / "report"  # the live measures as covariates and an exclusion rule
    # the rule at the median measured offset: it leaves out some trials, never all (how far
    # apart picture and sound are depends on how busy the machine is)
    offsets = sorted(abs(r["av_offset_ms"]) for r in records if r["av_offset_ms"] is not None)
    limit = str(offsets[len(offsets) // 2])
    code = main(["analyze", str(study / "vr.yaml"), str(out), "--out", str(report),
                 "--bootstrap", "0", "--max-av-offset-ms", limit])  # fmt: skip
    assert code == 0
    live = (report / "live_presentation.csv").read_text("utf-8")
    assert live.startswith("stimulus_set,condition,trials,display,median_abs_av_offset_ms")
    assert "webxr" in live and ",max_frame_age_ms,frames_frozen," in live
    assert "--max-av-offset-ms" in (report / "report.md").read_text("utf-8")
    # the frame measures: headless frames are sparse, so some frame stays on screen long
    assert "frame_age_max_ms" in (report / "ratings.csv").read_text("utf-8").splitlines()[0]
    # how the head moved while the panels waited: one row per screen with poses, the yaw
    # range that of its logged poses
    import pandas as pd

    moved = pd.read_csv(report / "vr_screen_poses.csv")
    assert len(moved) == sum(1 for w in waited if w["viewer_poses"])
    expected = sorted(round(np.ptp([v[4] for v in w["viewer_poses"]]), 2) for w in waited
                      if w["viewer_poses"])  # fmt: skip
    assert sorted(moved["head_yaw_range_deg"]) == pytest.approx(expected, abs=0.02)
    kinds = pd.read_csv(report / "vr_screen_poses_summary.csv")["screen"]
    assert {"vas", "text"} <= set(kinds)


@slow
def test_a_tab_closed_mid_trial_in_vr_resumes(study: Path, tmp_path: Path) -> None:
    """A session in VR (a textured, skinned avatar file; the headset's one view) closed after
    three answers and opened again resumes at the trial it left, the clip shown again."""
    server = _server(study, "vr_rpm.yaml", tmp_path / "db.sqlite", clips="rpm_clips")
    with BackgroundServer(server) as bg:
        driver = chromium(size=VR_WINDOW)
        try:
            first = SimulatedBrowser(server, bg.url, 1, stop_after=3, driver=driver,
                                     vr_stereo=False)  # fmt: skip
            assert first.run() == "stopped"
            time.sleep(1.0)
            driver.get("about:blank")
            assert len(_rows(server)) == 3
            again = SimulatedBrowser(server, bg.url, 1, driver=driver, vr_stereo=False)
            assert again.run() == "complete"
            assert "再開" in again.texts["resume"]
        finally:
            driver.quit()
    assert _clicked_equals_stored(server) == 18
    # after the resume (trials 2-9, two ratings each, one of trial 2 given before) each of
    # the 15 answers faded out when selected and each of the 8 clips at its end; every
    # screen and clip faded in
    fades = again.vr_fades
    assert fades is not None and fades["out"] >= 15 + 8 and fades["in"] >= fades["out"], fades
    with Session(server.engine) as s:
        resumed = [e.detail for e in s.scalars(select(Event).where(Event.kind == "resumed"))]
    assert resumed == [{"answered": 3, "first_trial": 2}]
    # the report says where the session ran and counts the clip shown again
    export_sessions(server.engine, results=tmp_path / "out")
    report = tmp_path / "report"
    code = main(["analyze", str(study / "vr_rpm.yaml"), str(tmp_path / "out"), "--out",
                 str(report), "--bootstrap", "0"])  # fmt: skip
    assert code == 0
    sessions = (report / "pilot_sessions.csv").read_text("utf-8").splitlines()
    assert sessions[0].endswith("mode,simulated,display") and sessions[1].endswith(
        "online,True,webxr"
    )
    quality = (report / "presentation_quality.csv").read_text("utf-8").splitlines()
    assert quality[0].endswith(",replays")
    assert sum(int(line.rsplit(",", 1)[1]) for line in quality[1:]) == 1  # trial 2, once
    assert "sessions: 1 online (webxr 1), all simulated" in (report / "report.md").read_text()


@slow
def test_a_participant_stops_from_the_vr_panel_with_the_headset_on(
    study: Path, tmp_path: Path
) -> None:
    """Every VR panel carries the page's Stop button: selected it asks on the panel (stop or
    continue); confirmed, VR ends and the page reloads as a stopped session; the answers
    given are kept, the stop logged at the screen it was selected on. The participant wears
    a gaze-only headset (no controllers: they look at a button or a place on the line and
    press the select button): the panels say so, the display logs it, and the head's ray is
    not logged as a controller."""
    server = _server(study, "vr_rpm.yaml", tmp_path / "db.sqlite", clips="rpm_clips")
    shots = tmp_path / "shots"
    with BackgroundServer(server) as bg:
        browser = SimulatedBrowser(
            server, bg.url, 1, withdraw_after=2, screenshots=shots, vr_input="gaze",
            window=VR_WINDOW, vr_stereo=False,
        )
        assert browser.run() == "withdrawn"
    assert browser.withdrew and browser.vr_fades["out"] >= 2, browser.vr_fades
    for name in ("vr-recentre", "vr-text-instructions", "vr-vas-naturalness"):
        drawn = json.loads((shots / f"{name}.panel.json").read_text("utf-8"))
        said = [line["text"] for line in drawn["lines"]]
        assert "選びたいものを見つめて、選択ボタンを押します。" in said, (name, said)
        assert not any("コントローラー" in t for t in said), (name, said)
    with Session(server.engine) as db:
        shown = [e.detail for e in db.scalars(select(Event).where(Event.kind == "display"))]
        records = [r.record for r in db.scalars(select(PlaybackRecord))]
    assert shown and all(e["input"] == "gaze" for e in shown)
    assert len(records) == 2 and all(r["viewer_poses"] for r in records)
    assert all(not r["controller_poses"] for r in records)
    asked = json.loads((shots / "vr-withdraw-ask.panel.json").read_text("utf-8"))
    drawn = {b["source"] for b in asked["blocks"]}
    assert "研究への参加を中止しますか？ここまでの回答は保存されます。" in drawn
    assert {"中止する", "続ける"} <= drawn and not asked["overflow"]
    assert _clicked_equals_stored(server) == 2
    with Session(server.engine) as db:
        stopped = [e.detail for e in db.scalars(select(Event).where(Event.kind == "withdrawn"))]
        person = db.scalars(select(Participant)).one()
    assert len(stopped) == 1 and stopped[0]["screen"] == "vas" and person.completed is None
    assert server.session_state(person)["withdrawn"]


@slow
def test_without_a_headset_webxr_falls_back_only_when_the_protocol_allows(
    study: Path, tmp_path: Path
) -> None:
    allowed = _server(study, "vr_fallback.yaml", tmp_path / "a.sqlite")
    with BackgroundServer(allowed) as bg:
        assert SimulatedBrowser(allowed, bg.url, 1, headset=False).run() == "complete"
    with Session(allowed.engine) as s:
        shown = [e.detail for e in s.scalars(select(Event).where(Event.kind == "display"))]
        records = [r.record for r in s.scalars(select(PlaybackRecord))]
    assert shown[0]["requested"] == "webxr" and shown[0]["ran"] == "live3d"
    assert {r["display"] for r in records} == {"live3d"}
    assert all(r["head_yaw_range_deg"] is None for r in records)  # no headset, no poses
    refused = _server(study, "vr.yaml", tmp_path / "b.sqlite")
    with (
        BackgroundServer(refused) as bg,
        pytest.raises(SessionError, match="VRヘッドセットが必要"),
    ):
        SimulatedBrowser(refused, bg.url, 1, headset=False).run(timeout_s=120)
    assert _rows(refused) == []


@slow
@pytest.mark.parametrize(
    ("name", "edits", "screen"),
    [
        ("gain_2afc", {r"    sets: 2": "    sets: 1",
                       r"presentations_per_condition: 5": "presentations_per_condition: 1"},
         "choice_2afc"),
        ("method_identify", {r"    sets: 4": "    sets: 1",
                             r"presentations_per_condition: 2": "presentations_per_condition: 1",
                             r"      - \{id: sentence.*\n": "",
                             r"\n  language: ja\n": "\n  language: ja\n  ssq: [before, after]\n"},
         "identify"),
        ("kato2021_srt_matrix", MATRIX_SHORT, "matrix"),
    ],
)  # fmt: skip
def test_forced_choice_and_identification_are_answered_in_vr(
    tmp_path: Path, name: str, edits: dict[str, str], screen: str
) -> None:
    from tests.task_protocols import short_task_protocol

    # the session's flow in VR, on the light sample avatar (a textured, skinned file) in a
    # headset with one view: the default head drawn twice a frame in software made these the
    # suite's slowest sessions (the kato2021 head-turn session keeps both)
    rpm = tmp_path / "rpm.glb"
    write_sample(rpm, kind="rpm")
    vr = {r"\npresentation:\n": "\npresentation:\n  display: webxr\n",
          r"\nrendering: \{(.*)\}\n": r"\nrendering: {\1, avatar: rpm.glb}\n"}  # fmt: skip
    # the sample is a stand-in (see study): a face the tracker does not take for one, so the
    # checks that read the face cannot pass on it
    accept = tuple(f"--accept-check={check}" for check in (
        "avatar_audit", "face_visible", "articulation", "modality"))  # fmt: skip
    path = short_task_protocol(name, tmp_path, {**edits, **vr},
                               files={"rpm.glb": rpm.read_bytes()}, extra=accept)  # fmt: skip
    assert "avatar: rpm.glb" in path.read_text(encoding="utf-8")
    protocol = load_protocol(path)
    assert protocol.presentation.display == "webxr"
    server, _ = prepare_server(
        protocol, protocol_path=path, clips_dir=tmp_path / "clips",
        db_url=f"sqlite:///{tmp_path / 'db.sqlite'}", results=tmp_path, admin_secret="s" * 20,
    )  # fmt: skip
    shots = tmp_path / "shots"
    with BackgroundServer(server) as bg:
        run = SimulatedBrowser(server, bg.url, 1, screenshots=shots, window=VR_WINDOW,
                               vr_stereo=False).run()  # fmt: skip
        assert run == "complete"
    rows = _rows(server)
    assert len(rows) == len(server.study.planned("P0001"))
    with Session(server.engine) as db:
        actions = [a.record for a in db.scalars(select(Action))]
        shown = {r.record["display"] for r in db.scalars(select(PlaybackRecord))}
    assert shown == {"webxr"}
    # the sickness questionnaire (identification only): before the study on the screen,
    # before the headset goes on (16 clicks), after it 16 panels of four buttons, each stored
    # as the button clicked or the ray selected
    sickness = [r for r in rows if r["screen"] == "ssq"]
    rows = [r for r in rows if r["screen"] != "ssq"]
    assert rows and {r["screen"] for r in rows} == {screen}
    chosen = {a["item"]: a["value"] for a in actions if a["item"].startswith("ssq_")}
    assert len(sickness) == (32 if screen == "identify" else 0) == len(chosen)
    assert {r["item"]: int(r["response"]) for r in sickness} == {k: int(v) for k, v in
                                                                chosen.items()}  # fmt: skip
    if sickness:
        # the first symptom before the study on the page (no panel); after it, its panel:
        # the question and the four answers drawn whole
        assert (shots / "ssq.png").exists() and not (shots / "ssq.panel.json").exists()
        lay = json.loads((shots / "vr-ssq.panel.json").read_text(encoding="utf-8"))
        assert not lay["overflow"]
        for block in lay["blocks"]:
            assert "".join(block["lines"]).replace(" ", "") == "".join(block["source"].split())
        sources = {b["source"] for b in lay["blocks"]}
        assert {"【全体的な不快感】いまのあなたの状態について、この症状はどのくらいありますか。",
                "なし", "少し", "中程度", "強い"} <= sources, sources  # fmt: skip
    clicked = {a["trial_index"]: a["value"] for a in actions if not a["item"].startswith("ssq_")}
    if screen == "matrix":  # the columns' 50 words drawn whole on one panel, none cut
        lay = json.loads((shots / "vr-matrix.panel.json").read_text(encoding="utf-8"))
        assert not lay["overflow"] and lay["height"] <= 1280
        drawn = {b["source"] for b in lay["blocks"]}
        assert {w for c in protocol.tasks[0].columns for w in c} <= drawn
    for r in rows:  # the option the ray selected is the one stored
        if screen in ("identify", "matrix"):
            assert r["response"] == clicked[r["trial_index"]]
        else:
            assert (r["response"] == r["condition"]) == (clicked[r["trial_index"]] == r["position"])
