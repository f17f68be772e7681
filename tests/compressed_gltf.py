"""Compressed and extended glTF files for the reader's tests, made here from an uncompressed
one as the usual tools write them (glTF-Transform's ``meshopt``, ``quantize``, ``draco``,
``webp``; VRoid exports): ``EXT_meshopt_compression`` buffer views (with the extension's empty
fallback buffer), ``KHR_mesh_quantization`` attributes (normalised 16-bit texture coordinates
and morph target deltas), ``KHR_draco_mesh_compression`` primitives (order kept: morph targets
stay plain), ``EXT_texture_webp`` and ``KHR_texture_basisu`` textures and
``KHR_texture_transform``. Each extension the result uses is listed as required, as a
compressing tool does."""

from __future__ import annotations

import io
import json
import struct
from pathlib import Path
from typing import Any

import numpy as np

COMPONENT = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32,
             5126: np.float32}  # fmt: skip
WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def glb_chunks(path: Path) -> tuple[dict[str, Any], bytes]:
    """(JSON chunk, every byte after it, unparsed) of a .glb/.vrm file."""
    raw = path.read_bytes()
    n = struct.unpack_from("<I", raw, 12)[0]
    return json.loads(raw[20 : 20 + n]), raw[20 + n :]


def write_glb_chunks(path: Path, doc: dict[str, Any], rest: bytes) -> Path:
    """A .glb of ``doc`` (NaN allowed, for damaged files) followed by ``rest`` as given."""
    text = json.dumps(doc, allow_nan=True).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + rest
    path.write_bytes(b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body)
    return path


def read_glb(path: Path) -> tuple[dict[str, Any], bytes]:
    """(JSON chunk, BIN chunk payload)."""
    doc, rest = glb_chunks(path)
    return doc, rest[8 : 8 + struct.unpack_from("<I", rest, 0)[0]] if rest else b""


def write_glb(path: Path, doc: dict[str, Any], blob: bytes) -> Path:
    blob += b"\0" * (-len(blob) % 4)
    return write_glb_chunks(path, doc, struct.pack("<II", len(blob), 0x004E4942) + blob)


def _array(doc: dict[str, Any], blob: bytes, index: int) -> np.ndarray:
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype = np.dtype(COMPONENT[acc["componentType"]])
    width = WIDTH[acc["type"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    stride = view.get("byteStride") or dtype.itemsize * width
    return np.ndarray((acc["count"], width), dtype, blob, start, (stride, dtype.itemsize)).copy()


class _Blob:
    def __init__(self, data: bytes = b""):
        self.data = bytearray(data)

    def add(self, data: bytes) -> int:
        self.data += b"\0" * (-len(self.data) % 4)
        start = len(self.data)
        self.data += data
        return start


def _requires(doc: dict[str, Any], name: str) -> None:
    for key in ("extensionsUsed", "extensionsRequired"):
        doc.setdefault(key, [])
        if name not in doc[key]:
            doc[key].append(name)


def _replace(
    doc: dict[str, Any], blob: _Blob, index: int, array: np.ndarray, stride: int | None = None,
    **acc: Any,
) -> None:  # fmt: skip
    """Accessor ``index`` rewritten as ``array`` in a view of its own (with ``acc`` fields;
    ``stride``: the rows of ``array`` are padded to that many bytes)."""
    a = doc["accessors"][index]
    start = blob.add(np.ascontiguousarray(array).tobytes())
    view = {"buffer": 0, "byteOffset": start, "byteLength": array.nbytes}
    if stride:
        view["byteStride"] = stride
    doc["bufferViews"].append(view)
    a.update(bufferView=len(doc["bufferViews"]) - 1, byteOffset=0, count=len(array), **acc)
    a.pop("min", None), a.pop("max", None)
    if a.get("type") == "VEC3" and acc.get("componentType") == 5126:
        a["min"], a["max"] = array.min(0).tolist(), array.max(0).tolist()


def quantize(doc: dict[str, Any], blob: _Blob, raw: bytes) -> None:
    """TEXCOORD_0 as normalised uint16, morph target POSITION deltas as normalised int16."""
    _requires(doc, "KHR_mesh_quantization")
    for mesh in doc["meshes"]:
        for prim in mesh["primitives"]:
            uv = prim["attributes"].get("TEXCOORD_0")
            plain = uv is not None and "bufferView" in doc["accessors"][uv]  # not Draco's
            if plain and doc["accessors"][uv]["componentType"] == 5126:
                q = np.round(np.clip(_array(doc, raw, uv), 0, 1) * 65535).astype(np.uint16)
                _replace(doc, blob, uv, q, componentType=5123, normalized=True)
            for tgt in prim.get("targets", []):
                if "POSITION" in tgt and doc["accessors"][tgt["POSITION"]]["componentType"] == 5126:
                    d = _array(doc, raw, tgt["POSITION"])
                    # rows padded to 8 bytes: vertex attributes align to 4 (glTF 2.0 §3.6.2.4)
                    q = np.zeros((len(d), 4), np.int16)
                    q[:, :3] = np.round(np.clip(d, -1, 1) * 32767)
                    _replace(doc, blob, tgt["POSITION"], q, stride=8, componentType=5122,
                             normalized=True)  # fmt: skip


def reorder(doc: dict[str, Any], blob: _Blob, raw: bytes, *, seed: int = 7) -> None:
    """Every primitive's vertices in a new order (as ``gltf-transform meshopt`` reorders them
    for the vertex cache): each vertex attribute and morph target permuted, the indices
    remapped; ``extras`` are left as they were, stale vertex indices included."""
    rng = np.random.default_rng(seed)
    done: dict[int, np.ndarray] = {}
    for mesh in doc["meshes"]:
        for prim in mesh["primitives"]:
            pos = prim["attributes"]["POSITION"]
            if pos not in done:
                done[pos] = rng.permutation(doc["accessors"][pos]["count"])
            perm = done[pos]
            accessors = [*prim["attributes"].values(),
                         *(a for t in prim.get("targets", []) for a in t.values())]  # fmt: skip
            for index in dict.fromkeys(accessors):
                a = doc["accessors"][index]
                rows = _array(doc, raw, index)[perm]
                _replace(doc, blob, index, rows, componentType=a["componentType"])
            if "indices" in prim:
                a = doc["accessors"][prim["indices"]]
                new_of_old = np.argsort(perm).astype(COMPONENT[a["componentType"]])
                _replace(doc, blob, prim["indices"], new_of_old[_array(doc, raw, prim["indices"])])


def meshopt(doc: dict[str, Any], blob: bytes) -> bytes:
    """Every vertex-attribute and index buffer view meshopt-encoded into buffer 0; the plain
    bytes' place is an empty fallback buffer (1), as glTF-Transform writes it."""
    import meshoptimizer

    _requires(doc, "EXT_meshopt_compression")
    out = _Blob()
    images = {img.get("bufferView") for img in doc.get("images", [])}
    uses: dict[int, dict[str, Any]] = {}
    for mesh in doc["meshes"]:
        for prim in mesh["primitives"]:
            index = prim.get("indices")
            view = doc["accessors"][index].get("bufferView") if index is not None else None
            if view is not None:  # (Draco's indices have none)
                uses[view] = {"mode": "TRIANGLES"}
    fallback = 0
    for i, view in enumerate(doc["bufferViews"]):
        data = blob[view.get("byteOffset", 0) : view.get("byteOffset", 0) + view["byteLength"]]
        acc = next((a for a in doc["accessors"] if a.get("bufferView") == i), None)
        if i in images or acc is None or acc["type"] == "MAT4":
            view["byteOffset"] = out.add(data)
            continue
        dtype = np.dtype(COMPONENT[acc["componentType"]])
        stride = view.get("byteStride") or dtype.itemsize * WIDTH[acc["type"]]
        if uses.get(i, {}).get("mode") == "TRIANGLES":
            idx = np.frombuffer(data, dtype).astype(np.uint32)
            enc = meshoptimizer.encode_index_buffer(idx, len(idx), int(idx.max()) + 1)
            ext = {"mode": "TRIANGLES", "count": len(idx), "byteStride": dtype.itemsize}
        elif stride % 4:
            view["byteOffset"] = out.add(data)  # meshopt needs 4-byte vertex strides
            continue
        else:
            rows = np.frombuffer(data, np.uint8).reshape(acc["count"], stride)
            enc = meshoptimizer.encode_vertex_buffer(rows, acc["count"], stride)
            ext = {"mode": "ATTRIBUTES", "count": acc["count"], "byteStride": stride}
        ext.update(buffer=0, byteOffset=out.add(bytes(enc)), byteLength=len(enc))
        view.update(buffer=1, byteOffset=fallback, extensions={"EXT_meshopt_compression": ext})
        if ext["mode"] == "ATTRIBUTES" and acc["type"] != "SCALAR":
            view["byteStride"] = stride
        fallback += view["byteLength"] + (-view["byteLength"] % 4)
    data = bytes(out.data)
    doc["buffers"] = [
        {"byteLength": len(data)},
        {"byteLength": fallback, "extensions": {"EXT_meshopt_compression": {"fallback": True}}},
    ]
    return data


def draco(doc: dict[str, Any], blob: _Blob, raw: bytes) -> None:
    """Each primitive's POSITION, TEXCOORD_0 and indices Draco-compressed (vertex order kept,
    so its plain morph targets still match); the accessors lose their buffer views."""
    import DracoPy

    _requires(doc, "KHR_draco_mesh_compression")
    used: dict[int, int] = {}  # accessor -> primitives using it (shared ones stay plain)
    for mesh in doc["meshes"]:
        for prim in mesh["primitives"]:
            for index in {*prim["attributes"].values(), prim.get("indices")} - {None}:
                used[index] = used.get(index, 0) + 1
    for mesh in doc["meshes"]:
        for prim in mesh["primitives"]:
            attrs = prim["attributes"]
            if any(used[i] > 1 for i in {*attrs.values(), prim.get("indices")} - {None}):
                continue
            pos = _array(doc, raw, attrs["POSITION"]).astype(np.float32)
            faces = _array(doc, raw, prim["indices"]).reshape(-1, 3)
            uv = (
                _array(doc, raw, attrs["TEXCOORD_0"]).astype(np.float64)
                if "TEXCOORD_0" in attrs
                else None
            )
            enc = DracoPy.encode(pos, faces=faces, tex_coord=uv, preserve_order=True,
                                 quantization_bits=16)  # fmt: skip
            decoded = DracoPy.decode(enc)
            ids = {a["attribute_type"]: a["unique_id"] for a in decoded.attributes}
            start = blob.add(enc)
            doc["bufferViews"].append({"buffer": 0, "byteOffset": start, "byteLength": len(enc)})
            ext = {"bufferView": len(doc["bufferViews"]) - 1,
                   "attributes": {"POSITION": ids[0]}}  # fmt: skip
            if uv is not None:
                ext["attributes"]["TEXCOORD_0"] = ids[3]
            for index in (attrs["POSITION"], prim["indices"], *(
                    [attrs["TEXCOORD_0"]] if uv is not None else [])):  # fmt: skip
                doc["accessors"][index].pop("bufferView", None)
                doc["accessors"][index].pop("byteOffset", None)
            prim.setdefault("extensions", {})["KHR_draco_mesh_compression"] = ext


def webp(doc: dict[str, Any], blob: _Blob, raw: bytes) -> None:
    """Every image re-encoded as WebP, its textures pointing at it through EXT_texture_webp."""
    from PIL import Image

    _requires(doc, "EXT_texture_webp")
    for img in doc.get("images", []):
        view = doc["bufferViews"][img["bufferView"]]
        start = view.get("byteOffset", 0)
        with Image.open(io.BytesIO(raw[start : start + view["byteLength"]])) as pic:
            out = io.BytesIO()
            pic.convert("RGB").save(out, format="WEBP", lossless=True)
        data = out.getvalue()
        doc["bufferViews"].append({"buffer": 0, "byteOffset": blob.add(data),
                                   "byteLength": len(data)})  # fmt: skip
        img.update(bufferView=len(doc["bufferViews"]) - 1, mimeType="image/webp")
    for tex in doc.get("textures", []):
        tex["extensions"] = {"EXT_texture_webp": {"source": tex.pop("source")}}


def basisu(doc: dict[str, Any]) -> None:
    """Textures that name only a KTX2 image (no decoder here: the reader draws without it)."""
    _requires(doc, "KHR_texture_basisu")
    for img in doc.get("images", []):
        img["mimeType"] = "image/ktx2"
    for tex in doc.get("textures", []):
        tex["extensions"] = {"KHR_texture_basisu": {"source": tex.pop("source")}}


def texture_transform(doc: dict[str, Any], *, offset, scale, rotation) -> None:
    _requires(doc, "KHR_texture_transform")
    for mat in doc.get("materials", []):
        info = mat.get("pbrMetallicRoughness", {}).get("baseColorTexture")
        if info is not None:
            info["extensions"] = {"KHR_texture_transform": {"offset": offset, "scale": scale,
                                                            "rotation": rotation}}  # fmt: skip


def compress(src: Path, dst: Path, *steps: str) -> Path:
    """``src`` (a .glb) through ``steps`` (reorder, quantize, draco, webp, basisu, meshopt -
    meshopt last) into ``dst``."""
    doc, raw = read_glb(src)
    blob = _Blob(raw)
    for step in steps:
        if step == "quantize":
            quantize(doc, blob, raw)
        elif step == "draco":
            draco(doc, blob, raw)
        elif step == "webp":
            webp(doc, blob, raw)
        elif step == "basisu":
            basisu(doc)
        elif step == "reorder":
            reorder(doc, blob, raw)
        elif step != "meshopt":
            raise ValueError(step)
        raw = bytes(blob.data)
    if "meshopt" in steps:
        raw = meshopt(doc, raw)
    doc["buffers"][0]["byteLength"] = len(raw)
    return write_glb(dst, doc, raw)
