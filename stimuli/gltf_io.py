"""glTF 2.0 files for avatars: the container through ``pygltflib``, the arrays with numpy.

``pygltflib`` parses and writes the container - ``.gltf`` JSON and ``.glb`` binary chunks,
data-URI and external buffers, and every object's ``extras`` and ``extensions`` (VRM keeps
its expressions there). It does not turn accessors into arrays, so :func:`accessor` does
that here, with numpy: strides, sparse accessors and normalised integers, per the glTF 2.0
specification §3.6.

Reading: every triangle primitive of every mesh reachable from the default scene is placed
with its node's world transform and merged; POSITION morph targets are merged by name
(``mesh.extras.targetNames``, as Blender, Ready Player Me and most exporters write them),
names normalised to ARKit camelCase / ``viseme_*`` (``_L``/``Left``, any case); a target a
primitive lacks is zero there. Vertex colours come from COLOR_0 or the material's base colour.
Landmarks, if the file was written by facelab, come from ``extras.facelab.landmarks``.

Writing: one mesh, one primitive (POSITION, COLOR_0, indices, one POSITION target per
blendshape, ``targetNames`` in ``mesh.extras``), as ``.glb`` or ``.gltf`` with an embedded
base64 buffer.
"""

from __future__ import annotations

import base64
from pathlib import Path
from typing import Any

import numpy as np
import pygltflib

from facelab.errors import AvatarError
from facelab.stimuli.arkit import canonical_arkit_name
from facelab.stimuli.mesh import Avatar

__all__ = ["accessor", "buffers_of", "open_gltf", "read_gltf", "write_gltf"]

COMPONENT_DTYPES = {
    5120: np.int8,
    5121: np.uint8,
    5122: np.int16,
    5123: np.uint16,
    5125: np.uint32,
    5126: np.float32,
}
TYPE_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


def open_gltf(path: Path) -> tuple[pygltflib.GLTF2, list[bytes]]:
    """The parsed document and the bytes of each of its buffers."""
    suffix = path.suffix.lower()
    if suffix not in (".gltf", ".glb", ".vrm"):
        raise AvatarError(f"{path}: expected a .gltf or .glb file (or .vrm)")
    if not path.is_file():
        raise AvatarError(f"{path}: file not found")
    try:
        raw = path.read_bytes()
        if suffix in (".glb", ".vrm"):
            if raw[:4] != b"glTF":
                raise AvatarError(f"{path}: not a glTF 2.0 binary (.glb) file")
            doc = pygltflib.GLTF2.load_from_bytes(raw)
        else:
            doc = pygltflib.GLTF2.from_json(raw.decode("utf-8"))
    except AvatarError:
        raise
    except Exception as exc:  # the JSON decoder and dataclass mapping raise many kinds
        raise AvatarError(f"{path}: not a valid glTF file ({type(exc).__name__}: {exc})") from None
    version = str(getattr(doc.asset, "version", "") or "")
    if version.split(".")[0] != "2":
        raise AvatarError(f"{path}: glTF version {version!r}; expected 2.x")
    return doc, buffers_of(doc, path)


def buffers_of(doc: pygltflib.GLTF2, path: Path) -> list[bytes]:
    """Bytes of every buffer: the GLB binary chunk, a data URI, or a file beside ``path``."""
    out = []
    for i, buf in enumerate(doc.buffers or []):
        uri = buf.uri
        if uri is None:
            out.append(doc.binary_blob() or b"")
        elif uri.startswith("data:"):
            try:
                out.append(base64.b64decode(uri.split(",", 1)[1]))
            except (IndexError, ValueError) as exc:
                raise AvatarError(f"{path}: buffer {i} has a broken data URI ({exc})") from None
        else:
            ext = path.parent / uri
            if not ext.is_file():
                raise AvatarError(f"{path}: buffer {i} refers to {uri}, which is missing")
            out.append(ext.read_bytes())
    return out


def accessor(doc: pygltflib.GLTF2, buffers: list[bytes], index: int) -> np.ndarray:
    """Accessor ``index`` as an array (count, width); normalised integers become [0, 1]."""
    acc = doc.accessors[index]
    dtype = np.dtype(COMPONENT_DTYPES[acc.componentType])
    width = TYPE_WIDTH[acc.type]
    count = acc.count
    out = np.zeros((count, width), dtype=dtype)
    if acc.bufferView is not None:
        view = doc.bufferViews[acc.bufferView]
        data = buffers[view.buffer]
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        stride = view.byteStride or dtype.itemsize * width
        out = np.ndarray(
            (count, width), dtype=dtype, buffer=data, offset=start, strides=(stride, dtype.itemsize)
        ).copy()
    sparse = acc.sparse
    if sparse is not None and sparse.count:
        iv = doc.bufferViews[sparse.indices.bufferView]
        idx = np.frombuffer(
            buffers[iv.buffer],
            dtype=COMPONENT_DTYPES[sparse.indices.componentType],
            count=sparse.count,
            offset=(iv.byteOffset or 0) + (sparse.indices.byteOffset or 0),
        )
        vv = doc.bufferViews[sparse.values.bufferView]
        vals = np.frombuffer(
            buffers[vv.buffer],
            dtype=dtype,
            count=sparse.count * width,
            offset=(vv.byteOffset or 0) + (sparse.values.byteOffset or 0),
        ).reshape(-1, width)
        out[idx] = vals
    if acc.normalized and dtype.kind in "iu":
        out = out.astype(np.float32) / np.iinfo(dtype).max
    return out


def node_matrix(node: pygltflib.Node) -> np.ndarray:
    """The node's local transform as a 4x4 matrix (column vectors)."""
    if node.matrix is not None:
        return np.array(node.matrix, dtype=float).reshape(4, 4).T
    t = np.array(node.translation if node.translation is not None else [0, 0, 0], float)
    x, y, z, w = node.rotation if node.rotation is not None else [0, 0, 0, 1]
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    s = np.array(node.scale if node.scale is not None else [1, 1, 1], float)
    m = np.eye(4)
    m[:3, :3] = r * s
    m[:3, 3] = t
    return m


def _extras(obj: Any) -> dict:
    extras = getattr(obj, "extras", None)
    return extras if isinstance(extras, dict) else {}


def read_gltf(path: Path) -> Avatar:
    doc, buffers = open_gltf(path)
    nodes = doc.nodes or []
    scenes = doc.scenes or []
    roots = scenes[doc.scene or 0].nodes if scenes else list(range(len(nodes)))
    placed: list[tuple[int, np.ndarray]] = []

    def visit(i: int, parent: np.ndarray) -> None:
        node = nodes[i]
        world = parent @ node_matrix(node)
        if node.mesh is not None:
            placed.append((node.mesh, world))
        for child in node.children or []:
            visit(child, world)

    try:
        for r in roots or []:
            visit(r, np.eye(4))
    except (IndexError, TypeError) as exc:
        raise AvatarError(f"{path}: malformed glTF ({type(exc).__name__}: {exc})") from None
    if not placed:
        raise AvatarError(f"{path}: no mesh in the scene")
    positions, faces, colors, per_target = [], [], [], []
    landmarks: dict[str, int] = {}
    offset = 0
    try:
        for mesh_index, world in placed:
            mesh = doc.meshes[mesh_index]
            names = _extras(mesh).get("targetNames", [])
            facelab = _extras(mesh).get("facelab", {})
            for prim in mesh.primitives:
                if (prim.mode if prim.mode is not None else 4) != 4:
                    continue  # points and lines are not surfaces
                attrs = prim.attributes
                if attrs.POSITION is None:
                    raise KeyError("a primitive has no POSITION attribute")
                pos = accessor(doc, buffers, attrs.POSITION).astype(np.float64)
                n = len(pos)
                pos_w = pos @ world[:3, :3].T + world[:3, 3]
                idx = (
                    accessor(doc, buffers, prim.indices).reshape(-1)
                    if prim.indices is not None
                    else np.arange(n)
                ).astype(np.int64)
                if attrs.COLOR_0 is not None:
                    col = accessor(doc, buffers, attrs.COLOR_0).astype(np.float32)[:, :3]
                else:
                    base = [0.8, 0.7, 0.65, 1]
                    if prim.material is not None:
                        pbr = doc.materials[prim.material].pbrMetallicRoughness
                        if pbr is not None and pbr.baseColorFactor is not None:
                            base = pbr.baseColorFactor
                    col = np.tile(np.array(base[:3], np.float32), (n, 1))
                targets = {}
                for k, tgt in enumerate(prim.targets or []):
                    position = tgt.get("POSITION") if isinstance(tgt, dict) else tgt.POSITION
                    if position is None:
                        continue
                    raw_name = names[k] if k < len(names) else f"target_{k}"
                    name = canonical_arkit_name(raw_name) or raw_name
                    targets[name] = (
                        accessor(doc, buffers, position).astype(np.float64) @ world[:3, :3].T
                    )
                positions.append(pos_w)
                faces.append(idx.reshape(-1, 3) + offset)
                colors.append(col)
                per_target.append((offset, n, targets))
                for key, value in facelab.get("landmarks", {}).items():
                    landmarks[key] = int(value) + offset
                offset += n
    except (KeyError, IndexError, ValueError, TypeError, AttributeError) as exc:
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


class _BufferBuilder:
    """Packs arrays into one buffer with 4-byte alignment, making views and accessors."""

    def __init__(self) -> None:
        self.blobs: list[bytes] = []
        self.size = 0
        self.views: list[pygltflib.BufferView] = []
        self.accessors: list[pygltflib.Accessor] = []

    def add(
        self, array: np.ndarray, kind: str, component: int, target: int | None, minmax: bool
    ) -> int:
        data = np.ascontiguousarray(array).tobytes()
        pad = (-self.size) % 4
        if pad:
            self.blobs.append(b"\x00" * pad)
            self.size += pad
        self.views.append(
            pygltflib.BufferView(
                buffer=0, byteOffset=self.size, byteLength=len(data), target=target
            )
        )
        self.blobs.append(data)
        self.size += len(data)
        self.accessors.append(
            pygltflib.Accessor(
                bufferView=len(self.views) - 1,
                componentType=component,
                count=len(array),
                type=kind,
                min=array.min(axis=0).tolist() if minmax else None,
                max=array.max(axis=0).tolist() if minmax else None,
            )
        )
        return len(self.accessors) - 1

    def buffer(self) -> bytes:
        data = b"".join(self.blobs)
        return data + b"\x00" * ((-len(data)) % 4)


def write_gltf(avatar: Avatar, path: Path) -> None:
    suffix = path.suffix.lower()
    if suffix not in (".glb", ".gltf"):
        raise AvatarError(f"{path}: expected a .glb or .gltf file name")
    b = _BufferBuilder()
    pos = b.add(avatar.neutral.astype(np.float32), "VEC3", 5126, 34962, True)
    colors = avatar.colors if avatar.colors is not None else np.full((len(avatar.neutral), 3), 0.8)
    col = b.add(np.asarray(colors, np.float32), "VEC3", 5126, 34962, False)
    idx = b.add(avatar.faces.astype(np.uint32).reshape(-1), "SCALAR", 5125, 34963, False)
    names = list(avatar.target_names)
    targets = [
        {"POSITION": b.add(avatar.targets[n].astype(np.float32), "VEC3", 5126, 34962, True)}
        for n in names
    ]
    buffer = b.buffer()
    doc = pygltflib.GLTF2(
        asset=pygltflib.Asset(version="2.0", generator="facelab"),
        scene=0,
        scenes=[pygltflib.Scene(nodes=[0])],
        nodes=[pygltflib.Node(mesh=0, name=avatar.name)],
        meshes=[
            pygltflib.Mesh(
                name=avatar.name,
                primitives=[
                    pygltflib.Primitive(
                        attributes=pygltflib.Attributes(POSITION=pos, COLOR_0=col),
                        indices=idx,
                        mode=4,
                        targets=targets,
                        material=0,
                    )
                ],
                weights=[0.0] * len(names),
                extras={"targetNames": names, "facelab": {"landmarks": avatar.landmarks}},
            )
        ],
        materials=[
            pygltflib.Material(
                pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
                    baseColorFactor=[1, 1, 1, 1], metallicFactor=0.0, roughnessFactor=0.8
                ),
                doubleSided=True,
            )
        ],
        accessors=b.accessors,
        bufferViews=b.views,
        buffers=[pygltflib.Buffer(byteLength=len(buffer))],
    )
    if suffix == ".gltf":
        doc.buffers[0].uri = (
            "data:application/octet-stream;base64," + base64.b64encode(buffer).decode()
        )
        path.write_text(doc.gltf_to_json(), encoding="utf-8")
        return
    doc.set_binary_blob(buffer)
    path.write_bytes(b"".join(doc.save_to_bytes()))
