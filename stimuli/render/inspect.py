"""What an avatar offers and which conditions it can play (``facelab avatar inspect``), and a
contact sheet of it: the five vowels, a blink, a head turn and a gaze shift.

Playability per registered method (``facelab.stimuli.methods.REGISTRY``): each method says
how it plays on the avatar (:meth:`Method.playback`) for the parameter sets it offers as
examples - e.g. ``vowel_blend`` with both shipped Z matrices: ``yes``, ``vowel presets`` on a
VRM without the ARKit targets (the five presets aa ih ou ee oh stand in for Z, Y = G·X), or
``no`` with the missing names; the viseme methods ``yes``, ``via ARKit mixes`` or ``no``.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from facelab.errors import AvatarError
from facelab.stimuli.arkit import ARKIT_NAMES, VISEME_TARGETS
from facelab.stimuli.avatar.gaze import gaze_map
from facelab.stimuli.avatar.lids import lid_model
from facelab.stimuli.avatar.mesh import LANDMARKS, Avatar
from facelab.stimuli.avatar.rig import ROLES, HeadPose
from facelab.stimuli.avatar.vrm import VOWEL_PRESET_TARGETS
from facelab.stimuli.capture.zmatrix import load_z
from facelab.stimuli.methods import REGISTRY
from facelab.stimuli.speech.track import VOWELS

__all__ = ["avatar_report", "format_report", "playability", "sheet_poses", "write_sheet"]


def playability(avatar: Avatar) -> dict[str, str]:
    """{method: how it plays on this avatar}: the first example parameter set it cannot play
    with, else how it plays with the first (see the module docstring)."""
    out = {}
    for name, method in REGISTRY.items():
        plays = [method.playback(avatar, params) for params in method.examples()]
        refused = [(p, params) for p, params in zip(plays, method.examples(), strict=True)
                   if not p.playable]  # fmt: skip
        out[name] = refused[0][0].how if refused else plays[0].how
    return out


def avatar_report(avatar: Avatar) -> dict:
    """A JSON-ready description: kind, size, meshes, targets, rig roles, textures, methods."""
    names = set(avatar.targets)
    sk = avatar.skeleton
    return {
        "name": avatar.name,
        "kind": avatar.source.get("kind", "unknown"),
        "vertices": len(avatar.neutral),
        "triangles": len(avatar.faces),
        "meshes": list(avatar.source.get("meshes", [])),
        "height_m": float(np.ptp(avatar.neutral[:, 1])),
        "arkit_targets": f"{len(names & set(ARKIT_NAMES))}/52",
        "viseme_targets": f"{len(names & set(VISEME_TARGETS))}/15",
        "missing_arkit": sorted(set(ARKIT_NAMES) - names),
        "other_targets": sorted(names - set(ARKIT_NAMES) - set(VISEME_TARGETS)),
        "vrm_presets": dict(avatar.source.get("presets", {})),
        "skeleton": None
        if sk is None
        else {
            "joints": len(sk.names),
            "roles": {r: sk.names[j] for r, j in sk.roles.items()},
            "missing_roles": [r for r in ROLES if r not in sk.roles],
        },
        "textures": [f"{t.shape[1]}x{t.shape[0]}" for t in avatar.textures],
        "landmarks": sorted(avatar.landmarks),
        "lip_landmarks": all(k in avatar.landmarks for k in LANDMARKS),
        "lid_limits": lid_model(avatar) is not None,
        "gaze": gaze_map(avatar).describe(),
        "methods": playability(avatar),
        "notes": list(avatar.source.get("notes", [])),  # what was read only in part
    }


def _scale_and_naming_hints(report: Mapping) -> list[str]:
    """What the geometry and the names alone say a user got wrong: a model far taller than a
    person or smaller than a head (glTF is in metres: an export in centimetres or
    millimetres), and shape names that are ARKit's behind a prefix the exporter added."""
    from facelab.stimuli.arkit import canonical_arkit_name

    out = []
    height = float(report["height_m"])
    if height > 3.0:
        out.append(f"warning: {height:.2f} m tall - taller than a person; glTF is in metres: "
                   "exported in centimetres? (scale by 0.01 on export)")  # fmt: skip
    elif 0 < height < 0.1:
        out.append(f"warning: {height:.3f} m tall - smaller than a head; glTF is in metres: "
                   "exported in another unit? (scale on export)")  # fmt: skip
    others = list(report["other_targets"])
    if others and str(report["arkit_targets"]).startswith("0/"):
        low, high = min(others), max(others)  # the shared start of all: of these two
        prefix = low[: next((i for i, (a, b) in enumerate(zip(low, high, strict=False)) if a != b),
                            min(len(low), len(high)))]  # fmt: skip
        cut = [canonical_arkit_name(n[len(prefix):]) for n in others] if len(prefix) >= 2 else []
        found = sum(1 for c in cut if c)
        shown = ", ".join(others[:6]) + (" ..." if len(others) > 6 else "")
        out.append(f"its targets: {shown}")
        if found:
            out.append(f"warning: {found} of them are ARKit or viseme names behind the prefix "
                       f"{prefix!r} - rename them without it (or export without the "
                       "prefix)")  # fmt: skip
    return out


def format_report(report: Mapping) -> str:
    """The report as aligned text lines."""
    sk = report["skeleton"]
    lines = [
        f"avatar     {report['name']} ({report['kind']})",
        f"geometry   {report['vertices']} vertices, {report['triangles']} triangles, "
        f"{report['height_m']:.2f} m tall, meshes: {', '.join(report['meshes']) or '-'}",
        f"targets    ARKit {report['arkit_targets']}, visemes {report['viseme_targets']}, "
        f"{len(report['other_targets'])} other",
    ]
    lines += [f"           {w}" for w in _scale_and_naming_hints(report)]
    if report["missing_arkit"] and len(report["missing_arkit"]) <= 26:
        lines.append(f"           missing ARKit: {', '.join(report['missing_arkit'])}")
    if report["vrm_presets"]:
        lines.append(
            "presets    "
            + ", ".join(f"{p} -> {t}" for t, p in sorted(report["vrm_presets"].items()))
        )
    if sk is None:
        lines.append("rig        none (no head, neck or eye rotation)")
    else:
        roles = ", ".join(f"{r}={n}" for r, n in sk["roles"].items()) or "-"
        missing = f"; missing {', '.join(sk['missing_roles'])}" if sk["missing_roles"] else ""
        lines.append(f"rig        {sk['joints']} joints; {roles}{missing}")
    lines.append(f"textures   {', '.join(report['textures']) or 'none (vertex colours)'}")
    lines.append(
        "landmarks  "
        + (
            "lip landmarks present (checked against the mouth's geometry in the audit)"
            if report["lip_landmarks"]
            else "no lip landmarks (lip metrics unavailable)"
        )
    )
    lines.append(
        "lids       "
        + (
            "a blink in a squint or smile closes the eye no further than shut (lid landmarks)"
            if report.get("lid_limits")
            else "no lid landmarks: blinks and squints add as the avatar's own shapes do"
        )
    )
    if report.get("gaze"):
        lines.append(f"gaze       {report['gaze']}")
    lines.append("methods")
    for method, how in report["methods"].items():
        lines.append(f"  {method:<17} {how}")
    audit = report.get("audit", [])
    unplayable = [m for m, how in report["methods"].items() if str(how).startswith("no")]
    if audit:
        lines.append(f"audit      {len(audit)} problem(s) for kato2021's conditions (facelab "
                     "check's avatar audit)")  # fmt: skip
    else:  # a method that cannot play drives nothing: it was not audited
        lines.append("audit      every target kato2021's conditions drive moves, none is a copy"
                     + (f"; not audited: {', '.join(unplayable)} (the avatar lacks their "
                        "targets, see methods)" if unplayable else ""))  # fmt: skip
    lines += [f"  {line}" for line in audit]
    for note in report.get("notes", []):
        lines.append(f"note       {note}")
    return "\n".join(lines)


def _vowel_weights(avatar: Avatar, vowel: str) -> dict[str, float]:
    """Target weights showing ``vowel`` at full strength on this avatar."""
    j = VOWELS.index(vowel)
    z = load_z("standard")
    arkit = {n: float(z[i, j]) for i, n in enumerate(ARKIT_NAMES) if z[i, j] > 0}
    if set(arkit) <= set(avatar.targets):
        return arkit
    preset = VOWEL_PRESET_TARGETS[j]
    if preset in avatar.targets:
        return {preset: 1.0}
    raise AvatarError(f"avatar {avatar.name!r} has neither the ARKit shapes nor a {preset} target")


def sheet_poses(avatar: Avatar) -> list[tuple[str, dict[str, float], HeadPose | None]]:
    """(label, weights, pose) for each tile of the contact sheet."""
    tiles: list[tuple[str, dict[str, float], HeadPose | None]] = [("neutral", {}, None)]
    for v in VOWELS:
        tiles.append((f"/{v}/", _vowel_weights(avatar, v), None))
    blink = {n: 1.0 for n in ("eyeBlinkLeft", "eyeBlinkRight") if n in avatar.targets}
    if blink:
        tiles.append(("blink", blink, None))
    sk = avatar.skeleton
    if sk is not None and "head" in sk.roles:
        tiles.append(("head yaw 25° pitch 10°", {}, HeadPose(yaw=25, pitch=10)))
        tiles.append(("head roll 12°", {}, HeadPose(roll=12)))
    gaze = gaze_map(avatar)
    if gaze.mode == "joints" and sk is not None and {"eye_left", "eye_right"} <= set(sk.roles):
        yaw, pitch = gaze.joint_angles(20, -10)
        tiles.append(("gaze 20° left, 10° up", {}, HeadPose(eye_yaw=yaw, eye_pitch=pitch)))
    elif gaze.mode == "shapes" and all(n in avatar.targets for pair in gaze.targets.values()
                                       for n in pair):  # fmt: skip
        tiles.append(("gaze 20° left, 10° up (shapes)", gaze.shape_weights(20, -10), None))
    return tiles


def write_sheet(avatar: Avatar, *, out: Path, tile: int = 360, msaa: int = 4) -> Path:
    """A contact sheet PNG (see :func:`sheet_poses`), two rows, labelled."""
    from PIL import Image, ImageDraw

    from facelab.stimuli.render.contact_sheets import sheet_font
    from facelab.stimuli.render.renderer import Renderer
    from facelab.stimuli.render.scene import face_closeup

    tiles = sheet_poses(avatar)
    settings = face_closeup(avatar, size_px=tile, msaa=msaa, margin=1.5)  # room for turns
    images = []
    font = sheet_font(max(12, tile // 18))
    with Renderer(avatar, settings) as r:
        for label, weights, pose in tiles:
            img = Image.fromarray(r.frame(avatar.weight_vector(weights), pose=pose))
            ImageDraw.Draw(img).text((8, 6), label, fill=(255, 255, 255), font=font)
            images.append(img)
    cols = (len(images) + 1) // 2
    sheet = Image.new("RGB", (cols * tile, 2 * tile + 40), (40, 40, 40))
    for i, img in enumerate(images):
        sheet.paste(img, ((i % cols) * tile, 40 + (i // cols) * tile))
    ImageDraw.Draw(sheet).text(
        (8, 8), f"{avatar.name} ({avatar.source.get('kind', '?')})", fill=(255, 255, 255), font=font
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out)
    return out
