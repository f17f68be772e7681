"""Compressed and extended glTF avatars, as glTF-Transform and VRoid Studio write them: each
sample avatar (Ready Player Me layout, VRM 1.0) through meshopt, quantization, Draco and WebP
(tests/compressed_gltf.py makes the files) reads back as the uncompressed file does; a
KTX2-only texture is left out with a note; an extension facelab does not read is refused by
name; damaged compressed data are refused in words, never with a decoder's message or a crash."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from facelab.errors import AvatarError
from facelab.experiment.cli import main
from facelab.stimuli.avatar import default_head, lip_metrics, load, save
from facelab.stimuli.avatar.samples import write_sample
from facelab.stimuli.checks.avatar_checks import landmark_rows
from tests.compressed_gltf import compress, read_glb, write_glb

STEPS = [
    ("meshopt",),
    ("quantize",),
    ("quantize", "meshopt"),
    ("draco",),
    ("webp",),
    ("draco", "quantize", "webp", "meshopt"),
]


@pytest.fixture(scope="module")
def samples(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("compressed")
    return {
        "rpm": write_sample(root / "rpm.glb", kind="rpm"),
        "vrm1": write_sample(root / "vrm1.vrm", kind="vrm1"),
    }


def _rotated(faces: np.ndarray) -> np.ndarray:
    """Each triangle started at its smallest index (codecs may rotate a triangle's corners;
    its winding, which decides the side it faces, is kept)."""
    shift = np.argmin(faces, axis=1)
    rows = np.arange(len(faces))[:, None]
    return faces[rows, (shift[:, None] + np.arange(3)) % 3]


@pytest.mark.parametrize("kind", ["rpm", "vrm1"])
@pytest.mark.parametrize("steps", STEPS, ids=["+".join(s) for s in STEPS])
def test_a_compressed_avatar_reads_as_the_plain_one(
    samples: dict[str, Path], tmp_path: Path, kind: str, steps: tuple[str, ...]
) -> None:
    plain = load(samples[kind])
    path = compress(samples[kind], tmp_path / f"{kind}.glb", *steps)
    doc, _ = read_glb(path)
    assert doc["extensionsRequired"]  # as a compressing tool marks it
    got = load(path)
    assert got.target_names == plain.target_names
    # positions: exact, or within Draco's 16-bit quantization of a 1.8 m figure
    assert np.abs(got.neutral - plain.neutral).max() < 5e-5
    assert np.array_equal(_rotated(got.faces), _rotated(plain.faces))
    for name in plain.target_names:  # 16-bit normalised deltas: within 1/32767 m
        assert np.abs(got.targets[name] - plain.targets[name]).max() < 3.1e-5, name
    assert got.skeleton is not None and plain.skeleton is not None
    assert got.skeleton.roles == plain.skeleton.roles
    assert np.allclose(got.skeleton.weights, plain.skeleton.weights, atol=1e-6)
    assert len(got.textures) == len(plain.textures) == 1
    assert np.array_equal(got.textures[0], plain.textures[0])  # WebP lossless
    assert np.abs(got.uv - plain.uv).max() < 2e-5  # 16-bit normalised coordinates
    assert "notes" not in got.source


def test_a_ktx2_texture_is_left_out_with_a_note(
    samples: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    got = load(compress(samples["rpm"], tmp_path / "ktx2.glb", "basisu"))
    assert got.textures == () and got.uv is None
    (note,) = got.source["notes"]
    assert "KHR_texture_basisu" in note and "drawn without it" in note
    assert main(["avatar", "inspect", str(tmp_path / "ktx2.glb")]) == 0
    out = capsys.readouterr().out
    assert "note       a KTX2 (KHR_texture_basisu) texture is not decoded" in out


def test_a_texture_transform_moves_the_coordinates(
    samples: dict[str, Path], tmp_path: Path
) -> None:
    from tests.compressed_gltf import texture_transform

    doc, blob = read_glb(samples["rpm"])
    texture_transform(doc, offset=[0.25, 0.5], scale=[2.0, 0.5], rotation=np.pi / 2)
    got = load(write_glb(tmp_path / "tt.glb", doc, blob))
    plain = load(samples["rpm"])
    uv = plain.uv
    # the extension's GLSL: T(offset) R(rotation) S(scale), R = [[cos, -sin], [sin, cos]]
    expected = np.column_stack([0.25 - 0.5 * uv[:, 1], 0.5 + 2.0 * uv[:, 0]])
    mapped = np.unique(plain.faces[plain.face_texture >= 0])  # the textured primitive's
    assert len(mapped) > 1000
    assert np.abs(got.uv[mapped] - expected[mapped]).max() < 1e-5


def test_an_extension_facelab_does_not_read_is_refused_by_name(
    samples: dict[str, Path], tmp_path: Path
) -> None:
    doc, blob = read_glb(samples["rpm"])
    doc["extensionsUsed"] = doc["extensionsRequired"] = ["EXT_mesh_gpu_instancing", "KHR_foo"]
    path = write_glb(tmp_path / "needs.glb", doc, blob)
    with pytest.raises(AvatarError) as err:
        load(path)
    message = str(err.value)
    assert "needs EXT_mesh_gpu_instancing, KHR_foo, which facelab does not read" in message
    assert "gltf-transform/cli copy needs.glb plain.glb" in message
    assert "malformed" not in message
    # at the command line: the same words, exit 2, no traceback
    code = main(["avatar", "inspect", str(path)])
    assert code == 2


@pytest.mark.parametrize("damage", ["meshopt", "draco"])
def test_damaged_compressed_data_are_refused_in_words(
    samples: dict[str, Path], tmp_path: Path, damage: str
) -> None:
    path = compress(samples["rpm"], tmp_path / "c.glb", damage)
    doc, blob = read_glb(path)
    data = bytearray(blob)
    if damage == "meshopt":
        ext = next(v["extensions"]["EXT_meshopt_compression"] for v in doc["bufferViews"]
                   if "extensions" in v)  # fmt: skip
    else:
        prim = next(p for m in doc["meshes"] for p in m["primitives"] if "extensions" in p)
        view = prim["extensions"]["KHR_draco_mesh_compression"]["bufferView"]
        ext = doc["bufferViews"][view]
    start = ext.get("byteOffset", 0)
    data[start : start + ext["byteLength"]] = bytes(ext["byteLength"])  # zeroed
    broken = write_glb(tmp_path / "broken.glb", doc, bytes(data))
    with pytest.raises(AvatarError) as err:
        load(broken)
    message = str(err.value)
    assert message.startswith(f"{broken}: cannot read its compressed geometry: ")
    assert "do not decode" in message or "missing" in message
    assert "Error" not in message and "error code" not in message


def test_a_compressed_avatar_is_described(
    samples: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The meshopt + quantized + WebP file as glTF-Transform writes it: inspect reads it."""
    path = compress(samples["rpm"], tmp_path / "web.glb", "quantize", "webp", "meshopt")
    assert main(["avatar", "inspect", str(path), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["arkit_targets"] == "52/52" and report["textures"] and not report["notes"]


@pytest.mark.slow
def test_damaged_compressed_files_load_or_are_refused(
    samples: dict[str, Path], tmp_path: Path
) -> None:
    """Random edits of compressed files' JSON (deleted keys, values of other types) and random
    bytes in their compressed streams: each loads into a finite avatar or is refused in
    words - no other exception, no crash of a decoder."""
    import random

    from tests.mutation import load_or_refuse, mutated

    rng = random.Random(20261125)
    files = {
        steps: read_glb(compress(samples["rpm"], tmp_path / f"{'_'.join(steps)}.glb", *steps))
        for steps in (("meshopt",), ("draco",), ("quantize", "webp", "meshopt"))
    }
    values = [None, 0, -1, 10**9, "", "x", [], {}, [1, 2], True, 0.5, float("nan"), 3,
              "TRIANGLES", "ATTRIBUTES", 2**40]  # fmt: skip
    outcomes = {"loaded": 0, "refused": 0}
    for i in range(200):
        doc, blob = files[rng.choice(sorted(files))]
        if i % 4 == 3:  # bytes of the binary chunk (compressed streams, images) damaged
            data = bytearray(blob)
            for _ in range(rng.choice([1, 5, 50])):
                data[rng.randrange(len(data))] = rng.randrange(256)
            path = write_glb(tmp_path / f"m{i}.glb", doc, bytes(data))
        else:
            path = write_glb(tmp_path / f"m{i}.glb", mutated(doc, rng=rng, values=values), blob)
        load_or_refuse(path, outcomes)
    assert min(outcomes.values()) > 20, outcomes


@pytest.mark.parametrize("steps", [("reorder",), ("reorder", "quantize", "meshopt")])
def test_landmarks_survive_a_tool_that_reorders_vertices(
    tmp_path: Path, steps: tuple[str, ...]
) -> None:
    """The default head saved, its vertices shuffled (as gltf-transform meshopt does; the
    stored landmark indices now point at other vertices), read back: every landmark is the
    same place on the face, the closed lips' upper and lower edge (one position) told apart
    by how they move, and the reader says it looked them up."""
    head = default_head()
    save(head, tmp_path / "head.glb")
    got = load(compress(tmp_path / "head.glb", tmp_path / "shuffled.glb", *steps))
    stale = [k for k, i in head.landmarks.items() if got.landmarks[k] != i]
    assert len(stale) == len(head.landmarks)  # the indices did change under the tool
    for name, i in head.landmarks.items():
        j = got.landmarks[name]
        assert np.abs(got.neutral[j] - head.neutral[i]).max() < 1e-4, name
        assert np.abs(got.targets["jawOpen"][j] - head.targets["jawOpen"][i]).max() < 1e-4, name
    lip = lip_metrics(got, got.deform({"jawOpen": 1.0}))
    assert lip["aperture"] > 0.005 and lip["width"] > 0.03  # the lips part, corners apart
    assert any("found by geometry" in n for n in got.source["notes"])
    rows = landmark_rows(got)
    assert [r.passed for r in rows] == [True]
