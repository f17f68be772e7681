"""Animation tracks (facelab.formats): the exact per-frame values a clip is drawn with, read
the same way by Python and by the browser's reader (static/track.js under Node)."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from facelab.errors import FormatError
from facelab.formats import POSE_CHANNELS, decode_track, encode_track, read_track

ROOT = Path(__file__).resolve().parents[1]
TRACK_JS = ROOT / "experiment" / "online" / "web" / "static" / "track.js"


def _track(rng: np.random.Generator, *, poses: bool) -> tuple[bytes, np.ndarray, np.ndarray]:
    w = rng.random((17, 3)).astype(np.float32)
    p = (rng.normal(size=(17, 6)) * 10).astype(np.float32) if poses else None
    data = encode_track(
        clip_id="c1", fps=30, blendshapes=["jawOpen", "mouthFunnel", "あ"], weights=w,
        poses=p, sample_rate=48_000, speech_start_s=0.3, avatar_sha256="ab" * 32,
    )  # fmt: skip
    return data, w, p


@pytest.mark.parametrize("poses", [False, True])
def test_a_track_reads_back_exactly(rng: np.random.Generator, poses: bool) -> None:
    data, w, p = _track(rng, poses=poses)
    t = decode_track(data)
    assert t.names[:3] == ["jawOpen", "mouthFunnel", "あ"]
    assert np.array_equal(t.values[:, :3], w)
    assert t.header["audio"]["speech_start_sample"] == 14_400 and t.header["fps"] == 30
    if poses:
        assert t.names[3:] == list(POSE_CHANNELS) and np.array_equal(t.values[:, 3:], p)
        assert t.header["channels"][3]["unit"] == "deg"
    else:
        assert len(t.names) == 3
    assert (12 + int.from_bytes(data[8:12], "little")) % 4 == 0  # values are 4-byte aligned


def test_broken_tracks_are_named(tmp_path: Path, rng: np.random.Generator) -> None:
    data, _, _ = _track(rng, poses=False)
    bad = tmp_path / "x.track.bin"
    for content, words in [
        (b"PK\x03\x04 not a track", "not a facelab animation track"),
        (data[:-4], "found 200 bytes"),
        (data[:12] + b"[" + data[13:], "header is not readable"),
    ]:
        bad.write_bytes(content)
        with pytest.raises(FormatError, match=words) as err:
            read_track(bad)
        assert str(bad) in str(err.value)


def test_the_browser_reader_gets_the_same_values(tmp_path: Path, rng) -> None:
    node = shutil.which("node")
    if node is None:
        pytest.fail("node is not installed (scripts/setup.sh installs it)")
    data, w, p = _track(rng, poses=True)
    path = tmp_path / "c1.track.bin"
    path.write_bytes(data)
    script = (
        "const T = require(process.argv[1]); const fs = require('fs');"
        "const b = fs.readFileSync(process.argv[2]);"
        "const t = T.parse(b.buffer.slice(b.byteOffset, b.byteOffset + b.length));"
        "console.log(JSON.stringify({names: t.names, values: Array.from(t.values),"
        " at: [t.frameAt(0), t.frameAt(0.1), t.frameAt(0.5666), t.frameAt(99)],"
        " f3: t.frame(3)}));"
    )
    out = json.loads(
        subprocess.run(
            [node, "-e", script, str(TRACK_JS), str(path)],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    )
    values = np.array(out["values"], np.float32).reshape(17, 9)
    assert out["names"] == ["jawOpen", "mouthFunnel", "あ", *POSE_CHANNELS]
    assert np.array_equal(values, np.concatenate([w, p], axis=1))
    assert out["at"] == [0, 3, 16, 16]
    assert out["f3"]["jawOpen"] == pytest.approx(float(w[3, 0]), abs=0)


@pytest.mark.slow
def test_render_writes_the_track_each_clip_was_drawn_from(tmp_path: Path) -> None:
    from dataclasses import replace

    from facelab.formats import read_manifest
    from facelab.hashing import sha256_file
    from facelab.protocol import load_protocol
    from facelab.stimuli.render.build import build_clips, settings_for
    from facelab.stimuli.render.clip import decode_frames
    from tests.protocol_edits import kato_short

    # every clip of kato2021 (each condition, set and stimulus), its stimuli shortened
    src = tmp_path / "kato2021.yaml"
    src.write_text(kato_short((ROOT / "protocols" / "kato2021.yaml").read_text("utf-8"),
                              one_set=False), encoding="utf-8")  # fmt: skip
    protocol = load_protocol(src)
    settings = replace(settings_for(protocol), width=160, height=90)
    out = tmp_path / "clips"
    build_clips(protocol, protocol_path=src, out=out, settings=settings, log=lambda s: None)
    rows = read_manifest(out)
    assert len(rows) == 6  # two stimuli (the vowels, a sentence) under three conditions
    for row in rows:
        track = read_track(out / row["track_file"])
        assert sha256_file(out / row["track_file"]) == row["track_sha256"]
        frames = decode_frames(out / row["path"], width=160, height=90)
        assert track.header["n_frames"] == len(frames) and track.header["clip_id"] == row["clip_id"]
        # the picture moves where the track moves: frame-to-frame change of the mouth region
        # against the track's frame-to-frame change (any method: ARKit or viseme channels)
        moved = np.abs(np.diff(track.values, axis=0)).sum(axis=1)
        luma = frames.astype(np.float32).mean(axis=3)
        var = luma.std(axis=0)
        pixels = np.abs(np.diff(luma[:, var >= np.percentile(var, 99)], axis=0)).mean(axis=1)
        r = np.corrcoef(moved, pixels)[0, 1]
        assert r > 0.5, (row["clip_id"], r)
    # deleting a track: the next render writes it again and reuses the clip
    first = read_manifest(out)[0]
    (out / first["track_file"]).unlink()
    again = build_clips(protocol, protocol_path=src, out=out, settings=settings,
                        log=lambda s: None)  # fmt: skip
    assert all(r["status"] == "unchanged" for r in again)
    assert sha256_file(out / first["track_file"]) == first["track_sha256"]
