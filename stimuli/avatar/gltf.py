"""glTF 2.0 files for avatars: the container through ``pygltflib``, the arrays with numpy.

``pygltflib`` parses and writes the container - ``.gltf`` JSON and ``.glb`` binary chunks,
data-URI and external buffers, and every object's ``extras`` and ``extensions`` (VRM keeps
its expressions there). It does not turn accessors into arrays, so :func:`accessor` does
that here, with numpy: strides, sparse accessors and normalised integers, per the glTF 2.0
specification §3.6.

Reading: every triangle primitive of every mesh reachable from the default scene is merged
into one avatar in the **rest world frame**:

* unskinned meshes are placed with their node's world transform; if an ancestor node is a
  joint, the mesh is bound rigidly to that joint (a hat or glasses follow the head);
* skinned meshes (``JOINTS_0``/``WEIGHTS_0`` with a ``skin``) are placed by their rest skinning
  matrices Σ w·(joint world · inverse bind) - the node's own transform is ignored, as glTF
  2.0 §3.7.3 requires - and keep their joints and weights (:class:`~facelab.stimuli.avatar.rig.
  Skeleton`: every skin's joints plus VRM humanoid bones, parents first; rig roles from the
  VRM humanoid or by joint name, see :func:`~facelab.stimuli.avatar.rig.match_roles`);
* POSITION morph targets are merged by name across meshes (``mesh.extras.targetNames`` or the
  primitive's, as Blender, Ready Player Me and most exporters write them), so one ARKit name
  drives the head, teeth and tongue meshes together; names are normalised to ARKit camelCase
  / ``viseme_*`` (``_L``/``Left``, any case); a target a primitive lacks is zero there;
* colours: the material's base colour × COLOR_0; a base-colour texture (PNG/JPEG, embedded,
  data URI or beside the file) with its TEXCOORD set is kept for the renderer, its alpha as
  the material says: ignored (``OPAQUE``), a cut-out at ``alphaCutoff`` (``MASK``: VRoid's
  eyelashes and brows, hair cards) or blended (``BLEND``); a texture used by materials of
  different alpha modes is kept once per mode; a surface whose material alone hides it
  (``BLEND`` at alpha 0, ``MASK`` with a base alpha under its cutoff) keeps its vertices but
  no triangles (a note);
* each mesh's vertices are listed in ``avatar.parts`` under the mesh name; VRM files are
  handled by :mod:`facelab.stimuli.avatar.vrm` (presets, humanoid bones, VRM 0.x facing −z).

Landmarks, if the file was written by facelab, come from ``extras.facelab``: each one's rest
position and motion under the targets (``landmark_points``) finds its vertex again after a tool
reordered or quantized the vertices (:mod:`.landmark_points`); ``landmarks`` (indices) is the
fallback for older files.

Compressed and extended files (:data:`READ_EXTENSIONS`; glTF-Transform, VRoid Studio and
Blender exports): ``EXT_meshopt_compression`` buffer views and ``KHR_draco_mesh_compression``
primitives are decoded into plain accessors as the file is opened (``meshoptimizer``,
``DracoPy``), ``KHR_mesh_quantization`` attributes are read as the normalised or plain
integers they are, ``EXT_texture_webp`` images are decoded by Pillow, ``KHR_texture_transform``
moves the texture coordinates, and a ``KHR_texture_basisu`` (KTX2) texture, which nothing here
decodes, is left out with a note in ``avatar.source["notes"]`` (``facelab avatar inspect``
prints it). An extension the file lists in ``extensionsRequired`` and facelab does not read is
refused by name before anything else, with the command that re-exports the file without it.

Writing: one mesh, one primitive (POSITION, COLOR_0, indices, one POSITION target per
blendshape, ``targetNames`` in ``mesh.extras``), and, for an avatar with a skeleton, its
joints as nodes with a skin (JOINTS_0, WEIGHTS_0, inverse bind matrices) - as ``.glb`` or
``.gltf`` with an embedded base64 buffer. Textures are not written, except by
:func:`live_glb` (the live 3D/VR views' copy: one primitive per base-colour texture).
"""

from __future__ import annotations

import base64
import io
import json
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pygltflib

from facelab.errors import AvatarError
from facelab.stimuli.arkit import canonical_arkit_name
from facelab.stimuli.avatar.landmark_points import landmark_points, resolve_landmarks
from facelab.stimuli.avatar.mesh import Avatar
from facelab.stimuli.avatar.rig import Skeleton, match_roles
from facelab.stimuli.avatar.vrm import apply_vrm, detect_kind, humanoid_nodes

__all__ = ["accessor", "buffers_of", "live_glb", "open_gltf", "read_gltf", "write_gltf"]

COMPONENT_DTYPES = {
    5120: np.int8,
    5121: np.uint8,
    5122: np.int16,
    5123: np.uint16,
    5125: np.uint32,
    5126: np.float32,
}
#: the most values one accessor may hold (a 50k-vertex head with 52 targets reads ~8M)
MAX_VALUES = 2**27
TYPE_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


def open_gltf(path: Path) -> tuple[pygltflib.GLTF2, list[bytes]]:
    """The parsed document and the bytes of each of its buffers."""
    suffix = path.suffix.lower()
    if suffix not in (".gltf", ".glb", ".vrm"):
        raise AvatarError(f"{path}: expected a .gltf or .glb file (or .vrm)")
    if not path.is_file():
        what = "is a folder, not a file" if path.is_dir() else "file not found"
        raise AvatarError(f"{path}: {what}")
    raw = path.read_bytes()
    text = _glb_json(raw, path) if suffix in (".glb", ".vrm") else _gltf_json(raw, path)
    try:
        json.loads(text)  # parsed again by pygltflib: its own reading maps attributes too
    except ValueError as exc:
        raise AvatarError(
            f"{path}: its glTF JSON is not valid JSON (at character {getattr(exc, 'pos', '?')} "
            f"of {len(text)}; a truncated or damaged file?)"
        ) from None
    try:
        doc = (
            pygltflib.GLTF2.load_from_bytes(raw)
            if suffix in (".glb", ".vrm")
            else pygltflib.GLTF2.from_json(text)
        )
    except Exception:  # the dataclass mapping raises many kinds
        raise AvatarError(
            f"{path}: its JSON is not a glTF 2.0 document (expected the glTF top-level "
            "objects: asset, nodes, meshes, accessors, bufferViews, buffers)"
        ) from None
    version = str(getattr(doc.asset, "version", "") or "")
    if version.split(".")[0] != "2":
        raise AvatarError(f"{path}: glTF version {version!r}; expected 2.x")
    _check_required(doc, path)
    buffers = buffers_of(doc, path)
    try:
        buffers = _decode_meshopt(doc, buffers)
        _decode_draco(doc, buffers)
    except _MalformedError as exc:
        raise AvatarError(f"{path}: cannot read its compressed geometry: {exc}") from None
    except _MALFORMED:  # a damaged document: buffer views or extensions of the wrong shape
        raise AvatarError(
            f"{path}: malformed glTF: a buffer view, mesh primitive or compression extension "
            "refers to data that is not there or has the wrong shape (a damaged file?)"
        ) from None
    return doc, buffers


#: glTF extensions facelab reads (a file that *requires* another one is refused by name):
#: geometry compression and quantization are decoded into plain accessors on reading, WebP
#: textures are decoded by Pillow, texture transforms applied to the coordinates; material
#: extensions only refine how a surface looks, and the renderer draws base colour
READ_EXTENSIONS = {
    "KHR_mesh_quantization": "quantized attributes",
    "EXT_meshopt_compression": "meshopt-compressed buffers",
    "KHR_draco_mesh_compression": "Draco-compressed geometry",
    "EXT_texture_webp": "WebP textures",
    "KHR_texture_transform": "texture coordinate transforms",
    "KHR_materials_unlit": "unlit materials (drawn lit)",
    "KHR_materials_emissive_strength": "emissive strength (not drawn)",
    "KHR_materials_specular": "specular (not drawn)",
    "KHR_materials_ior": "index of refraction (not drawn)",
    "KHR_materials_clearcoat": "clear coat (not drawn)",
    "VRM": "VRM 0.x (expressions, humanoid bones; MToon drawn by its lit colour)",
    "VRMC_vrm": "VRM 1.0 (expressions, humanoid bones, look-at)",
    "VRMC_materials_mtoon": "MToon materials (drawn by their lit colour and texture)",
    "VRMC_springBone": "spring bones (left at rest)",
    "VRMC_node_constraint": "node constraints (left at rest)",
    "KHR_texture_basisu": "KTX2/Basis textures (not decoded: drawn without them)",
}


def _check_required(doc: pygltflib.GLTF2, path: Path) -> None:
    """An extension the file requires and facelab does not read is refused by name."""
    listed = doc.extensionsRequired or []
    if not isinstance(listed, list):
        raise AvatarError(f"{path}: malformed glTF: extensionsRequired is not a list of names")
    required = [str(e) for e in listed]
    unknown = [e for e in required if e not in READ_EXTENSIONS]
    if unknown:
        listed = ", ".join(unknown)
        raise AvatarError(
            f"{path}: needs {listed}, which facelab does not read; re-export without "
            f"{'it' if len(unknown) == 1 else 'them'}, e.g. `npx @gltf-transform/cli copy "
            f"{path.name} plain.glb` (it writes plain geometry and textures), or from the "
            "authoring tool without that option"
        )


def _new_buffer(doc: pygltflib.GLTF2, buffers: list[bytes], data: bytes) -> int:
    """``data`` (decoded geometry) as a buffer of its own; its index."""
    buffers.append(data)
    doc.buffers.append(pygltflib.Buffer(byteLength=len(data)))
    return len(buffers) - 1


def _new_view(doc: pygltflib.GLTF2, buffers: list[bytes], data: bytes) -> int:
    """A buffer view over ``data`` in a buffer of its own; its index."""
    buffer = _new_buffer(doc, buffers, data)
    doc.bufferViews.append(pygltflib.BufferView(buffer=buffer, byteOffset=0, byteLength=len(data)))
    return len(doc.bufferViews) - 1


def _decode_meshopt(doc: pygltflib.GLTF2, buffers: list[bytes]) -> list[bytes]:
    """Every ``EXT_meshopt_compression`` buffer view replaced by its decoded bytes (the
    extension's fallback buffer, which holds no data, is never read)."""
    buffers = list(buffers)
    for i, view in enumerate(doc.bufferViews or []):
        ext = (view.extensions or {}).get("EXT_meshopt_compression")
        if not ext:
            continue
        meshoptimizer = _decoder("meshoptimizer", "EXT_meshopt_compression")

        try:
            count, stride = int(ext["count"]), int(ext["byteStride"])
            start = int(ext.get("byteOffset", 0))
            data = buffers[int(ext["buffer"])][start : start + int(ext["byteLength"])]
            mode, flt = ext.get("mode", "ATTRIBUTES"), ext.get("filter", "NONE")
            # the binding's default output (float32 rows, count * stride bytes) and its uint32
            # indices (count * 4 >= count * stride bytes) are sized right; its dtype= path
            # allocates count elements only - never used here
            if mode == "ATTRIBUTES":
                if stride % 4 or not 0 < stride <= 256:
                    raise _MalformedError(f"buffer view {i}: meshopt stride {stride}")
                out = meshoptimizer.decode_vertex_buffer(count, stride, data)
            elif mode in ("TRIANGLES", "INDICES") and stride in (2, 4):
                decode_indices = (
                    meshoptimizer.decode_index_buffer
                    if mode == "TRIANGLES"
                    else meshoptimizer.decode_index_sequence
                )
                # 16-bit indices come back packed at the front of the 32-bit array
                packed = np.asarray(decode_indices(count, stride, data))
                out = packed.view(np.uint8)[: count * stride]
            else:
                raise _MalformedError(f"buffer view {i}: meshopt mode {mode!r}")
            if flt != "NONE":
                decode = {
                    "OCTAHEDRAL": meshoptimizer.decode_filter_oct,
                    "QUATERNION": meshoptimizer.decode_filter_quat,
                    "EXPONENTIAL": meshoptimizer.decode_filter_exp,
                }.get(flt)
                if decode is None:
                    raise _MalformedError(f"buffer view {i}: meshopt filter {flt!r}")
                out = decode(np.frombuffer(np.asarray(out).tobytes(), np.uint8), count, stride)
            raw = np.asarray(out).tobytes()
        except _MalformedError:
            raise
        except Exception:  # the decoder's own errors: a damaged stream
            raise _MalformedError(f"buffer view {i}: its meshopt data do not decode") from None
        if len(raw) != count * stride:
            raise _MalformedError(f"buffer view {i}: meshopt data decode to the wrong size")
        view.buffer, view.byteOffset, view.byteLength = _new_buffer(doc, buffers, raw), 0, len(raw)
        view.byteStride = stride if view.byteStride else None
        view.extensions = {}
    return buffers


def _decoder(module: str, extension: str) -> Any:
    """The decoder package an extension needs, or a worded refusal naming the install."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise _MalformedError(
            f"it uses {extension}, whose decoder ({module}) is not installed: "
            "pip install 'facelab[stimuli]'"
        ) from None


def _decode_draco(doc: pygltflib.GLTF2, buffers: list[bytes]) -> None:
    """Every ``KHR_draco_mesh_compression`` primitive's attributes and indices decoded into
    the accessors it names (float32 attributes, uint32 indices); morph targets are not
    compressed by that extension and are read as they are."""
    for m, mesh in enumerate(doc.meshes or []):
        for prim in mesh.primitives:
            ext = (prim.extensions or {}).get("KHR_draco_mesh_compression")
            if not ext:
                continue
            DracoPy = _decoder("DracoPy", "KHR_draco_mesh_compression")  # noqa: N806

            view = doc.bufferViews[int(ext["bufferView"])]
            start = view.byteOffset or 0
            try:
                decoded = DracoPy.decode(buffers[view.buffer][start : start + view.byteLength])
            except Exception:
                raise _MalformedError(f"mesh {m}: its Draco data do not decode") from None
            for name, unique_id in ext.get("attributes", {}).items():
                index = getattr(prim.attributes, name, None)
                attribute = decoded.get_attribute_by_unique_id(int(unique_id))
                if index is None or attribute is None:
                    raise _MalformedError(f"mesh {m}: Draco attribute {name} is missing")
                data = np.ascontiguousarray(np.asarray(attribute["data"]), np.float32)
                data = data.reshape(len(data), -1)
                acc = doc.accessors[index]
                if len(data) != acc.count:
                    raise _MalformedError(f"mesh {m}: Draco attribute {name} has {len(data)} "
                                          f"values, its accessor {acc.count}")  # fmt: skip
                acc.bufferView = _new_view(doc, buffers, data.tobytes())
                acc.byteOffset, acc.componentType, acc.normalized = 0, 5126, False
                acc.sparse = None
            if prim.indices is not None:
                faces = np.ascontiguousarray(np.asarray(decoded.faces), np.uint32).reshape(-1)
                acc = doc.accessors[prim.indices]
                acc.bufferView = _new_view(doc, buffers, faces.tobytes())
                acc.byteOffset, acc.componentType, acc.count = 0, 5125, len(faces)
            prim.extensions = {}


#: the first bytes of files people rename by mistake
_MAGIC = {
    b"\xff\xd8\xff": "a JPEG image",
    b"\x89PNG": "a PNG image",
    b"PK\x03\x04": "a ZIP archive (e.g. an .fbx/.vroid export bundle)",
    b"Kayd": "an FBX file",
    b"glTF": "a binary glTF (name it .glb)",
}


def _looks_like(raw: bytes) -> str:
    return next((what for magic, what in _MAGIC.items() if raw.startswith(magic)), "")


def _glb_json(raw: bytes, path: Path) -> str:
    """The JSON chunk of a binary glTF, after checking its 12-byte header and chunk header."""
    if raw[:4] != b"glTF":
        seen = _looks_like(raw)
        if not seen and raw.lstrip(b"\xef\xbb\xbf \t\r\n")[:1] == b"{":
            seen = "glTF JSON text, not binary (name it .gltf)"
        raise AvatarError(
            f"{path}: not a glTF 2.0 binary (.glb) file"
            + (f"; it is {seen}" if seen else "")  # (not the glTF magic: checked above)
        )
    if len(raw) < 20:
        raise AvatarError(f"{path}: truncated: {len(raw)} bytes, shorter than a .glb header")
    version, length = struct.unpack_from("<II", raw, 4)
    if version != 2:
        raise AvatarError(f"{path}: binary glTF version {version}; expected 2")
    if length > len(raw):
        raise AvatarError(
            f"{path}: truncated: its header says {length} bytes, the file has {len(raw)}"
        )
    chunk_length, chunk_type = struct.unpack_from("<II", raw, 12)
    if chunk_type != 0x4E4F534A:  # "JSON"
        raise AvatarError(f"{path}: damaged: the first chunk of a .glb must be its JSON")
    if 20 + chunk_length > len(raw):
        raise AvatarError(
            f"{path}: truncated: its JSON chunk needs {chunk_length} bytes, the file ends "
            f"{len(raw) - 20} bytes in"
        )
    try:
        return raw[20 : 20 + chunk_length].decode("utf-8")
    except UnicodeDecodeError:
        raise AvatarError(f"{path}: damaged: its JSON chunk is not UTF-8 text") from None


def _gltf_json(raw: bytes, path: Path) -> str:
    """The text of a .gltf file (JSON), or a refusal that says what the file is instead."""
    seen = _looks_like(raw)
    if seen:
        raise AvatarError(f"{path}: not a glTF JSON (.gltf) file; it is {seen}")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        raise AvatarError(
            f"{path}: not a glTF JSON (.gltf) file: it is not UTF-8 text (a binary file?)"
        ) from None


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
    """Accessor ``index`` as an array (count, width); normalised integers become [0, 1].

    Raises ValueError when the accessor is malformed: a count beyond :data:`MAX_VALUES`,
    data reaching outside its buffer view, sparse indices outside the count, or non-finite
    floats (NaN/inf positions would render as nothing, silently)."""
    acc = doc.accessors[index]
    dtype = np.dtype(COMPONENT_DTYPES[acc.componentType])
    width = TYPE_WIDTH[acc.type]
    count = acc.count
    if not isinstance(count, int) or count < 0 or count * width > MAX_VALUES:
        raise _MalformedError(f"accessor {index}: count {count!r} (at most {MAX_VALUES // width})")
    out = np.zeros((count, width), dtype=dtype)
    if acc.bufferView is not None:
        view = doc.bufferViews[acc.bufferView]
        data = buffers[view.buffer]
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        stride = view.byteStride or dtype.itemsize * width
        end = start + (count - 1) * stride + dtype.itemsize * width if count else start
        if min(start, stride) < 0 or end > (view.byteOffset or 0) + view.byteLength:
            raise _MalformedError(
                f"accessor {index}: its data reach outside buffer view {acc.bufferView}"
            )
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
        if idx.size and int(idx.max()) >= count:
            raise _MalformedError(
                f"accessor {index}: sparse index {int(idx.max())} >= count {count}"
            )
        out[idx] = vals
    if dtype.kind == "f" and not np.isfinite(out).all():
        raise _MalformedError(f"accessor {index}: holds non-finite values (NaN or infinity)")
    if acc.normalized and dtype.kind in "iu":  # glTF 2.0 §3.11: signed ones clamp at -1
        out = np.maximum(out.astype(np.float32) / np.iinfo(dtype).max, -1.0)
    return out


def node_matrix(node: pygltflib.Node) -> np.ndarray:
    """The node's local transform as a 4x4 matrix (column vectors)."""
    if node.matrix is not None:
        return _numbers(node.matrix, 16, "matrix").reshape(4, 4).T
    t = _numbers(node.translation if node.translation is not None else [0, 0, 0], 3, "translation")
    x, y, z, w = _numbers(
        node.rotation if node.rotation is not None else [0, 0, 0, 1], 4, "rotation"
    )
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    s = _numbers(node.scale if node.scale is not None else [1, 1, 1], 3, "scale")
    m = np.eye(4)
    m[:3, :3] = r * s
    m[:3, 3] = t
    return m


def _numbers(values: Any, count: int, what: str) -> np.ndarray:
    """``values`` as ``count`` finite floats, or a ValueError saying what they are instead."""
    try:
        out = np.array(values, dtype=float)
    except (TypeError, ValueError):
        raise _MalformedError(f"'{what}' is {values!r}; expected {count} numbers") from None
    if out.shape != (count,) or not np.isfinite(out).all():
        raise _MalformedError(f"'{what}' is {values!r}; expected {count} finite numbers")
    return out


def _extras(obj: Any) -> dict:
    extras = getattr(obj, "extras", None)
    return extras if isinstance(extras, dict) else {}


def _get(obj: Any, key: str) -> Any:
    """An attribute of a pygltflib object or a key of a plain dict (extensions are dicts)."""
    return obj.get(key) if isinstance(obj, dict) else getattr(obj, key, None)


def _image_bytes(doc: pygltflib.GLTF2, buffers: list[bytes], image: Any, path: Path) -> bytes:
    view = _get(image, "bufferView")
    if view is not None:
        bv = doc.bufferViews[view]
        start = bv.byteOffset or 0
        return buffers[bv.buffer][start : start + bv.byteLength]
    uri = _get(image, "uri") or ""
    if uri.startswith("data:"):
        return base64.b64decode(uri.split(",", 1)[1])
    ext = path.parent / uri
    if not ext.is_file():
        raise AvatarError(f"{path}: image {uri!r} is missing")
    return ext.read_bytes()


def _texture_source(texture: Any, notes: list[str]) -> int | None:
    """The image a texture shows: its own ``source``, or its ``EXT_texture_webp`` source; a
    texture only in ``KHR_texture_basisu`` (KTX2) has none here, and that is noted."""
    ext = _get(texture, "extensions") or {}
    webp = (ext.get("EXT_texture_webp") or {}).get("source")
    if webp is not None:
        return int(webp)
    if texture.source is not None:
        return int(texture.source)
    if "KHR_texture_basisu" in ext:
        notes.append(
            "a KTX2 (KHR_texture_basisu) texture is not decoded here: drawn without it (its "
            "material's base colour); re-export with PNG, JPEG or WebP textures to see it"
        )
    return None


def _transform_uv(uv: np.ndarray, transform: dict[str, Any]) -> np.ndarray:
    """Texture coordinates through ``KHR_texture_transform``: uv' = T(offset) R(rotation)
    S(scale) uv, with R = [[cos, -sin], [sin, cos]] as the extension's GLSL writes it."""
    offset = _numbers(transform.get("offset", [0.0, 0.0]), 2, "KHR_texture_transform offset")
    scale = _numbers(transform.get("scale", [1.0, 1.0]), 2, "KHR_texture_transform scale")
    (rotation,) = _numbers([transform.get("rotation", 0.0)], 1, "KHR_texture_transform rotation")
    c, s = np.cos(rotation), np.sin(rotation)
    m = np.array([[c, -s], [s, c]]) @ np.diag(scale)
    return (uv.astype(np.float64) @ m.T + offset).astype(np.float32)


def _decode_image(data: bytes, what: str) -> np.ndarray:
    """(H, W, 4) uint8 RGBA from PNG, JPEG or WebP bytes."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data)) as img:
            return np.asarray(img.convert("RGBA"), np.uint8).copy()
    except (UnidentifiedImageError, OSError):
        raise AvatarError(
            f"{what}: cannot decode the image (not a PNG, JPEG or WebP image, or damaged)"
        ) from None


#: told by ``avatar inspect`` when a file has MToon (VRM toon) materials
MTOON_NOTE = (
    "MToon materials drawn with their lit colour and texture (shade colour, rim and outline "
    "not drawn)"
)


def _alpha_cut(material: Any, factor_alpha: float) -> tuple[str, float]:
    """How a material's texture alpha is drawn: ``("OPAQUE", 1)`` ignores it, ``("MASK",
    cutoff)`` keeps texels whose alpha x the factor's alpha reaches the cutoff (glTF's
    default 0.5), ``("BLEND", factor)`` blends by it."""
    mode = str(_get(material, "alphaMode") or "OPAQUE").upper()
    if mode == "MASK":
        cutoff = _get(material, "alphaCutoff")
        return "MASK", float(0.5 if cutoff is None else cutoff) / max(float(factor_alpha), 1e-6)
    if mode == "BLEND":
        return "BLEND", float(factor_alpha)
    return "OPAQUE", 1.0


def _hidden_by_alpha(material: Any, base: list[float]) -> str | None:
    """The alpha mode by which a material's own alpha hides its surface whatever its
    texture says - blended at a factor alpha under half a grey level, or cut out at a cutoff
    the factor alpha never reaches (texels' alpha only lowers it) - or None."""
    alpha = float(base[3]) if len(base) > 3 else 1.0
    mode, value = _alpha_cut(material, alpha)
    hidden = (mode == "BLEND" and alpha < 0.5 / 255) or (mode == "MASK" and value > 1.0)
    return mode if hidden else None


def _with_alpha(rgba: np.ndarray, cut: tuple[str, float]) -> np.ndarray:
    """The texture as the renderer draws it: alpha 255 (opaque), 0/255 (masked: a cut-out
    such as eyelashes or a brow card) or the blended alpha."""
    mode, value = cut
    out = rgba.copy()
    if mode == "OPAQUE":
        out[..., 3] = 255
    elif mode == "MASK":
        out[..., 3] = np.where(rgba[..., 3] / 255.0 >= value, 255, 0)
    else:
        out[..., 3] = np.round(rgba[..., 3] * min(max(value, 0.0), 1.0)).astype(np.uint8)
    return out


class _Graph:
    """Node hierarchy of the default scene: parent and rest world matrix of every node."""

    def __init__(self, doc: pygltflib.GLTF2, path: Path):
        nodes = doc.nodes or []
        scenes = doc.scenes or []
        roots = scenes[doc.scene or 0].nodes if scenes else list(range(len(nodes)))
        self.parent: dict[int, int] = {}
        self.world: dict[int, np.ndarray] = {}
        self.order: list[int] = []  # parents before children
        stack = [(r, -1, np.eye(4)) for r in reversed(roots or [])]
        while stack:
            i, parent, above = stack.pop()
            if i in self.world:
                raise AvatarError(f"{path}: node {i} is reached twice (a cycle or shared child)")
            self.parent[i] = parent
            try:
                local = node_matrix(nodes[i])
            except ValueError as exc:
                raise _MalformedError(f"node {i}: {exc}") from None
            self.world[i] = above @ local
            self.order.append(i)
            for child in reversed(nodes[i].children or []):
                stack.append((child, i, self.world[i]))

    def nearest(self, node: int, among: dict[int, int]) -> int | None:
        """The value in ``among`` of ``node`` or its nearest ancestor that is a key there."""
        while node >= 0:
            if node in among:
                return among[node]
            node = self.parent.get(node, -1)
        return None


#: what reading a malformed file raises (a wrong type, a missing key, an index out of range,
#: an array of the wrong size) - any of these while reading is the file's fault, not facelab's
_MALFORMED = (KeyError, IndexError, ValueError, TypeError, AttributeError)


class _MalformedError(ValueError):
    """A problem of the file that facelab's reader found and put in words."""


def read_gltf(path: Path) -> Avatar:
    """An :class:`Avatar` from glTF 2.0 / VRM; see the module docstring for what is read.

    Raises :class:`AvatarError` naming the file and the problem for any malformed content
    (the glTF JSON, its accessors, node transforms, skins, VRM extensions)."""
    doc, buffers = open_gltf(path)
    try:
        return _avatar_of(doc, buffers, path)
    except _MalformedError as exc:
        raise AvatarError(f"{path}: malformed glTF: {exc}") from None
    except _MALFORMED:
        raise AvatarError(
            f"{path}: malformed glTF: an accessor, buffer view, node, skin or VRM extension "
            "refers to data that is not there or has the wrong shape (a damaged or truncated "
            "file, or one that needs an extension facelab does not read)"
        ) from None


def _avatar_of(doc: pygltflib.GLTF2, buffers: list[bytes], path: Path) -> Avatar:
    graph = _Graph(doc, path)
    nodes = doc.nodes or []
    kind = detect_kind(doc)
    # the joints: every skin's joints plus the humanoid head/neck/eye nodes, parents first
    joint_nodes = {j for sk in doc.skins or [] for j in (sk.joints or [])}
    roles_by_node = humanoid_nodes(doc) if kind.startswith("vrm") else {}
    joint_nodes |= set(roles_by_node.values())
    joint_nodes &= set(graph.world)
    ordered = [n for n in graph.order if n in joint_nodes]
    joint_index = {n: i for i, n in enumerate(ordered)}
    placed = [i for i in graph.order if nodes[i].mesh is not None]
    if not placed:
        raise AvatarError(f"{path}: no mesh in the scene")
    positions, faces, colors, uvs, face_tex, skins_j, skins_w, per_target = ([] for _ in range(8))
    raw_targets: dict[tuple[int, int], list[tuple[int, np.ndarray]]] = {}
    textures: list[np.ndarray] = []
    texture_of_image: dict[tuple[int, tuple[str, float]], int] = {}
    images: dict[int, np.ndarray] = {}  # decoded once, however many materials use them
    notes: list[str] = []  # what was read only in part (told by avatar inspect)
    landmarks: dict[str, int] = {}
    landmark_at: dict[str, Any] = {}  # extras.facelab.landmark_points (see .landmark_points)
    mesh_names: list[str] = []
    parts: dict[str, np.ndarray] = {}
    offset = 0
    for node_index in placed:
        node = nodes[node_index]
        mesh = doc.meshes[node.mesh]
        mesh_names.append(mesh.name or f"mesh_{node.mesh}")
        names = _extras(mesh).get("targetNames", [])
        facelab = _extras(mesh).get("facelab", {})
        defaults = [(names[k] if k < len(names) else f"target_{k}", w)
                    for k, w in enumerate(_get(mesh, "weights") or [])
                    if isinstance(w, int | float) and w]  # fmt: skip
        if defaults:  # glTF viewers start from them; facelab's rest face is every shape at 0
            said = ", ".join(f"{n} {w:g}" for n, w in defaults[:4])
            notes.append(f"mesh {mesh.name or node.mesh!r}: its default morph weights ({said}"
                         f"{', …' if len(defaults) > 4 else ''}) are not applied: facelab's rest "
                         "face has every shape at 0, as the methods drive them")  # fmt: skip
        skin = doc.skins[node.skin] if node.skin is not None else None
        if skin is not None:
            ibm = (
                accessor(doc, buffers, skin.inverseBindMatrices)
                .astype(np.float64)
                .reshape(-1, 4, 4)
                .transpose(0, 2, 1)
                if skin.inverseBindMatrices is not None
                else np.tile(np.eye(4), (len(skin.joints), 1, 1))
            )
            rest = np.stack([graph.world[j] @ m for j, m in zip(skin.joints, ibm, strict=True)])
            to_global = np.array([joint_index[j] for j in skin.joints], np.int64)
        rigid = graph.nearest(node_index, joint_index)
        for prim in mesh.primitives:
            if (prim.mode if prim.mode is not None else 4) != 4:
                continue  # points and lines are not surfaces
            attrs = prim.attributes
            if attrs.POSITION is None:
                raise _MalformedError("a primitive has no POSITION attribute")
            pos = accessor(doc, buffers, attrs.POSITION).astype(np.float64)
            n = len(pos)
            if skin is not None and attrs.JOINTS_0 is not None and attrs.WEIGHTS_0 is not None:
                local_j = accessor(doc, buffers, attrs.JOINTS_0).astype(np.int64)
                w = accessor(doc, buffers, attrs.WEIGHTS_0).astype(np.float64)
                total = w.sum(axis=1, keepdims=True)
                w = np.where(total > 0, w / np.maximum(total, 1e-12), 0.0)
                blend = np.einsum("vk,vkij->vij", w, rest[local_j])  # (n, 4, 4)
                if np.allclose(blend, np.eye(4), rtol=0, atol=1e-6):  # bound at rest: keep exact
                    blend = np.broadcast_to(np.eye(4), blend.shape)
                lin = blend[:, :3, :3]
                pos_w = np.einsum("vij,vj->vi", lin, pos) + blend[:, :3, 3]
                joints_v = to_global[local_j]
                weights_v = w
            else:
                world = graph.world[node_index]
                lin = np.broadcast_to(world[:3, :3], (n, 3, 3))
                pos_w = pos @ world[:3, :3].T + world[:3, 3]
                joints_v = np.zeros((n, 4), np.int64)
                weights_v = np.zeros((n, 4))
                if rigid is not None:
                    joints_v[:, 0] = rigid
                    weights_v[:, 0] = 1.0
            idx = (
                accessor(doc, buffers, prim.indices).reshape(-1)
                if prim.indices is not None
                else np.arange(n)
            ).astype(np.int64)
            base = [1.0, 1.0, 1.0, 1.0]
            tex_index, tex_coord, transform = -1, 0, None
            if prim.material is not None:
                mat = doc.materials[prim.material]
                pbr = mat.pbrMetallicRoughness
                if pbr is not None and pbr.baseColorFactor is not None:
                    base = list(pbr.baseColorFactor)
                if _get(mat, "extensions") and "VRMC_materials_mtoon" in mat.extensions:
                    notes.append(MTOON_NOTE)
                if mode := _hidden_by_alpha(mat, base):  # as every glTF viewer: not drawn
                    notes.append(f"mesh {mesh.name or node.mesh!r}, material "
                                 f"{mat.name or prim.material!r}: fully transparent ({mode}, "
                                 f"alpha {base[-1]:g}): not drawn")  # fmt: skip
                    idx = idx[:0]
                info = _get(pbr, "baseColorTexture") if pbr is not None else None
                if info is not None and _get(info, "index") is not None:
                    source = _texture_source(doc.textures[_get(info, "index")], notes)
                    tex_coord = _get(info, "texCoord") or 0
                    transform = (_get(info, "extensions") or {}).get("KHR_texture_transform")
                    if transform:
                        tex_coord = transform.get("texCoord", tex_coord)
                    if source is not None:
                        cut = _alpha_cut(mat, base[3] if len(base) > 3 else 1.0)
                        if source not in images:
                            images[source] = _decode_image(
                                _image_bytes(doc, buffers, doc.images[source], path),
                                f"{path}: image {source}",
                            )
                        if (source, cut) not in texture_of_image:
                            texture_of_image[source, cut] = len(textures)
                            textures.append(_with_alpha(images[source], cut))
                        tex_index = texture_of_image[source, cut]
            elif attrs.COLOR_0 is None:
                base = [0.8, 0.7, 0.65, 1.0]
            col = np.tile(np.array(base[:3], np.float32), (n, 1))
            if attrs.COLOR_0 is not None:
                col = col * accessor(doc, buffers, attrs.COLOR_0).astype(np.float32)[:, :3]
            uv_attr = attrs.TEXCOORD_1 if tex_coord == 1 else attrs.TEXCOORD_0
            uv = (
                accessor(doc, buffers, uv_attr).astype(np.float32)
                if uv_attr is not None
                else np.zeros((n, 2), np.float32)
            )
            if tex_index >= 0 and uv_attr is None:
                tex_index = -1  # a texture without coordinates cannot be mapped
            if tex_index >= 0 and transform:
                uv = _transform_uv(uv, transform)
            targets, raw_of = {}, {}
            prim_names = _extras(prim).get("targetNames", names)
            for k, tgt in enumerate(prim.targets or []):
                position = _get(tgt, "POSITION")
                if position is None:
                    continue
                raw_name = prim_names[k] if k < len(prim_names) else f"target_{k}"
                try:
                    moved = accessor(doc, buffers, position).astype(np.float64)
                except _MalformedError as exc:  # name the shape, not only its accessor
                    raise _MalformedError(f"mesh {mesh.name or node.mesh!r}, morph target "
                                          f"{raw_name!r} ({k}): {exc}") from None  # fmt: skip
                delta = np.einsum("vij,vj->vi", lin, moved)
                raw_targets.setdefault((node.mesh, k), []).append((offset, delta))
                name = canonical_arkit_name(raw_name) or raw_name
                if name in targets:  # the later one would silently replace the earlier
                    first = raw_of[name]
                    if first[1] == raw_name:
                        raise AvatarError(
                            f"{path}: mesh {mesh.name or node.mesh!r} has two morph targets "
                            f"named {raw_name!r} (targets {first[0]} and {k}): rename one in "
                            "the modelling tool and export again"
                        )
                    keep = (k, raw_name) if raw_name == name else first  # the exact spelling
                    where = mesh.name or node.mesh
                    notes.append(f"mesh {where!r}: targets {first[1]!r} and {raw_name!r} both "
                                 f"mean {name!r}; {keep[1]!r} is used")  # fmt: skip
                    if keep == first:
                        continue
                targets[name], raw_of[name] = delta, (k, raw_name)
            positions.append(pos_w)
            faces.append(idx.reshape(-1, 3) + offset)
            colors.append(col)
            uvs.append(uv)
            face_tex.append(np.full(len(idx) // 3, tex_index, np.int64))
            skins_j.append(joints_v)
            skins_w.append(weights_v)
            per_target.append((offset, n, targets))
            part = mesh.name or f"mesh_{node.mesh}"
            parts[part] = np.concatenate(
                [parts.get(part, np.zeros(0, np.int64)), offset + np.arange(n)]
            )
            for key, value in facelab.get("landmarks", {}).items():
                landmarks[key] = int(value) + offset
            if isinstance(facelab.get("landmark_points"), dict):
                landmark_at.update(facelab["landmark_points"])
            offset += n
    vrm0 = (doc.extensions or {}).get("VRM")
    if isinstance(vrm0, dict) and any(
        isinstance(m, dict) and "MToon" in str(m.get("shader", ""))
        for m in vrm0.get("materialProperties") or []
    ):
        notes.append(MTOON_NOTE)
    if not positions:
        raise AvatarError(f"{path}: no triangle primitives")
    if not any(len(f) for f in faces):
        raise AvatarError(f"{path}: every surface is fully transparent (its materials' alpha): "
                          "nothing to draw")  # fmt: skip
    verts = np.vstack(positions)
    all_names = sorted({name for _, _, t in per_target for name in t})
    merged = {name: np.zeros_like(verts) for name in all_names}
    for start, n, t in per_target:
        for name, delta in t.items():
            merged[name][start : start + n] = delta
    skeleton = None
    if ordered:
        above = [graph.nearest(graph.parent[n], joint_index) for n in ordered]
        parents = np.array([-1 if p is None else p for p in above], np.int64)
        names_j = tuple(nodes[n].name or f"joint_{n}" for n in ordered)
        roles = {r: joint_index[n] for r, n in roles_by_node.items() if n in joint_index}
        for role, j in match_roles(names_j).items():
            roles.setdefault(role, j)
        skeleton = Skeleton(
            names_j,
            parents,
            np.array([graph.world[n][:3, 3] for n in ordered]),
            np.vstack(skins_j),
            np.vstack(skins_w),
            roles,
        )
    face_texture = np.concatenate(face_tex)
    landmarks, landmark_notes = resolve_landmarks(
        points=landmark_at, indices=landmarks, neutral=verts, targets=merged
    )
    notes += landmark_notes
    avatar = Avatar(
        verts,
        np.vstack(faces),
        {k: v.astype(np.float32) for k, v in merged.items()},
        landmarks,
        np.vstack(colors),
        name=path.stem,
        parts=parts,
        skeleton=skeleton,
        uv=np.vstack(uvs) if textures else None,
        # RGB, or RGBA where the material lets something through (cut-outs, blending)
        textures=tuple(t if (t[..., 3] < 255).any() else t[..., :3].copy() for t in textures),
        face_texture=face_texture if textures else None,
        source={
            "kind": kind,
            "file": path.name,
            "meshes": mesh_names,
            **({"notes": sorted(set(notes))} if notes else {}),
        },
    )
    return apply_vrm(avatar, doc, raw_targets) if kind.startswith("vrm") else avatar


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

    def add_bytes(self, data: bytes) -> int:
        """A 4-byte aligned buffer view of raw bytes (an image); returns the view index."""
        pad = (-self.size) % 4
        if pad:
            self.blobs.append(b"\x00" * pad)
            self.size += pad
        self.views.append(
            pygltflib.BufferView(buffer=0, byteOffset=self.size, byteLength=len(data))
        )
        self.blobs.append(data)
        self.size += len(data)
        return len(self.views) - 1

    def buffer(self) -> bytes:
        data = b"".join(self.blobs)
        return data + b"\x00" * ((-len(data)) % 4)


def write_gltf(avatar: Avatar, path: Path) -> None:
    suffix = path.suffix.lower()
    if suffix not in (".glb", ".gltf"):
        raise AvatarError(f"{path}: expected a .glb or .gltf file name")
    doc, buffer = _gltf_document(avatar)
    if suffix == ".gltf":
        doc.buffers[0].uri = (
            "data:application/octet-stream;base64," + base64.b64encode(buffer).decode()
        )
        path.write_text(doc.gltf_to_json(), encoding="utf-8")
        return
    doc.set_binary_blob(buffer)
    path.write_bytes(b"".join(doc.save_to_bytes()))


def live_glb(avatar: Avatar) -> bytes:
    """The avatar as the live browser and VR views draw it (``facelab serve`` with
    ``display: live3d | webxr``): exactly the geometry, targets (named as the animation
    tracks' channels) and skeleton the offline renderer deforms, with the vertex colours in
    linear light as the offline shading uses them (squared), and the skeleton's roles
    (``neck``, ``head``, ``eye_left``, ``eye_right`` -> joint name) in the mesh's
    ``extras.facelab.roles`` so a track's head and eye channels turn the same joints."""
    doc, buffer = _gltf_document(avatar, live=True)
    doc.set_binary_blob(buffer)
    return b"".join(doc.save_to_bytes())


def _gltf_document(avatar: Avatar, *, live: bool = False) -> tuple[pygltflib.GLTF2, bytes]:
    """The glTF document of ``avatar`` and its one binary buffer; ``live``: the live views'
    copy (:func:`live_glb`: linear colours, the skeleton's roles, textures)."""
    b = _BufferBuilder()
    pos = b.add(avatar.neutral.astype(np.float32), "VEC3", 5126, 34962, True)
    colors = avatar.colors if avatar.colors is not None else np.full((len(avatar.neutral), 3), 0.8)
    colors = np.asarray(colors, np.float32) ** 2 if live else colors
    col = b.add(np.asarray(colors, np.float32), "VEC3", 5126, 34962, False)
    # one primitive per base-colour texture (the live view draws textured avatars as the
    # offline renderer does: texture x lit vertex colour); every primitive shares the vertex
    # data and targets. write_gltf keeps its one untextured primitive.
    face_tex = (
        avatar.face_texture
        if live and avatar.face_texture is not None and avatar.uv is not None
        else np.full(len(avatar.faces), -1)
    )
    groups = [
        (int(t), b.add(avatar.faces[face_tex == t].astype(np.uint32).reshape(-1), "SCALAR",
                       5125, 34963, False))
        for t in np.unique(face_tex)
    ]  # fmt: skip
    names = list(avatar.target_names)
    targets = [
        {"POSITION": b.add(avatar.targets[n].astype(np.float32), "VEC3", 5126, 34962, True)}
        for n in names
    ]
    attributes = pygltflib.Attributes(POSITION=pos, COLOR_0=col)
    textured = [t for t, _ in groups if t >= 0]
    if textured:
        attributes.TEXCOORD_0 = b.add(avatar.uv.astype(np.float32), "VEC2", 5126, 34962, False)
    images = [pygltflib.Image(bufferView=b.add_bytes(_png(avatar.textures[t])),
                              mimeType="image/png") for t in textured]  # fmt: skip
    nodes = [pygltflib.Node(mesh=0, name=avatar.name)]
    skins = []
    sk = avatar.skeleton
    if sk is not None:
        # joints as nodes 1..J (rest rotation identity, translated to their pivots); the
        # inverse bind matrix of a joint is then a translation by minus its pivot
        attributes.JOINTS_0 = b.add(sk.joints.astype(np.uint16), "VEC4", 5123, 34962, False)
        attributes.WEIGHTS_0 = b.add(sk.weights.astype(np.float32), "VEC4", 5126, 34962, False)
        ibm = np.tile(np.eye(4, dtype=np.float32), (len(sk.names), 1, 1))
        ibm[:, :3, 3] = -sk.pivots
        ibm_acc = b.add(ibm.transpose(0, 2, 1).reshape(-1, 16), "MAT4", 5126, None, False)
        for j, name in enumerate(sk.names):
            parent = sk.parents[j]
            offset = sk.pivots[j] - (sk.pivots[parent] if parent >= 0 else 0.0)
            children = [int(c) + 1 for c in np.nonzero(sk.parents == j)[0]]
            nodes.append(
                pygltflib.Node(name=name, translation=offset.tolist(), children=children or None)
            )
        nodes[0].skin = 0
        roots = [j + 1 for j in range(len(sk.names)) if sk.parents[j] < 0]
        skins = [
            pygltflib.Skin(joints=list(range(1, len(sk.names) + 1)), inverseBindMatrices=ibm_acc)
        ]
    else:
        roots = []
    buffer = b.buffer()
    facelab_extras: dict[str, Any] = {
        "landmarks": avatar.landmarks,
        "landmark_points": landmark_points(
            neutral=avatar.neutral, targets=avatar.targets, landmarks=avatar.landmarks
        ),
    }
    if live and sk is not None:
        facelab_extras["roles"] = {role: sk.names[j] for role, j in sk.roles.items()}
    doc = pygltflib.GLTF2(
        asset=pygltflib.Asset(version="2.0", generator="facelab"),
        scene=0,
        scenes=[pygltflib.Scene(nodes=[0, *roots])],
        nodes=nodes,
        skins=skins,
        meshes=[
            pygltflib.Mesh(
                name=avatar.name,
                primitives=[
                    pygltflib.Primitive(
                        attributes=attributes,
                        indices=idx,
                        mode=4,
                        targets=targets,
                        material=0 if t < 0 else 1 + textured.index(t),
                    )
                    for t, idx in groups
                ],
                weights=[0.0] * len(names),
                extras={"targetNames": names, "facelab": facelab_extras},
            )
        ],
        materials=[
            pygltflib.Material(
                pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
                    baseColorFactor=[1, 1, 1, 1], metallicFactor=0.0, roughnessFactor=0.8
                ),
                doubleSided=True,
            ),
            *(
                pygltflib.Material(
                    pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
                        baseColorTexture=pygltflib.TextureInfo(index=k),
                        metallicFactor=0.0,
                        roughnessFactor=0.8,
                    ),
                    doubleSided=True,
                    alphaMode="BLEND" if avatar.textures[t].shape[2] == 4 else "OPAQUE",
                )
                for k, t in enumerate(textured)
            ),
        ],
        **(
            {
                "textures": [pygltflib.Texture(source=k, sampler=0) for k in range(len(textured))],
                "images": images,
                "samplers": [pygltflib.Sampler(magFilter=9729, minFilter=9987)],
            }
            if textured
            else {}
        ),
        accessors=b.accessors,
        bufferViews=b.views,
        buffers=[pygltflib.Buffer(byteLength=len(buffer))],
    )
    return doc, buffer


def _png(image: np.ndarray) -> bytes:
    """An (H, W, 3|4) uint8 image as PNG bytes."""
    from PIL import Image as PILImage

    out = io.BytesIO()
    PILImage.fromarray(np.asarray(image, np.uint8)).save(out, format="PNG")
    return out.getvalue()
