"""Minimal glTF 2.0 reading and writing for avatars with morph targets (numpy only).

Reading: every triangle primitive of every mesh reachable from the default scene is placed
with its node's world transform and merged; POSITION morph targets are merged by name
(``mesh.extras.targetNames``, as Blender, Ready Player Me and most exporters write them),
names normalised to ARKit camelCase / ``viseme_*`` (``_L``/``Left``, any case); a target a
primitive lacks is zero there. Vertex colours come from COLOR_0 or the material's base colour.
Landmarks, if the file was written by facelab, come from ``extras.facelab.landmarks``.

Writing: one mesh, one primitive (POSITION, COLOR_0, indices, one POSITION target per blendshape,
``targetNames`` in ``mesh.extras``), as ``.glb`` or ``.gltf`` with an embedded base64 buffer.
"""

from __future__ import annotations

import base64
import json
import struct
from pathlib import Path

import numpy as np

from stimuli.arkit import canonical_arkit_name
from stimuli.avatar import Avatar, AvatarError

__all__ = ["read_gltf", "write_gltf"]

_COMPONENT = {
    5120: np.int8,
    5121: np.uint8,
    5122: np.int16,
    5123: np.uint16,
    5125: np.uint32,
    5126: np.float32,
}
_COUNT = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
_GLB_MAGIC, _JSON, _BIN = 0x46546C67, 0x4E4F534A, 0x004E4942


def _parse(path: Path) -> tuple[dict, list[bytes]]:
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise AvatarError(f"{path}: cannot read ({exc})") from None
    binary = b""
    try:
        if path.suffix.lower() == ".glb":
            magic, version, _length = struct.unpack_from("<III", raw, 0)
            if magic != _GLB_MAGIC or version != 2:
                raise AvatarError(f"{path}: not a glTF 2.0 binary (.glb) file")
            offset, doc = 12, None
            while offset < len(raw):
                size, kind = struct.unpack_from("<II", raw, offset)
                chunk = raw[offset + 8 : offset + 8 + size]
                if kind == _JSON:
                    doc = json.loads(chunk.decode("utf-8"))
                elif kind == _BIN:
                    binary = chunk
                offset += 8 + size
            if doc is None:
                raise AvatarError(f"{path}: the .glb has no JSON chunk")
        elif path.suffix.lower() == ".gltf":
            doc = json.loads(raw.decode("utf-8"))
        else:
            raise AvatarError(f"{path}: expected a .gltf or .glb file")
    except (struct.error, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise AvatarError(f"{path}: not a valid glTF file ({exc})") from None
    if str(doc.get("asset", {}).get("version", "")).split(".")[0] != "2":
        raise AvatarError(
            f"{path}: glTF version {doc.get('asset', {}).get('version')!r}; expected 2.x"
        )
    buffers = []
    for i, buf in enumerate(doc.get("buffers", [])):
        uri = buf.get("uri")
        if uri is None:
            buffers.append(binary)
        elif uri.startswith("data:"):
            buffers.append(base64.b64decode(uri.split(",", 1)[1]))
        else:
            ext = path.parent / uri
            if not ext.is_file():
                raise AvatarError(f"{path}: buffer {i} refers to {uri}, which is missing")
            buffers.append(ext.read_bytes())
    return doc, buffers


def _accessor(doc: dict, buffers: list[bytes], index: int) -> np.ndarray:
    acc = doc["accessors"][index]
    dtype = np.dtype(_COMPONENT[acc["componentType"]])
    width = _COUNT[acc["type"]]
    count = acc["count"]
    out = np.zeros((count, width), dtype=dtype)
    if "bufferView" in acc:
        view = doc["bufferViews"][acc["bufferView"]]
        data = buffers[view["buffer"]]
        start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        stride = view.get("byteStride") or dtype.itemsize * width
        row = np.ndarray(
            (count, width), dtype=dtype, buffer=data, offset=start, strides=(stride, dtype.itemsize)
        )
        out = row.copy()
    sparse = acc.get("sparse")
    if sparse:
        idx_info, val_info = sparse["indices"], sparse["values"]
        iv = doc["bufferViews"][idx_info["bufferView"]]
        idx = np.frombuffer(
            buffers[iv["buffer"]],
            dtype=_COMPONENT[idx_info["componentType"]],
            count=sparse["count"],
            offset=iv.get("byteOffset", 0) + idx_info.get("byteOffset", 0),
        )
        vv = doc["bufferViews"][val_info["bufferView"]]
        vals = np.frombuffer(
            buffers[vv["buffer"]],
            dtype=dtype,
            count=sparse["count"] * width,
            offset=vv.get("byteOffset", 0) + val_info.get("byteOffset", 0),
        ).reshape(-1, width)
        out[idx] = vals
    if acc.get("normalized") and dtype.kind in "iu":
        out = out.astype(np.float32) / np.iinfo(dtype).max
    return out


def _node_matrix(node: dict) -> np.ndarray:
    if "matrix" in node:
        return np.array(node["matrix"], dtype=float).reshape(4, 4).T
    t = np.array(node.get("translation", [0, 0, 0]), float)
    x, y, z, w = node.get("rotation", [0, 0, 0, 1])
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    s = np.array(node.get("scale", [1, 1, 1]), float)
    m = np.eye(4)
    m[:3, :3] = r * s
    m[:3, 3] = t
    return m


def read_gltf(path: Path) -> Avatar:
    doc, buffers = _parse(path)
    scenes = doc.get("scenes", [])
    roots = (
        scenes[doc.get("scene", 0)]["nodes"] if scenes else list(range(len(doc.get("nodes", []))))
    )
    placed: list[tuple[int, np.ndarray]] = []

    def visit(i: int, parent: np.ndarray) -> None:
        node = doc["nodes"][i]
        world = parent @ _node_matrix(node)
        if "mesh" in node:
            placed.append((node["mesh"], world))
        for child in node.get("children", []):
            visit(child, world)

    for r in roots:
        visit(r, np.eye(4))
    if not placed:
        raise AvatarError(f"{path}: no mesh in the scene")
    positions, faces, colors, per_target = [], [], [], []
    landmarks: dict[str, int] = {}
    offset = 0
    try:
        for mesh_index, world in placed:
            mesh = doc["meshes"][mesh_index]
            names = (mesh.get("extras") or {}).get("targetNames", [])
            facelab = (mesh.get("extras") or {}).get("facelab", {})
            for prim in mesh["primitives"]:
                if prim.get("mode", 4) != 4:
                    continue  # points and lines are not surfaces
                pos = _accessor(doc, buffers, prim["attributes"]["POSITION"]).astype(np.float64)
                n = len(pos)
                pos_w = pos @ world[:3, :3].T + world[:3, 3]
                idx = (
                    _accessor(doc, buffers, prim["indices"]).reshape(-1)
                    if "indices" in prim
                    else np.arange(n)
                ).astype(np.int64)
                if "COLOR_0" in prim["attributes"]:
                    col = _accessor(doc, buffers, prim["attributes"]["COLOR_0"]).astype(np.float32)[
                        :, :3
                    ]
                else:
                    mat = doc.get("materials", [{}])[prim["material"]] if "material" in prim else {}
                    base = mat.get("pbrMetallicRoughness", {}).get(
                        "baseColorFactor", [0.8, 0.7, 0.65, 1]
                    )
                    col = np.tile(np.array(base[:3], np.float32), (n, 1))
                targets = {}
                for k, tgt in enumerate(prim.get("targets", [])):
                    if "POSITION" not in tgt:
                        continue
                    raw_name = names[k] if k < len(names) else f"target_{k}"
                    name = canonical_arkit_name(raw_name) or raw_name
                    targets[name] = (
                        _accessor(doc, buffers, tgt["POSITION"]).astype(np.float64)
                        @ world[:3, :3].T
                    )
                positions.append(pos_w)
                faces.append(idx.reshape(-1, 3) + offset)
                colors.append(col)
                per_target.append((offset, n, targets))
                for key, value in facelab.get("landmarks", {}).items():
                    landmarks[key] = int(value) + offset
                offset += n
    except (KeyError, IndexError, ValueError, TypeError) as exc:
        raise AvatarError(f"{path}: malformed glTF ({type(exc).__name__}: {exc})") from None
    if not positions:
        raise AvatarError(f"{path}: no triangle primitives")
    verts = np.vstack(positions)
    all_names = sorted({name for _, _, t in per_target for name in t})
    merged = {name: np.zeros_like(verts) for name in all_names}
    for start, n, t in per_target:
        for name, delta in t.items():
            merged[name][start : start + n] = delta
    return Avatar(
        verts,
        np.vstack(faces),
        {k: v.astype(np.float32) for k, v in merged.items()},
        landmarks,
        np.vstack(colors),
        name=path.stem,
    )


def write_gltf(avatar: Avatar, path: Path) -> None:
    suffix = path.suffix.lower()
    if suffix not in (".glb", ".gltf"):
        raise AvatarError(f"{path}: expected a .glb or .gltf file name")
    blobs: list[bytes] = []
    views: list[dict] = []
    accessors: list[dict] = []

    def add(
        array: np.ndarray, kind: str, component: int, target: int | None, minmax: bool = False
    ) -> int:
        data = np.ascontiguousarray(array).tobytes()
        offset = sum(len(b) for b in blobs)
        pad = (-offset) % 4
        if pad:
            blobs.append(b"\x00" * pad)
            offset += pad
        blobs.append(data)
        view = {"buffer": 0, "byteOffset": offset, "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        views.append(view)
        acc = {
            "bufferView": len(views) - 1,
            "componentType": component,
            "count": len(array),
            "type": kind,
        }
        if minmax:
            acc["min"] = array.min(axis=0).tolist()
            acc["max"] = array.max(axis=0).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    pos = add(avatar.neutral.astype(np.float32), "VEC3", 5126, 34962, minmax=True)
    colors = avatar.colors if avatar.colors is not None else np.full((len(avatar.neutral), 3), 0.8)
    col = add(np.asarray(colors, np.float32), "VEC3", 5126, 34962)
    idx = add(avatar.faces.astype(np.uint32).reshape(-1), "SCALAR", 5125, 34963)
    names = list(avatar.target_names)
    targets = [
        {"POSITION": add(avatar.targets[n].astype(np.float32), "VEC3", 5126, 34962, minmax=True)}
        for n in names
    ]
    buffer = b"".join(blobs)
    doc = {
        "asset": {"version": "2.0", "generator": "facelab"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": avatar.name}],
        "meshes": [
            {
                "name": avatar.name,
                "primitives": [
                    {
                        "attributes": {"POSITION": pos, "COLOR_0": col},
                        "indices": idx,
                        "mode": 4,
                        "targets": targets,
                        "material": 0,
                    }
                ],
                "weights": [0.0] * len(names),
                "extras": {"targetNames": names, "facelab": {"landmarks": avatar.landmarks}},
            }
        ],
        "materials": [
            {
                "pbrMetallicRoughness": {
                    "baseColorFactor": [1, 1, 1, 1],
                    "metallicFactor": 0.0,
                    "roughnessFactor": 0.8,
                },
                "doubleSided": True,
            }
        ],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": len(buffer)}],
    }
    if suffix == ".gltf":
        doc["buffers"][0]["uri"] = (
            "data:application/octet-stream;base64," + base64.b64encode(buffer).decode()
        )
        path.write_text(json.dumps(doc), encoding="utf-8")
        return
    text = json.dumps(doc).encode("utf-8")
    text += b" " * ((-len(text)) % 4)
    buffer += b"\x00" * ((-len(buffer)) % 4)
    total = 12 + 8 + len(text) + 8 + len(buffer)
    with open(path, "wb") as fh:
        fh.write(struct.pack("<III", _GLB_MAGIC, 2, total))
        fh.write(struct.pack("<II", len(text), _JSON) + text)
        fh.write(struct.pack("<II", len(buffer), _BIN) + buffer)
