"""What an avatar's geometry can show, measured rather than assumed from its target names.

A file may name all 52 ARKit targets and still leave some of them empty (every delta zero) or
fill two with the same shape (a VRoid export whose ``mouthFunnel`` and ``mouthPucker`` are both
its ``Fcl_MTH_U``). The animation methods (which targets stand in for which) and the stimulus
checks (``facelab check``'s avatar audit) both ask these functions, so the two cannot disagree.

Distances are millimetres of the avatar's own units read as metres (glTF's unit).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from facelab.stimuli.avatar.mesh import Avatar

__all__ = [
    "EMPTY_TARGET_MM",
    "IDENTICAL_TOLERANCE_MM",
    "WILD_TARGET_MM",
    "WILD_TARGET_SPANS",
    "face_orientation",
    "identical_targets",
    "moved_vertices",
    "target_motion_mm",
    "unusable_targets",
]

#: a target whose largest vertex displacement at full weight is below this moves nothing a
#: viewer could see (a pixel of a 720p close-up is about 0.3 mm on a face)
EMPTY_TARGET_MM = 0.5
#: a face shape moving a vertex further than this (mm) at full weight tears the face - on a
#: human-sized head a jaw opens about 20-40 mm (the default head's jawOpen 36, the samples'
#: 12): shapes exported at another scale than the mesh (centimetres) or a broken export.
#: Used when the face's own scale cannot be found; else :data:`WILD_TARGET_SPANS`
WILD_TARGET_MM = 150.0
#: ... as a multiple of the face's mouth-to-eyes distance (the default head's jawOpen moves
#: 0.33 of it), so a model in centimetres, shapes and mesh alike, is not called torn
WILD_TARGET_SPANS = 1.0
#: two targets whose deltas differ nowhere by more than this are the same shape
IDENTICAL_TOLERANCE_MM = 0.01


def _measured(avatar: Avatar) -> dict[object, tuple]:
    """The avatar's measures so far (the methods and checks ask the same questions of one
    avatar many times: validating the shipped protocols asked 2,107 times), each kept with
    the target arrays it was measured on - a target replaced by another array is measured
    again."""
    cache = avatar.__dict__.get("_facelab_audit")
    if cache is None:
        cache = avatar.__dict__["_facelab_audit"] = {}
    return cache


def target_motion_mm(avatar: Avatar, names: Iterable[str]) -> dict[str, float]:
    """{name: the largest displacement of any vertex at full weight, mm} for each of ``names``
    the avatar has (absent names are left out)."""
    cache, out = _measured(avatar), {}
    for n in names:
        delta = avatar.targets.get(n)
        if delta is None:
            continue
        hit = cache.get(n)
        if hit is None or hit[0] is not delta:
            mm = float(np.sqrt((delta.astype(np.float64) ** 2).sum(axis=1)).max()) * 1e3
            hit = cache[n] = (delta, mm)
        out[n] = hit[1]
    return out


def identical_targets(avatar: Avatar, names: Iterable[str]) -> list[tuple[str, str]]:
    """Pairs of ``names`` (present, not empty) whose shapes are the same within
    :data:`IDENTICAL_TOLERANCE_MM`, each pair once, in sorted order."""
    motion = target_motion_mm(avatar, names)
    live = sorted(n for n, mm in motion.items() if mm >= EMPTY_TARGET_MM)
    cache, pairs = _measured(avatar), []
    tol = IDENTICAL_TOLERANCE_MM * 1e-3
    for i, a in enumerate(live):
        da = avatar.targets[a]
        for b in live[i + 1 :]:
            db = avatar.targets[b]
            hit = cache.get((a, b))
            if hit is None or hit[0] is not da or hit[1] is not db:
                hit = cache[(a, b)] = (da, db, bool(np.abs(da - db).max() <= tol))
            if hit[2]:
                pairs.append((a, b))
    return pairs


def unusable_targets(avatar: Avatar, names: Iterable[str]) -> dict[str, str]:
    """{name: why} for each of ``names`` the avatar has but cannot show: empty (moves less
    than :data:`EMPTY_TARGET_MM`) or the same shape as another of ``names``."""
    names = list(names)
    why = {
        n: f"empty (moves {mm:.2f} mm at full weight)"
        for n, mm in target_motion_mm(avatar, names).items()
        if mm < EMPTY_TARGET_MM
    }
    for a, b in identical_targets(avatar, names):
        why.setdefault(a, f"the same shape as {b}")
        why.setdefault(b, f"the same shape as {a}")
    return why


#: shapes that open the mouth / close the eyes, in the naming conventions facelab reads
#: (ARKit, Oculus visemes, VRM 0.x presets and VRoid's, VRM 1.0 expressions)
MOUTH_OPENERS = ("jawOpen", "viseme_aa", "aa", "A", "Fcl_MTH_A", "mouth_aa")
EYE_CLOSERS = ("eyeBlinkLeft", "eyeBlinkRight", "blink", "Blink", "Fcl_EYE_Close", "eye_blink")


def moved_vertices(
    avatar: Avatar, names: Iterable[str], *, at_least: int = 3
) -> np.ndarray | None:
    """(V,) bool: the rest vertices the shapes ``names`` move (by more than 1e-4 of the
    model's size) that are drawn (:meth:`Avatar.drawn`), or None when fewer than
    ``at_least`` move."""
    mask = np.zeros(len(avatar.neutral), bool)
    scale = float(np.ptp(avatar.neutral, axis=0).max()) or 1.0
    for name in names:
        delta = avatar.targets.get(name)
        if delta is not None:
            mask |= np.abs(delta).max(axis=1) > 1e-4 * scale
    mask &= avatar.drawn()
    return mask if mask.sum() >= at_least else None


def face_orientation(avatar: Avatar) -> tuple[float, float, float] | None:
    """How the face sits before the camera (facelab looks along -Z at a face facing +Z,
    +Y up): ``(up, towards, span_m)`` - the cosine between +Y and the line from the mouth's
    moving vertices up to the eyes'; the Z component of the mean normal of the surface the
    eye-closing shapes move (the lids face the camera: negative means facing away, or the
    triangles wound inside out; a head bowed 45 degrees still gives 0.33 on the default
    head); and the length of that mouth-to-eyes line (the face's own scale, whatever the
    file's unit). None without a mouth-opening and an eye-closing shape to find them by."""
    mouth, eyes = moved_vertices(avatar, MOUTH_OPENERS), moved_vertices(avatar, EYE_CLOSERS)
    if mouth is None or eyes is None:
        return None
    v = avatar.neutral.astype(np.float64)
    line = v[eyes].mean(axis=0) - v[mouth].mean(axis=0)
    span = float(np.linalg.norm(line))
    up = float(line[1] / (span or 1.0))
    tri = avatar.faces[eyes[avatar.faces].all(axis=1)]
    if not len(tri):
        return up, float("nan"), span
    normal = np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]]).sum(axis=0)
    return up, float(normal[2] / (np.linalg.norm(normal) or 1.0)), span
