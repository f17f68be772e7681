"""Small avatar files in the formats users bring, written by code (tests and benchmarks).

:func:`write_sample` writes a stand-in for what Ready Player Me, VRoid (VRM 0.x / 1.0) and
generic skinned exporters produce, built the way those files are built - not with facelab's
own writer: a humanoid skeleton (Hips, Spine, Neck, Head, LeftEye, RightEye) with rest
rotations and inverse bind matrices, a full-body scale (the head 1.6 m up, a torso below it),
several meshes (head, teeth, two eyes, torso; a rigid hat parented to the head joint in the
generic file) each skinned to the skeleton, morph targets repeated by name on every mesh they
move (``jawOpen`` on the head and the teeth), a base-colour texture on the head (hair above,
skin below) and vertex colours on the teeth. Per kind:

* ``skinned`` - ARKit names on the meshes, Mixamo-style joint names (``mixamorig:Neck``);
* ``rpm`` - Ready Player Me names: meshes ``Wolf3D_Head``, ``Wolf3D_Teeth``, ``EyeLeft``,
  ``EyeRight``; all 52 ARKit targets and the 15 ``viseme_*`` targets;
* ``vrm0`` - VRoid's raw names (``Fcl_MTH_A`` …) with ``extensions.VRM`` blend-shape groups
  (presets a i u e o blink joy) and humanoid bones; facing −z, as VRM 0.x models do;
* ``vrm1`` - the same in ``extensions.VRMC_vrm`` (presets aa ih ou ee oh blinkLeft
  blinkRight happy); facing +z.

``vroid=True`` (``vrm0``/``vrm1``) lays the face out as VRoid Studio / UniVRM export it: the
``Face`` mesh is several primitives with their own vertices (skin, hair cap, eyelash cards),
its morph targets are stored as sparse accessors (only the vertices a shape moves; an
all-zero target as an accessor without data), the materials are MToon (VRM 0.x
``materialProperties`` with shader ``VRM/MToon``; VRM 1.0 ``VRMC_materials_mtoon``) with
their glTF fallback, the eyelashes an alpha-masked (``MASK``) cut-out, and every texture a
region of one atlas picked by ``KHR_texture_transform`` (the atlas's fourth region is
magenta: a reader that ignores the transform shows it).

The geometry is simple (an ellipsoid head with a mouth region): these files test loading,
names, skinning and framing, not looks. ``head_rows`` sets the mesh density (about
``2 * head_rows**2`` head vertices; 160 gives ~51k vertices in all).
"""

from __future__ import annotations

import base64
import io
from pathlib import Path

import numpy as np
import pygltflib

from facelab.errors import AvatarError
from facelab.stimuli.arkit import ARKIT_NAMES, VISEME_TARGETS
from facelab.stimuli.avatar.gltf import _BufferBuilder

__all__ = ["HEAD_JOINT_Y", "KINDS", "write_sample"]

KINDS = ("skinned", "rpm", "vrm0", "vrm1")
HEAD_JOINT_Y = 1.58
HEAD_CENTRE = np.array([0.0, 1.67, 0.0])
HEAD_RADII = np.array([0.075, 0.11, 0.09])
MOUTH_Y = 1.615
EYE_X, EYE_Y, EYE_R = 0.031, 1.69, 0.011

# joint: (parent, world position, rest rotation about z in degrees - non-trivial on purpose)
_JOINTS = {
    "Hips": (None, (0.0, 1.0, 0.0), 0.0),
    "Spine": ("Hips", (0.0, 1.3, 0.0), 0.0),
    "Neck": ("Spine", (0.0, 1.5, -0.01), 15.0),
    "Head": ("Neck", (0.0, HEAD_JOINT_Y, 0.0), -25.0),
    "LeftEye": ("Head", (EYE_X, EYE_Y, 0.07), 0.0),
    "RightEye": ("Head", (-EYE_X, EYE_Y, 0.07), 0.0),
}
_VRM0_RAW = {"a": "Fcl_MTH_A", "i": "Fcl_MTH_I", "u": "Fcl_MTH_U", "e": "Fcl_MTH_E",
             "o": "Fcl_MTH_O", "blink": "Fcl_EYE_Close", "joy": "Fcl_ALL_Joy"}  # fmt: skip
_VRM1_PRESETS = {"aa": "a", "ih": "i", "ou": "u", "ee": "e", "oh": "o",
                 "blinkLeft": "blink_l", "blinkRight": "blink_r", "happy": "joy"}  # fmt: skip


def _rot_z(deg: float) -> np.ndarray:
    a = np.radians(deg)
    m = np.eye(4)
    m[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return m


def _world_matrices() -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for name, (_, pos, rot) in _JOINTS.items():
        m = _rot_z(rot)
        m[:3, 3] = pos
        out[name] = m
    return out


def _ellipsoid(centre: np.ndarray, radii: np.ndarray, rows: int, cols: int):
    phi = np.linspace(-np.pi / 2 + 1e-3, np.pi / 2 - 1e-3, rows)
    theta = np.linspace(-np.pi, np.pi, cols, endpoint=False)
    p, t = np.meshgrid(phi, theta, indexing="ij")
    unit = np.stack([np.cos(p) * np.sin(t), np.sin(p), np.cos(p) * np.cos(t)], -1).reshape(-1, 3)
    r, c = np.meshgrid(np.arange(rows - 1), np.arange(cols), indexing="ij")
    a, b = r * cols + c, r * cols + (c + 1) % cols
    d, e = a + cols, b + cols
    faces = np.concatenate(
        [np.stack([a, b, d], -1).reshape(-1, 3), np.stack([b, e, d], -1).reshape(-1, 3)]
    )
    uv = np.stack([(t.ravel() + np.pi) / (2 * np.pi), 0.5 - p.ravel() / np.pi], -1)
    return centre + unit * radii, faces, uv


def _bump(v: np.ndarray, centre: tuple[float, float, float], sigma: float) -> np.ndarray:
    return np.exp(-0.5 * np.sum((v - np.asarray(centre)) ** 2, axis=1) / sigma**2)


def _head_targets(v: np.ndarray) -> dict[str, np.ndarray]:
    """Semantic displacement fields (m) for the shapes the tests look at; the rest small."""
    front = (v[:, 2] > 0.02).astype(float)
    below = (v[:, 1] < MOUTH_Y).astype(float) * front
    mouth = _bump(v, (0.0, MOUTH_Y, 0.09), 0.02)
    t: dict[str, np.ndarray] = {}
    t["jawOpen"] = np.outer(below * _bump(v, (0.0, 1.59, 0.07), 0.04), [0.0, -0.012, -0.002])
    for side, sgn in (("Left", 1.0), ("Right", -1.0)):
        corner = _bump(v, (sgn * 0.022, MOUTH_Y, 0.085), 0.01)
        t[f"mouthSmile{side}"] = np.outer(corner, [sgn * 0.004, 0.006, -0.002])
        lid = _bump(v, (sgn * EYE_X, EYE_Y + 0.008, 0.08), 0.008) * front
        t[f"eyeBlink{side}"] = np.outer(lid, [0.0, -0.009, 0.0])
    t["mouthFunnel"] = np.outer(mouth, [0.0, 0.0, 0.006])
    t["mouthPucker"] = np.outer(mouth, [0.0, 0.0, 0.008])
    t["mouthStretchLeft"] = np.outer(_bump(v, (0.022, MOUTH_Y, 0.085), 0.01), [0.006, 0, 0])
    t["mouthStretchRight"] = np.outer(_bump(v, (-0.022, MOUTH_Y, 0.085), 0.01), [-0.006, 0, 0])
    rng = np.random.default_rng(0)
    for name in ARKIT_NAMES:
        if name not in t:
            centre = (rng.uniform(-0.04, 0.04), rng.uniform(1.6, 1.72), 0.08)
            t[name] = np.outer(_bump(v, centre, 0.012) * front, rng.normal(0, 0.002, 3))
    vowels = {"aa": 1.0, "E": 0.5, "ih": 0.3, "oh": 0.6, "ou": 0.2}
    for name in VISEME_TARGETS:
        key = name.removeprefix("viseme_")
        if key in vowels:
            t[name] = t["jawOpen"] * vowels[key] + (
                t["mouthPucker"] * 0.8 if key in ("oh", "ou") else 0.0
            )
        else:
            t[name] = (
                t["jawOpen"] * 0.1 + t["mouthStretchLeft"] * 0.2 + t["mouthStretchRight"] * 0.2
            )
    return t


def _png(rgb_top: tuple[int, int, int], rgb_bottom: tuple[int, int, int], size: int = 32) -> bytes:
    """A PNG texture: the top half one colour, the bottom half another."""
    from PIL import Image

    image = Image.new("RGB", (size, size), rgb_top)
    image.paste(rgb_bottom, (0, size // 2, size, size))
    out = io.BytesIO()
    image.save(out, format="PNG")
    return out.getvalue()


#: texture colours: hair above, skin below (sRGB 0-255)
HAIR_RGB, SKIN_RGB = (70, 40, 25), (225, 180, 150)


#: the VRoid layout's atlas (64 x 64): hair (top left), skin (top right), eyelashes - black
#: strands on alpha 0 (bottom left), magenta (bottom right, never meant to show); each
#: material's KHR_texture_transform (offset, scale) picks its region
ATLAS_REGIONS = {"hair": (0.0, 0.0), "skin": (0.5, 0.0), "lashes": (0.0, 0.5)}
MAGENTA = (255, 0, 255)


def _atlas_png(size: int = 64) -> bytes:
    from PIL import Image

    half = size // 2
    rgba = np.zeros((size, size, 4), np.uint8)
    rgba[:half, :half] = (*HAIR_RGB, 255)
    rgba[:half, half:] = (*SKIN_RGB, 255)
    rgba[half:, half:] = (*MAGENTA, 255)
    strands = (np.arange(half) // 2) % 2 == 0  # two-texel strands, two-texel gaps
    rgba[half:, :half, :3] = 20
    rgba[half:, :half, 3] = np.where(strands[None, :], 255, 0)
    out = io.BytesIO()
    Image.fromarray(rgba).save(out, format="PNG")
    return out.getvalue()


def _sparse_target(b: _BufferBuilder, delta: np.ndarray) -> int:
    """A POSITION morph target as VRoid writes it: a sparse accessor holding only the moved
    vertices, or (nothing moves) an accessor without data, which reads as zeros."""
    moved = np.nonzero(np.abs(delta).max(axis=1) > 1e-9)[0]
    bounds = {"min": delta.min(axis=0).tolist(), "max": delta.max(axis=0).tolist()}
    if len(moved) == 0:
        b.accessors.append(
            pygltflib.Accessor(componentType=5126, count=len(delta), type="VEC3", **bounds)
        )
        return len(b.accessors) - 1
    indices = b.add_bytes(moved.astype(np.uint32).tobytes())
    values = b.add_bytes(delta[moved].astype(np.float32).tobytes())
    b.accessors.append(
        pygltflib.Accessor(
            componentType=5126,
            count=len(delta),
            type="VEC3",
            sparse=pygltflib.Sparse(
                count=len(moved),
                indices=pygltflib.AccessorSparseIndices(bufferView=indices, componentType=5125),
                values=pygltflib.AccessorSparseValues(bufferView=values),
            ),
            **bounds,
        )
    )
    return len(b.accessors) - 1


def _lash_cards() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two eyelash cards (quads in front of the upper lids): vertices, faces, uv."""
    verts, faces, uv = [], [], []
    for sgn in (1.0, -1.0):
        x0, x1 = sgn * EYE_X - 0.014, sgn * EYE_X + 0.014
        y0, y1, z = EYE_Y + 0.006, EYE_Y + 0.013, 0.084
        k = len(verts)
        verts += [(x0, y0, z), (x1, y0, z), (x1, y1, z), (x0, y1, z)]
        uv += [(0, 1), (1, 1), (1, 0), (0, 0)]
        faces += [(k, k + 1, k + 2), (k, k + 2, k + 3)]
    return np.array(verts), np.array(faces), np.array(uv, float)


def write_sample(path: Path | str, *, kind: str, head_rows: int = 40, vroid: bool = False) -> Path:
    """Write a sample avatar of ``kind`` (see the module docstring) to ``path`` (.glb, .gltf or
    .vrm); return the path. ``vroid`` (VRM kinds only): VRoid Studio's layout."""
    if kind not in KINDS:
        raise AvatarError(f"unknown sample kind {kind!r}; expected one of {', '.join(KINDS)}")
    if vroid and not kind.startswith("vrm"):
        raise AvatarError(f"vroid=True is for the VRM kinds, not {kind!r}")
    path = Path(path)
    worlds = _world_matrices()
    joint_names = list(_JOINTS)
    b = _BufferBuilder()
    # --- geometry (world rest pose, facing +z) ---------------------------------------------
    hv, hf, huv = _ellipsoid(HEAD_CENTRE, HEAD_RADII, head_rows, 2 * head_rows)
    head_w = np.clip((hv[:, 1] - 1.54) / 0.06, 0, 1)
    head_j = np.tile([joint_names.index("Head"), joint_names.index("Neck"), 0, 0], (len(hv), 1))
    head_wt = np.stack([head_w, 1 - head_w, 0 * head_w, 0 * head_w], -1)
    tv, tf, _ = _ellipsoid(np.array([0.0, MOUTH_Y, 0.07]), np.array([0.02, 0.006, 0.008]), 6, 12)
    teeth_j = np.tile([joint_names.index("Head"), 0, 0, 0], (len(tv), 1))
    teeth_wt = np.tile([1.0, 0, 0, 0], (len(tv), 1))
    eyes = {}
    for side, sgn in (("Left", 1), ("Right", -1)):
        ev, ef, _ = _ellipsoid(np.array([sgn * EYE_X, EYE_Y, 0.07]), np.full(3, EYE_R), 8, 16)
        eyes[side] = (ev, ef, joint_names.index(f"{side}Eye"))
    bv, bf, _ = _ellipsoid(np.array([0.0, 1.25, 0.0]), np.array([0.18, 0.3, 0.1]), 10, 20)
    head_t = _head_targets(hv)
    teeth_t = {"jawOpen": np.outer((tv[:, 1] < MOUTH_Y).astype(float), [0.0, -0.010, 0.0])}
    names = list(ARKIT_NAMES) + (list(VISEME_TARGETS) if kind == "rpm" else [])
    if kind == "vrm0":
        raw = {v: k for k, v in _VRM0_RAW.items()}  # raw name -> preset
        src = {"a": "viseme_aa", "i": "viseme_ih", "u": "viseme_ou", "e": "viseme_E",
               "o": "viseme_oh", "blink": None, "joy": "mouthSmileLeft"}  # fmt: skip
        vis = {n: head_t["jawOpen"] * w for n, w in
               (("viseme_aa", 1.0), ("viseme_ih", 0.3), ("viseme_ou", 0.2), ("viseme_E", 0.5),
                ("viseme_oh", 0.6))}  # fmt: skip
        blink = head_t["eyeBlinkLeft"] + head_t["eyeBlinkRight"]
        head_t = {
            raw_name: (blink if src[p] is None else vis.get(src[p], head_t.get(src[p])))
            for raw_name, p in raw.items()
        }
        teeth_t = {"Fcl_MTH_A": teeth_t["jawOpen"]}
        names = list(head_t)
    elif kind == "vrm1":
        base = {"aa": 1.0, "ih": 0.3, "ou": 0.2, "ee": 0.5, "oh": 0.6}
        new = {f"mouth_{k}": head_t["jawOpen"] * w for k, w in base.items()}
        new["blink_L"] = head_t["eyeBlinkLeft"]
        new["blink_R"] = head_t["eyeBlinkRight"]
        new["happy"] = head_t["mouthSmileLeft"] + head_t["mouthSmileRight"]
        head_t = new
        teeth_t = {"mouth_aa": teeth_t["jawOpen"]}
        names = list(head_t)
    flip = np.array([-1.0, 1.0, -1.0]) if kind == "vrm0" else np.ones(3)
    turn = np.diag([*flip, 1.0])
    worlds = {k: turn @ m @ turn for k, m in worlds.items()} if kind == "vrm0" else worlds

    def primitive(v, f, joints, weights, targets, tnames, *, uv, material, color, sparse):
        attrs = pygltflib.Attributes(
            POSITION=b.add((v * flip).astype(np.float32), "VEC3", 5126, 34962, True),
            JOINTS_0=b.add(joints.astype(np.uint16), "VEC4", 5123, 34962, False),
            WEIGHTS_0=b.add(weights.astype(np.float32), "VEC4", 5126, 34962, False),
        )
        if uv is not None:
            attrs.TEXCOORD_0 = b.add(uv.astype(np.float32), "VEC2", 5126, 34962, False)
        if color is not None:
            attrs.COLOR_0 = b.add(color.astype(np.float32), "VEC4", 5126, 34962, False)
        deltas = [(targets[n] if n in targets else np.zeros_like(v)) * flip for n in tnames]
        prim_targets = [
            {"POSITION": _sparse_target(b, d) if sparse
             else b.add(d.astype(np.float32), "VEC3", 5126, 34962, True)}
            for d in deltas
        ]  # fmt: skip
        return pygltflib.Primitive(
            attributes=attrs,
            indices=b.add(f.astype(np.uint32).reshape(-1), "SCALAR", 5125, 34963, False),
            targets=prim_targets or None,
            material=material,
        )

    def add_mesh(name, v, f, joints, weights, targets, *, uv=None, material, color=None):
        tnames = [n for n in names if n in targets]
        if not (vroid and name == "Face"):
            prims = [primitive(v, f, joints, weights, targets, tnames, uv=uv, material=material,
                               color=color, sparse=False)]  # fmt: skip
        else:  # skin and hair cap with their own vertices, lash cards
            prims = []
            hair = v[f].mean(axis=1)[:, 1] > HEAD_CENTRE[1] + 0.06
            for faces, mat in ((f[~hair], 0), (f[hair], 4)):
                used, local = np.unique(faces, return_inverse=True)
                prims.append(primitive(
                    v[used], local.reshape(-1, 3), joints[used], weights[used],
                    {n: t[used] for n, t in targets.items()}, tnames, uv=uv[used],
                    material=mat, color=None, sparse=True,
                ))  # fmt: skip
            lv, lf, luv = _lash_cards()
            blink = {"Left": lv[:, 0] > 0, "Right": lv[:, 0] < 0}
            lash_t = {
                n: np.outer(
                    blink["Left"] * ("blink_R" not in n) + blink["Right"] * ("blink_L" not in n),
                    [0.0, -0.008, 0.0],
                )
                if n in ("Fcl_EYE_Close", "blink_L", "blink_R") else np.zeros_like(lv)
                for n in tnames
            }  # fmt: skip
            prims.append(primitive(
                lv, lf, np.tile([joint_names.index("Head"), 0, 0, 0], (len(lv), 1)),
                np.tile([1.0, 0, 0, 0], (len(lv), 1)), lash_t, tnames, uv=luv, material=5,
                color=None, sparse=True,
            ))  # fmt: skip
        meshes.append(
            pygltflib.Mesh(
                name=name,
                primitives=prims,
                weights=[0.0] * len(tnames) if tnames else None,
                extras={"targetNames": tnames} if tnames else None,
            )
        )
        return len(meshes) - 1, tnames

    meshes: list[pygltflib.Mesh] = []
    rpm = kind == "rpm"
    head_mesh, head_names = add_mesh(
        "Wolf3D_Head" if rpm else ("Face" if kind.startswith("vrm") else "head"),
        hv, hf, head_j, head_wt, head_t, uv=huv, material=0,
    )  # fmt: skip
    teeth_colour = np.tile([0.9, 0.88, 0.8, 1.0], (len(tv), 1))
    teeth_mesh, teeth_names = add_mesh(
        "Wolf3D_Teeth" if rpm else "teeth", tv, tf, teeth_j, teeth_wt, teeth_t,
        material=1, color=teeth_colour,
    )  # fmt: skip
    eye_meshes = {}
    for side, (ev, ef, j) in eyes.items():
        eye_meshes[side], _ = add_mesh(
            f"Eye{side}" if rpm else f"eye_{side.lower()}",
            ev, ef, np.tile([j, 0, 0, 0], (len(ev), 1)), np.tile([1.0, 0, 0, 0], (len(ev), 1)),
            {}, material=2,
        )  # fmt: skip
    torso_j = np.tile([joint_names.index("Spine"), 0, 0, 0], (len(bv), 1))
    torso_mesh, _ = add_mesh(
        "Wolf3D_Outfit_Top" if rpm else "torso", bv, bf, torso_j,
        np.tile([1.0, 0, 0, 0], (len(bv), 1)), {}, material=3,
    )  # fmt: skip
    # --- nodes ------------------------------------------------------------------------------
    prefix = "mixamorig:" if kind == "skinned" else ("J_Bip_C_" if kind.startswith("vrm") else "")
    nodes: list[pygltflib.Node] = []
    node_of: dict[str, int] = {}
    for name, (parent, _, _) in _JOINTS.items():
        local = worlds[name] if parent is None else np.linalg.inv(worlds[parent]) @ worlds[name]
        node_of[name] = len(nodes)
        nodes.append(
            pygltflib.Node(name=prefix + name, matrix=local.T.reshape(-1).tolist(), children=[])
        )
        if parent is not None:
            nodes[node_of[parent]].children.append(node_of[name])
    ibm = np.stack([np.linalg.inv(worlds[n]) for n in joint_names]).astype(np.float32)
    ibm_acc = b.add(ibm.transpose(0, 2, 1).reshape(-1, 16), "MAT4", 5126, None, False)
    skin = pygltflib.Skin(joints=[node_of[n] for n in joint_names], inverseBindMatrices=ibm_acc)
    mesh_nodes = []
    for m in (head_mesh, teeth_mesh, eye_meshes["Left"], eye_meshes["Right"], torso_mesh):
        mesh_nodes.append(len(nodes))
        # a skinned mesh node's own transform must be ignored (glTF 2.0 §3.7.3): give it one
        nodes.append(pygltflib.Node(name=meshes[m].name, mesh=m, skin=0, translation=[5.0, 0, 0]))
    if kind == "skinned":  # a rigid (unskinned) hat, child of the head joint
        cv, cf, _ = _ellipsoid(np.array([0.0, 0.0, 0.0]), np.array([0.08, 0.03, 0.095]), 8, 16)
        hat_mesh = len(meshes)
        attrs = pygltflib.Attributes(
            POSITION=b.add(cv.astype(np.float32), "VEC3", 5126, 34962, True)
        )
        meshes.append(pygltflib.Mesh(name="hat", primitives=[pygltflib.Primitive(
            attributes=attrs,
            indices=b.add(cf.astype(np.uint32).reshape(-1), "SCALAR", 5125, 34963, False),
            material=3)]))  # fmt: skip
        hat_world = np.eye(4)
        hat_world[:3, 3] = HEAD_CENTRE + np.array([0.0, 0.10, 0.0])
        local = np.linalg.inv(worlds["Head"]) @ hat_world
        nodes.append(pygltflib.Node(name="hat", mesh=hat_mesh, matrix=local.T.reshape(-1).tolist()))
        nodes[node_of["Head"]].children.append(len(nodes) - 1)
    # --- texture, materials ------------------------------------------------------------------
    image_view = b.add_bytes(_atlas_png() if vroid else _png(HAIR_RGB, SKIN_RGB))

    def material(rgba, texture=False, region=None, mask=False):
        pbr = pygltflib.PbrMetallicRoughness(baseColorFactor=rgba, metallicFactor=0.0)
        if texture:
            pbr.baseColorTexture = pygltflib.TextureInfo(index=0)
            if vroid:  # a region of the atlas
                transform = {"offset": list(ATLAS_REGIONS[region]), "scale": [0.5, 0.5]}
                pbr.baseColorTexture.extensions = {"KHR_texture_transform": transform}
        out = pygltflib.Material(pbrMetallicRoughness=pbr)
        if vroid:
            if mask:
                out.alphaMode, out.alphaCutoff = "MASK", 0.5
            if kind == "vrm1":
                out.extensions = {"VRMC_materials_mtoon": {
                    "specVersion": "1.0", "shadeColorFactor": [c * 0.7 for c in rgba[:3]],
                    "shadingToonyFactor": 0.9, "outlineWidthMode": "none"}}  # fmt: skip
        return out

    materials = [
        material([1, 1, 1, 1], texture=True, region="skin"),
        material([1, 1, 1, 1]),
        material([0.95, 0.95, 0.95, 1]),
        material([0.2, 0.25, 0.4, 1]),
    ]
    if vroid:
        materials += [
            material([1, 1, 1, 1], texture=True, region="hair"),
            material([1, 1, 1, 1], texture=True, region="lashes", mask=True),
        ]
    buffer = b.buffer()
    doc = pygltflib.GLTF2(
        asset=pygltflib.Asset(
            version="2.0",
            generator={
                "rpm": "Ready Player Me (facelab sample)",
                "vrm0": "VRoid (facelab sample)",
                "vrm1": "VRoid (facelab sample)",
            }.get(kind, "Blender (facelab sample)"),
        ),
        scene=0,
        scenes=[pygltflib.Scene(nodes=[node_of["Hips"], *mesh_nodes])],
        nodes=nodes,
        meshes=meshes,
        skins=[skin],
        materials=materials,
        textures=[pygltflib.Texture(source=0)],
        images=[pygltflib.Image(bufferView=image_view, mimeType="image/png")],
        accessors=b.accessors,
        bufferViews=b.views,
        buffers=[pygltflib.Buffer(byteLength=len(buffer))],
    )
    if kind == "vrm0":
        groups = []
        for raw_name, preset in {v: k for k, v in _VRM0_RAW.items()}.items():
            binds = [{"mesh": head_mesh, "index": head_names.index(raw_name), "weight": 100}]
            if raw_name in teeth_names:
                binds.append(
                    {"mesh": teeth_mesh, "index": teeth_names.index(raw_name), "weight": 100}
                )
            groups.append({"name": preset.upper(), "presetName": preset, "binds": binds})
        bones = [
            {"bone": b, "node": node_of[n]}
            for b, n in (("neck", "Neck"), ("head", "Head"), ("leftEye", "LeftEye"),
                         ("rightEye", "RightEye"))
        ]  # fmt: skip
        doc.extensions = {"VRM": {"specVersion": "0.0", "humanoid": {"humanBones": bones},
                                  "blendShapeMaster": {"blendShapeGroups": groups}}}  # fmt: skip
        doc.extensionsUsed = ["VRM"]
        # VRoid Studio's lookAt: the eye bones turn 10 deg at a 90 deg gaze
        doc.extensions["VRM"]["firstPerson"] = {
            "lookAtTypeName": "Bone",
            **{k: {"curve": [0, 0, 0, 1, 1, 1, 1, 0], "xRange": 90.0, "yRange": 10.0}
               for k in ("lookAtHorizontalInner", "lookAtHorizontalOuter", "lookAtVerticalDown",
                         "lookAtVerticalUp")},
        }  # fmt: skip
        if vroid:  # UniVRM 0.x keeps the MToon parameters beside the glTF fallback
            doc.extensions["VRM"]["materialProperties"] = [
                {"name": f"material_{i}", "shader": "VRM/MToon",
                 "renderQueue": 2450 if m.alphaMode == "MASK" else 2000,
                 "floatProperties": {"_Cutoff": 0.5, "_BlendMode": 1 if m.alphaMode else 0},
                 "vectorProperties": {"_Color": m.pbrMetallicRoughness.baseColorFactor,
                                      "_ShadeColor": [0.7, 0.6, 0.6, 1.0]},
                 "textureProperties": {"_MainTex": 0}
                 if m.pbrMetallicRoughness.baseColorTexture is not None else {},
                 "keywordMap": {"_ALPHATEST_ON": True} if m.alphaMode == "MASK" else {},
                 "tagMap": {"RenderType": "TransparentCutout" if m.alphaMode else "Opaque"}}
                for i, m in enumerate(materials)
            ]  # fmt: skip
    elif kind == "vrm1":
        head_node = mesh_nodes[0]
        teeth_node = mesh_nodes[1]
        preset = {}
        for vrm_name in _VRM1_PRESETS:
            raw_name = {"aa": "mouth_aa", "ih": "mouth_ih", "ou": "mouth_ou", "ee": "mouth_ee",
                        "oh": "mouth_oh", "blinkLeft": "blink_L", "blinkRight": "blink_R",
                        "happy": "happy"}[vrm_name]  # fmt: skip
            binds = [{"node": head_node, "index": head_names.index(raw_name), "weight": 1.0}]
            if raw_name in teeth_names:
                binds.append(
                    {"node": teeth_node, "index": teeth_names.index(raw_name), "weight": 1.0}
                )
            preset[vrm_name] = {"morphTargetBinds": binds}
        bones = {
            "neck": {"node": node_of["Neck"]},
            "head": {"node": node_of["Head"]},
            "leftEye": {"node": node_of["LeftEye"]},
            "rightEye": {"node": node_of["RightEye"]},
        }
        look_at = {"type": "bone", **{k: {"inputMaxValue": 90.0, "outputScale": 10.0}
                   for k in ("rangeMapHorizontalInner", "rangeMapHorizontalOuter",
                             "rangeMapVerticalDown", "rangeMapVerticalUp")}}  # fmt: skip
        doc.extensions = {"VRMC_vrm": {"specVersion": "1.0", "humanoid": {"humanBones": bones},
                                       "expressions": {"preset": preset},
                                       "lookAt": look_at}}  # fmt: skip
        doc.extensionsUsed = ["VRMC_vrm"] + (["VRMC_materials_mtoon"] if vroid else [])
    if vroid:
        doc.extensionsUsed.append("KHR_texture_transform")
        doc.extensionsRequired = ["KHR_texture_transform"]  # the atlas is wrong without it
    if path.suffix.lower() == ".gltf":
        doc.buffers[0].uri = (
            "data:application/octet-stream;base64," + base64.b64encode(buffer).decode()
        )
        path.write_text(doc.gltf_to_json(), encoding="utf-8")
    else:
        doc.set_binary_blob(buffer)
        path.write_bytes(b"".join(doc.save_to_bytes()))
    return path
