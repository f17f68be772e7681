"""Track files as other tools write them, for the external_track tests: Live Link Face CSV,
NVIDIA Audio2Face blendshape JSON, ARKit JSON frames, Oculus/uLipSync viseme CSV and a glTF
file with a morph-weight animation. Written here from arrays with known values."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from facelab.stimuli.arkit import ARKIT_NAMES, OCULUS_VISEMES

ANGLES = ("HeadYaw", "HeadPitch", "HeadRoll", "LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll",
          "RightEyeYaw", "RightEyePitch", "RightEyeRoll")  # fmt: skip


def pascal(name: str) -> str:
    return name[0].upper() + name[1:]


def live_link_face_csv(
    path: Path, weights: np.ndarray, *, fps: int = 60, start_s: int = 37, timecode_fps: int = 30,
    names: tuple[str, ...] = ARKIT_NAMES, angles: np.ndarray | None = None,
) -> Path:  # fmt: skip
    """(T, 52) weights captured at ``fps`` as Live Link Face writes them: Timecode
    HH:MM:SS:FF.fff at ``timecode_fps`` (the sub-frame after the dot: a 60 fps capture on a
    30 fps timecode alternates .000 and .500) from ``start_s`` into the hour,
    BlendShapeCount 61, PascalCase names, nine angles (``angles`` (T, 9) in :data:`ANGLES`
    order, radians; default a small wobble)."""
    lines = [",".join(["Timecode", "BlendShapeCount", *map(pascal, names), *ANGLES])]
    for k, row in enumerate(weights):
        frames = (start_s + k / fps) * timecode_fps
        whole = int(np.floor(frames + 1e-9))
        sub = frames - whole
        sec, ff = divmod(whole, timecode_fps)
        hms = f"{sec // 3600:02d}:{sec // 60 % 60:02d}:{sec % 60:02d}"
        tc = f"{hms}:{ff:02d}.{round(sub * 1000):03d}"
        at = [0.01 * np.sin(k / 10)] * len(ANGLES) if angles is None else angles[k]
        lines.append(",".join([tc, "61", *(f"{v:.6f}" for v in row),
                               *(f"{a:.5f}" for a in at)]))  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def audio2face_json(path: Path, weights: np.ndarray, *, fps: int = 30) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({
        "exportFps": fps, "trackPath": "/World/audio2face/Player", "numPoses": 52,
        "numFrames": len(weights), "facsNames": list(ARKIT_NAMES),
        "weightMat": np.round(weights, 6).tolist(),
    }), encoding="utf-8")  # fmt: skip
    return path


def arkit_json(path: Path, times: np.ndarray, weights: np.ndarray) -> Path:
    frames = [{"time": float(t), "blendshapes": {n: float(v) for n, v in
                                                 zip(ARKIT_NAMES, row, strict=True) if v}}
              for t, row in zip(times, weights, strict=True)]  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"frames": frames}), encoding="utf-8")
    return path


def viseme_csv(path: Path, times: np.ndarray, weights: np.ndarray) -> Path:
    """(T, 15) Oculus viseme weights with a ``time`` column, uLipSync-style bare names."""
    lines = [",".join(["time", *OCULUS_VISEMES])]
    lines += [",".join([f"{t:.4f}", *(f"{v:.5f}" for v in row)])
              for t, row in zip(times, weights, strict=True)]  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def gltf_animation(path: Path, times: np.ndarray, weights: np.ndarray) -> Path:
    """A .glb with one triangle carrying the 52 ARKit targets (empty) and an animation of
    their weights (LINEAR)."""
    import pygltflib

    blob = bytearray()

    def add(arr: np.ndarray, kind: str, target: int | None) -> int:
        data = np.ascontiguousarray(arr, np.float32).tobytes()
        offset = len(blob)
        blob.extend(data + b"\0" * (-len(data) % 4))
        views.append(pygltflib.BufferView(buffer=0, byteOffset=offset, byteLength=len(data),
                                          target=target))  # fmt: skip
        count = len(arr) if kind != "SCALAR" or arr.ndim == 1 else arr.size
        acc = pygltflib.Accessor(bufferView=len(views) - 1, componentType=5126, count=count,
                                 type=kind)  # fmt: skip
        if kind == "VEC3" or (kind == "SCALAR" and arr.ndim == 1):
            acc.min = np.atleast_1d(arr.min(axis=0)).tolist()
            acc.max = np.atleast_1d(arr.max(axis=0)).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    views: list = []
    accessors: list = []
    tri = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]], np.float32)
    pos = add(tri, "VEC3", 34962)
    targets = [{"POSITION": add(np.zeros((3, 3)), "VEC3", 34962)} for _ in ARKIT_NAMES]
    t_in = add(np.asarray(times, np.float32), "SCALAR", None)
    w_out = add(np.asarray(weights, np.float32).reshape(-1), "SCALAR", None)
    accessors[w_out].count = int(np.asarray(weights).size)
    doc = pygltflib.GLTF2(
        scene=0, scenes=[pygltflib.Scene(nodes=[0])], nodes=[pygltflib.Node(mesh=0)],
        meshes=[pygltflib.Mesh(primitives=[pygltflib.Primitive(
            attributes=pygltflib.Attributes(POSITION=pos), targets=targets)],
            extras={"targetNames": list(ARKIT_NAMES)}, weights=[0.0] * 52)],
        animations=[pygltflib.Animation(
            samplers=[pygltflib.AnimationSampler(input=t_in, output=w_out, interpolation="LINEAR")],
            channels=[pygltflib.AnimationChannel(
                sampler=0, target=pygltflib.AnimationChannelTarget(node=0, path="weights"))])],
        accessors=accessors, bufferViews=views, buffers=[pygltflib.Buffer(byteLength=len(blob))],
    )  # fmt: skip
    doc.set_binary_blob(bytes(blob))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"".join(doc.save_to_bytes()))
    return path
