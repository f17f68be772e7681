"""VRM files laid out as VRoid Studio exports them (issue 37.2): a face of several primitives
with their own vertices, sparse morph targets, MToon materials, an alpha-masked eyelash card
and a texture atlas read through ``KHR_texture_transform`` - written by
``write_sample(..., vroid=True)`` and read back by ``avatar.load``, compared with the plain
sample of the same kind (one primitive, dense targets, no atlas)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from facelab.experiment.cli import main
from facelab.stimuli.avatar import load
from facelab.stimuli.avatar.gltf import MTOON_NOTE
from facelab.stimuli.avatar.samples import write_sample
from facelab.stimuli.render.renderer import Renderer
from facelab.stimuli.render.scene import RenderSettings

VRM_KINDS = ("vrm0", "vrm1")


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("vroid")
    out = {}
    for kind in VRM_KINDS:
        out[kind] = write_sample(folder / f"{kind}_vroid.vrm", kind=kind, vroid=True)
        out[f"{kind}_plain"] = write_sample(folder / f"{kind}_plain.vrm", kind=kind)
    return out


def _doc(path: Path) -> dict:
    import pygltflib

    return json.loads(pygltflib.GLTF2().load_binary(str(path)).gltf_to_json())


@pytest.mark.parametrize("kind", VRM_KINDS)
def test_the_file_has_what_vroid_writes(files, kind: str) -> None:
    doc = _doc(files[kind])
    face = next(m for m in doc["meshes"] if m["name"] == "Face")
    assert len(face["primitives"]) == 3
    targets = [t["POSITION"] for p in face["primitives"] for t in p["targets"]]
    accessors = [doc["accessors"][i] for i in targets]
    assert all("bufferView" not in a for a in accessors)  # no dense target
    assert any("sparse" in a for a in accessors)
    assert any("sparse" not in a for a in accessors)  # an all-zero target: no data at all
    modes = [doc["materials"][p["material"]].get("alphaMode") for p in face["primitives"]]
    assert "MASK" in modes
    assert "KHR_texture_transform" in doc["extensionsRequired"]
    if kind == "vrm1":
        assert all("VRMC_materials_mtoon" in m["extensions"] for m in doc["materials"])
    else:
        shaders = {m["shader"] for m in doc["extensions"]["VRM"]["materialProperties"]}
        assert shaders == {"VRM/MToon"}


@pytest.mark.parametrize("kind", VRM_KINDS)
def test_sparse_targets_and_split_primitives_read_as_the_plain_file(files, kind: str) -> None:
    """Every vertex of the plain face is in the VRoid-layout face (split at the hair line,
    so seam vertices appear twice) and every shape moves it the same."""
    plain, vroid = load(files[f"{kind}_plain"]), load(files[kind])
    assert vroid.source["kind"] == kind
    p_idx, v_idx = plain.parts["Face"], vroid.parts["Face"]
    assert len(v_idx) >= len(p_idx) + 8  # seam vertices twice, eight lash-card vertices
    dist, nearest = cKDTree(vroid.neutral[v_idx]).query(plain.neutral[p_idx])
    assert dist.max() < 1e-6
    assert set(plain.targets) <= set(vroid.targets)
    moved = 0
    for name in plain.targets:
        want = plain.targets[name][p_idx]
        got = vroid.targets[name][v_idx[nearest]]
        np.testing.assert_allclose(got, want, atol=1e-6, err_msg=name)
        moved += np.abs(want).max() > 1e-4
    assert moved >= 7  # the vowels, blink and joy/happy move the face


@pytest.mark.parametrize("kind", VRM_KINDS)
def test_texture_transform_alpha_mask_and_mtoon_are_read(files, kind: str) -> None:
    a = load(files[kind])
    assert MTOON_NOTE in a.source["notes"]
    channels = sorted(t.shape[2] for t in a.textures)
    assert channels == [3, 4]  # the atlas opaque (skin, hair) and masked (lashes)
    masked = next(t for t in a.textures if t.shape[2] == 4)
    assert set(np.unique(masked[..., 3])) == {0, 255}
    # the skin's coordinates land in the atlas's skin region, never the magenta one
    skin_faces = a.faces[a.face_texture >= 0]
    uv = a.uv[np.unique(skin_faces)]
    assert (uv[:, 0] >= 0.0).all() and (uv[:, 0] <= 1.0).all()
    assert not ((uv[:, 0] > 0.5) & (uv[:, 1] > 0.5)).any()


def _magenta(img: np.ndarray) -> int:
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return int(np.count_nonzero((r > 180) & (g < 90) & (b > 180)))


@pytest.mark.parametrize("kind", VRM_KINDS)
def test_the_eyelash_card_is_a_cut_out_not_a_bar(files, kind: str) -> None:
    """Rendered, the face shows no magenta (the atlas is read through the transform) and the
    lash card lets the skin through its gaps: drawn opaque, the same card covers more of the
    picture with its dark strand colour."""
    a = load(files[kind])
    opaque = dataclasses.replace(a, textures=tuple(t[..., :3].copy() for t in a.textures))
    settings = RenderSettings(width=320, height=320, zoom=2.0)
    weights = np.zeros(len(a.target_names))
    with Renderer(a, settings) as r:
        masked_img = r.frame(weights)
    with Renderer(opaque, settings) as r:
        opaque_img = r.frame(weights)
    assert _magenta(masked_img) == 0

    def dark(img: np.ndarray) -> int:
        return int(np.count_nonzero(img[..., :3].max(axis=2) < 60))

    assert dark(opaque_img) > 0
    assert dark(masked_img) < 0.75 * dark(opaque_img)


def test_avatar_sample_and_inspect_with_a_sheet(tmp_path: Path, capsys) -> None:
    out = tmp_path / "model.vrm"
    assert main(["avatar", "sample", "--kind", "vrm1", "--vroid", "--out", str(out)]) == 0
    sheet = tmp_path / "sheet.png"
    assert main(["avatar", "inspect", str(out), "--sheet", str(sheet), "--tile", "128"]) == 0
    text = capsys.readouterr().out
    assert "MToon" in text and "vowel presets" in text
    from PIL import Image

    with Image.open(sheet) as img:
        assert _magenta(np.asarray(img.convert("RGB"))) == 0
    assert main(["avatar", "sample", "--kind", "rpm", "--vroid", "--out", str(out)]) == 2
