"""The default head, built by code: a stylised human head with every ARKit and viseme target.

:func:`default_head` builds a skull surface with a real mouth slit (upper and lower lips are
separate vertices, with inner lip surfaces), a dark mouth interior, upper and lower teeth and
a tongue, eyeballs behind lid openings, brows, hair, neck and shoulders - and all 52 ARKit
targets plus the 15 ``viseme_*`` targets as smooth per-vertex displacement fields.

Proportions follow an adult face in thirds (hairline to brows, brows to the base of the nose,
nose to chin): a cranium tall and broad enough for a forehead, cheekbones and an angle of the
jaw that widen only the sides of the face (never the mouth, nose or eyes, whose shapes the
articulation checks measure), a chin with some breadth; hair with volume, its line receding
a little at the temples, cut round the ears and fading into the skin rather than ending on
the grid's staircase; ears standing out far enough to be seen from the front; a neck that
widens into the trapezius and sloping shoulders; skin tinted (warmer cheeks and nose tip, a
faint beard shadow along the jaw, shaded eye sockets, fine mottling). Visemes
are mixes of ARKit shapes (:data:`~facelab.stimuli.avatar.targets.VISEME_MIXES`), an approximation
of the MPEG-4 viseme shapes that keeps all conditions on one face.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from functools import cache

import numpy as np
from scipy import sparse

from facelab.stimuli.arkit import ARKIT_NAMES
from facelab.stimuli.avatar.mesh import Avatar
from facelab.stimuli.avatar.rig import Skeleton
from facelab.stimuli.avatar.targets import VISEME_MIXES

__all__ = ["default_head"]


def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _tint(colors: np.ndarray, target: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(V, 3) colours moved towards ``target`` ((3,) or (V, 3)) by ``w`` (V,) in [0, 1]."""
    return colors * (1 - w[:, None]) + target * w[:, None]


def _gauss(x: np.ndarray, y: np.ndarray, cx: float, cy: float, sx: float, sy: float) -> np.ndarray:
    return np.exp(-0.5 * (((x - cx) / sx) ** 2 + ((y - cy) / sy) ** 2))


# Head proportions (metres)
HEAD_W, HEAD_H, HEAD_D = 0.074, 0.112, 0.094  # half extents of the base ellipsoid
HEAD_CENTRE_Y = 0.0
MOUTH_Y = -0.052  # height of the mouth slit
MOUTH_HALF_W = 0.0235
EYE_Y = 0.022
EYE_X = 0.033
EYE_R = 0.0118
EYE_HALF_W, EYE_HALF_H = 0.0120, 0.0055  # the lid opening (an almond), half width and height
NOSE_LIFT = 0.005  # the nose's tip and base sit this much above the first design's
LID_EXTENT = 0.0085  # skin above the upper lid margin that moves in a blink
HINGE = np.array([0.0, -0.002, -0.012])  # jaw rotation axis point (x axis through it)

SKIN = np.array([0.86, 0.68, 0.58])
LIP = np.array([0.74, 0.30, 0.34])
BROW = np.array([0.25, 0.18, 0.14])
HAIR = np.array([0.16, 0.11, 0.08])
SCLERA = np.array([0.95, 0.94, 0.92])
IRIS = np.array([0.30, 0.20, 0.12])
PUPIL = np.array([0.03, 0.03, 0.03])
TEETH = np.array([0.86, 0.84, 0.77])
MOUTH = np.array([0.20, 0.06, 0.07])
TONGUE = np.array([0.66, 0.30, 0.32])
CLOTH = np.array([0.22, 0.30, 0.42])
LASH = np.array([0.10, 0.07, 0.06])
EAR = np.array([0.84, 0.62, 0.54])


def _front_surface(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Forward offset (metres, along z) of facial features at surface points (front only)."""
    front = _smoothstep(0.0, 0.06, z)
    # the nose: a narrow bridge widening towards a rounded tip, with the alae either side
    ny = y - NOSE_LIFT
    half_w = 0.0060 + 0.0045 * _smoothstep(-0.004, -0.028, ny)
    nose = 0.021 * np.exp(-0.5 * ((x / half_w) ** 2 + ((ny + 0.018) / 0.022) ** 2))
    nose *= _smoothstep(-0.045, -0.030, ny)
    nose += 0.007 * _gauss(x, ny, 0.0, -0.0335, 0.009, 0.007)
    nose += 0.0035 * (
        _gauss(x, ny, 0.0088, -0.0335, 0.0033, 0.0038)
        + _gauss(x, ny, -0.0088, -0.0335, 0.0033, 0.0038)
    )
    bridge = 0.004 * _gauss(x, y, 0.0, 0.012, 0.008, 0.012)
    sockets = -0.009 * (
        _gauss(x, y, EYE_X, EYE_Y, 0.014, 0.010) + _gauss(x, y, -EYE_X, EYE_Y, 0.014, 0.010)
    )
    brow = 0.004 * _gauss(x, y, 0.0, 0.040, 0.045, 0.007)
    cheeks = 0.005 * (
        _gauss(x, y, 0.040, -0.015, 0.014, 0.014) + _gauss(x, y, -0.040, -0.015, 0.014, 0.014)
    )
    lips = 0.010 * _gauss(x, y, 0.0, MOUTH_Y + 0.002, 0.020, 0.010)
    philtrum = -0.002 * _gauss(x, y, 0.0, -0.043, 0.004, 0.004)
    chin = 0.007 * _gauss(x, y, 0.0, -0.090, 0.016, 0.010)
    under_lip = -0.003 * _gauss(x, y, 0.0, -0.068, 0.016, 0.005)
    return front * (nose + bridge + sockets + brow + cheeks + lips + philtrum + chin + under_lip)


@dataclass
class _Part:
    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    name: str


def _grid_faces(rows: int, cols: int, *, wrap: bool) -> np.ndarray:
    r, c = np.meshgrid(np.arange(rows - 1), np.arange(cols if wrap else cols - 1), indexing="ij")
    a = r * cols + c
    b = r * cols + (c + 1) % cols
    d = (r + 1) * cols + c
    e = (r + 1) * cols + (c + 1) % cols
    # counter-clockwise seen from outside (rows go up, columns go round towards +x)
    return np.concatenate(
        [np.stack([a, b, d], -1).reshape(-1, 3), np.stack([b, e, d], -1).reshape(-1, 3)]
    )


def _sphere(
    centre: np.ndarray, radii: np.ndarray, rows: int, cols: int
) -> tuple[np.ndarray, np.ndarray]:
    phi = np.linspace(-np.pi / 2, np.pi / 2, rows)
    theta = np.linspace(-np.pi, np.pi, cols, endpoint=False)
    p, t = np.meshgrid(phi, theta, indexing="ij")
    v = np.stack([np.cos(p) * np.sin(t), np.sin(p), np.cos(p) * np.cos(t)], -1).reshape(-1, 3)
    return centre + v * radii, _grid_faces(rows, cols, wrap=True)


def _head_surface() -> tuple[_Part, dict[str, np.ndarray]]:
    """The skin: a deformed ellipsoid grid with a mouth slit, inner lips and eye openings."""
    n_theta, n_phi = 144, 110
    s = np.linspace(-1, 1, n_theta, endpoint=False)
    theta = np.pi * (0.35 * s + 0.65 * s**3)  # dense at the front
    u = np.linspace(-1, 1, n_phi)
    phi = (np.pi / 2) * 0.985 * (0.45 * u + 0.55 * u**3)  # dense at mid height
    p, t = np.meshgrid(phi, theta, indexing="ij")
    x = HEAD_W * np.cos(p) * np.sin(t)
    y = HEAD_H * np.sin(p) + HEAD_CENTRE_Y
    z = HEAD_D * np.cos(p) * np.cos(t)
    # a narrower jaw and chin, a fuller cranium at the back
    narrow = 1 - 0.17 * _smoothstep(-0.01, -0.11, y) * _smoothstep(-0.02, 0.06, z)
    x = x * narrow
    # a cranium tall enough for a forehead (the hairline a third of the face above the brows)
    y = y + 0.016 * _smoothstep(0.045, HEAD_H, y)
    x = x * (1 + 0.07 * _smoothstep(0.05, 0.11, y))  # a broad crown, not a dome
    # the sides of the face (never the mouth, nose or eyes): cheekbones and the angle of the jaw
    lateral = np.sign(x) * _smoothstep(0.040, 0.064, np.abs(x))
    x = x + lateral * (
        0.0050 * np.exp(-0.5 * ((y + 0.068) / 0.014) ** 2) * _smoothstep(-0.045, 0.0, z)
        + 0.0035 * np.exp(-0.5 * ((y + 0.006) / 0.012) ** 2) * _smoothstep(-0.02, 0.04, z)
    )
    # a chin with some breadth (below the lower lip's reach)
    x = x + np.sign(x) * 0.003 * _smoothstep(0.0, 0.025, np.abs(x)) * np.exp(
        -0.5 * ((y + 0.098) / 0.010) ** 2
    ) * _smoothstep(0.0, 0.05, z)
    z = z * (1 - 0.12 * _smoothstep(-0.03, -0.11, y) * _smoothstep(0.0, 0.05, -z))
    z = z + _front_surface(x, y, z)
    verts = np.stack([x, y, z], -1).reshape(-1, 3)
    rows, cols = n_phi, n_theta
    faces = _grid_faces(rows, cols, wrap=True)

    # mouth slit: the grid row nearest MOUTH_Y at the front; duplicate its vertices across
    # the mouth width so the quads below use the copies (the lower lip)
    front_col = np.argmin(np.abs(theta))
    mouth_row = int(np.argmin(np.abs(y[:, front_col] - MOUTH_Y)))
    slit_cols = [
        c for c in range(cols) if abs(x[mouth_row, c]) < MOUTH_HALF_W and z[mouth_row, c] > 0
    ]
    slit_cols.sort(key=lambda c: x[mouth_row, c])
    inner_slit = slit_cols[1:-1]  # the two end vertices stay shared: the mouth corners
    upper_idx = np.array([mouth_row * cols + c for c in inner_slit])
    lower_idx = np.arange(len(verts), len(verts) + len(upper_idx))
    verts = np.vstack([verts, verts[upper_idx]])
    remap = dict(zip(upper_idx.tolist(), lower_idx.tolist(), strict=True))
    # rows go up with the index (phi from -90 to +90 degrees): the quads between mouth_row - 1
    # and mouth_row lie below the slit and take the copies
    below = (faces // cols).max(axis=1) <= mouth_row
    for f in np.nonzero(below)[0]:
        faces[f] = [remap.get(int(v), int(v)) for v in faces[f]]
    corners = np.array([mouth_row * cols + slit_cols[0], mouth_row * cols + slit_cols[-1]])

    # inner lip surfaces: strips from each slit edge curling back into the mouth
    def inner_strip(edge: np.ndarray, sign: float) -> tuple[np.ndarray, np.ndarray]:
        chain = np.concatenate([[corners[0]], edge, [corners[1]]])
        base = verts[chain]
        steps = [(0.0020, 0.0012), (0.0040, 0.0016), (0.0060, 0.0014)]
        rows_v = [chain]
        new = []
        for k, (back, spread) in enumerate(steps):
            taper = np.sin(np.linspace(0, np.pi, len(chain))) ** 0.6
            ring = base + np.stack(
                [np.zeros(len(chain)), sign * spread * taper, -back * np.ones(len(chain))], -1
            )
            ring[:, 0] *= 1 - 0.08 * (k + 1)
            start = len(verts) + sum(len(r) for r in new)
            new.append(ring)
            rows_v.append(np.arange(start, start + len(chain)))
        strip_faces = []
        for a, b in itertools.pairwise(rows_v):
            for i in range(len(chain) - 1):
                tri1, tri2 = [a[i], a[i + 1], b[i]], [a[i + 1], b[i + 1], b[i]]
                if sign < 0:
                    tri1, tri2 = tri1[::-1], tri2[::-1]
                strip_faces += [tri1, tri2]
        return np.vstack(new), np.array(strip_faces)

    up_v, up_f = inner_strip(upper_idx, +1.0)
    upper_inner = np.arange(len(verts), len(verts) + len(up_v))
    verts = np.vstack([verts, up_v])
    lo_v, lo_f = inner_strip(lower_idx, -1.0)
    lower_inner = np.arange(len(verts), len(verts) + len(lo_v))
    verts = np.vstack([verts, lo_v])
    faces = np.vstack([faces, up_f, lo_f])

    # eye openings: drop the quads inside an almond around each eye; pull the rim onto the eyeball
    keep = np.ones(len(faces), bool)
    centroid = verts[faces].mean(axis=1)
    for side in (1, -1):
        cx = side * EYE_X
        dx = (centroid[:, 0] - cx) / EYE_HALF_W
        dy = (centroid[:, 1] - EYE_Y - 0.0008 * (1 - dx**2)) / EYE_HALF_H
        keep &= ~((dx**2 + dy**2 < 1.0) & (centroid[:, 2] > 0))
    faces = faces[keep]
    verts, lid_rim = _smooth_eye_openings(verts, faces)
    # the lids: from the margin (on a shell 1.2 mm outside the eyeball) the skin blends back
    # into the face surface by 1.7 times the opening's size
    shell_r = EYE_R + 0.0012
    for side in (1, -1):
        ec = _eye_centre(side)
        rel_x = (verts[:, 0] - side * EYE_X) / EYE_HALF_W
        rel_y = (verts[:, 1] - EYE_Y) / EYE_HALF_H
        rho = np.hypot(rel_x, rel_y)
        planar = (verts[:, 0] - ec[0]) ** 2 + (verts[:, 1] - ec[1]) ** 2
        z_shell = ec[2] + np.sqrt(np.clip(shell_r**2 - planar, 0.0, None))
        w = _smoothstep(1.7, 1.0, rho) * (verts[:, 2] > 0.03)
        verts[:, 2] = w * z_shell + (1 - w) * verts[:, 2]

    # colours: skin, lips, brows, hair
    vx, vy, vz = verts[:, 0], verts[:, 1], verts[:, 2]
    colors = np.tile(SKIN, (len(verts), 1))
    # skin that is not one flat colour: warmer cheeks and nose tip, a faint shadow of beard
    # along the jaw and under the chin, a lighter forehead, and fine mottling
    for sgn in (1, -1):
        blush = _gauss(vx, vy, sgn * 0.040, -0.022, 0.016, 0.014) * (vz > 0.02)
        colors = _tint(colors, np.array([0.86, 0.52, 0.48]), 0.10 * blush)
    tip = _gauss(vx, vy, 0.0, -0.032 + NOSE_LIFT, 0.008, 0.008) * (vz > 0.05)
    colors = _tint(colors, np.array([0.86, 0.55, 0.50]), 0.08 * tip)
    beard = _smoothstep(-0.066, -0.085, vy) * _smoothstep(0.072, 0.045, np.abs(vx)) * (vz > 0.0)
    colors *= 1 - 0.07 * np.clip(beard, 0, 1)[:, None] * np.array([1.0, 0.9, 0.8])
    colors *= 1 + 0.03 * _smoothstep(0.045, 0.075, vy)[:, None]
    # where light reaches less: the eye sockets (a lid crease above the eye, beside the nose,
    # below the lower lid)
    shade = np.zeros(len(vx))
    for sgn in (1, -1):
        shade += 0.16 * _gauss(vx, vy, sgn * (EYE_X - 0.004), EYE_Y + 0.009, 0.011, 0.004)
        shade += 0.10 * _gauss(vx, vy, sgn * (EYE_X - 0.012), EYE_Y - 0.002, 0.004, 0.008)
        shade += 0.08 * _gauss(vx, vy, sgn * (EYE_X - 0.002), EYE_Y - 0.011, 0.010, 0.003)
    colors *= 1 - np.clip(2.2 * shade, 0, 0.66)[:, None] * (vz > 0.02)[:, None]
    # light the per-vertex shading cannot take away (it casts no shadows): beside the nose,
    # the folds from the nose to the mouth corners, under the nose and under the lower lip
    occluded = np.zeros(len(vx))
    for sgn in (1, -1):
        occluded += 0.09 * _gauss(vx, vy, sgn * 0.0095, -0.014 + NOSE_LIFT, 0.0022, 0.013)
        occluded += 0.05 * _gauss(vx, vy, sgn * 0.021, -0.047, 0.004, 0.009)
    occluded += 0.12 * _gauss(vx, vy, 0.0, -0.0405 + NOSE_LIFT, 0.009, 0.0025)
    occluded += 0.07 * _gauss(vx, vy, 0.0, -0.0665, 0.013, 0.003)
    colors *= 1 - np.clip(occluded, 0, 0.24)[:, None] * (vz > 0.02)[:, None]
    mottle = np.sin(410 * vx + 37 * vy) * np.sin(380 * vy - 29 * vz) * np.sin(350 * vz + 41 * vx)
    colors *= 1 + 0.015 * mottle[:, None]
    # the vermilion: an upper lip with a cupid's bow and a fuller lower lip, edged sharply
    across = np.clip(1 - (vx / 0.0225) ** 2, 0, 1)
    top = (
        MOUTH_Y
        + 0.0058 * across**0.6
        + 0.0010 * np.exp(-(((np.abs(vx) - 0.0048) / 0.0030) ** 2))
        - 0.0009 * np.exp(-((vx / 0.0022) ** 2))
    )
    bottom = MOUTH_Y - 0.0078 * across**0.7
    lip_w = (
        _smoothstep(top + 0.0010, top - 0.0010, vy)
        * _smoothstep(bottom - 0.0010, bottom + 0.0010, vy)
        * (vz > 0.03)
        * _smoothstep(0.0235, 0.0215, np.abs(vx))
    )
    colors = _tint(colors, LIP, lip_w)
    # the commissures: a small shadowed crease where the lips meet (it moves with the corners)
    for sgn in (1, -1):
        crease = np.exp(
            -0.5 * (((vx - sgn * MOUTH_HALF_W) / 0.0016) ** 2 + ((vy - MOUTH_Y) / 0.0010) ** 2)
        )
        colors *= 1 - 0.55 * (crease * (vz > 0.03))[:, None]
    # nostrils and the shadowed underside of the nose
    for sgn in (1, -1):
        nostril = np.exp(
            -0.5 * (((vx - sgn * 0.0062) / 0.0026) ** 2 + ((vy + 0.0385 - NOSE_LIFT) / 0.0016) ** 2)
        )
        colors *= 1 - 0.55 * (nostril * (vz > 0.05))[:, None]
    # inner lips: lip colour at the edge, darkening to the mouth interior
    for inner in (upper_inner, lower_inner):
        ring = np.arange(len(inner)) // (len(inner) // 3)
        shade = np.array([0.55, 0.20, 0.0])[np.minimum(ring, 2)]
        colors[inner] = LIP * shade[:, None] + MOUTH * (1 - shade[:, None])
    for side in (1, -1):
        bx = (vx - side * (EYE_X + 0.002)) / 0.020
        by = (vy - (EYE_Y + 0.016 - 0.004 * bx**2)) / 0.0028
        brow_w = (
            0.9 * _smoothstep(0.2, 0.6, np.exp(-0.5 * (bx**8 + (by * 1.25) ** 2))) * (vz > 0.03)
        )
        colors = _tint(colors, BROW, brow_w)
    # lash lines: dark along the upper lid margin, faint along the lower
    for rim in (lid_rim,):
        upper = verts[rim, 1] > EYE_Y + 0.0008
        colors[rim[upper]] = LASH
        colors[rim[~upper]] = colors[rim[~upper]] * 0.75 + LASH * 0.25
    # the hairline: high over the forehead, receding a little at the temples, down the sides
    # in front of the ears (sideburns) and low at the nape
    ax = np.abs(vx)
    hairline = (
        0.088
        - 0.010 * (ax / 0.045) ** 2
        + 0.005 * np.exp(-0.5 * ((ax - 0.036) / 0.008) ** 2)
        - 0.075 * _smoothstep(0.050, 0.070, ax) * _smoothstep(0.030, -0.005, vz)
        - 0.05 * _smoothstep(0.02, -0.06, vz)
    )
    hair_w = _smoothstep(hairline - 0.004, hairline + 0.008, vy)
    # the ears stay free: the hair is cut round them, above and behind
    ear_zone = np.exp(-0.5 * (((vy + 0.004) / 0.024) ** 4 + ((vz + 0.014) / 0.022) ** 4))
    hair_w *= 1 - ear_zone * _smoothstep(0.055, 0.068, ax)
    hair_w = np.maximum(hair_w, _smoothstep(0.0, -0.04, vz) * _smoothstep(-0.06, -0.02, vy))
    hair_w *= ~np.isin(np.arange(len(verts)), np.concatenate([upper_inner, lower_inner]))
    paint = _smoothstep(0.2, 0.32, hair_w)  # the scalp is dark under the hair shell
    colors = _tint(colors, HAIR, paint)

    # drop the vertices the eye openings left unused, renumbering everything that refers to them
    used = np.unique(faces)
    remap = np.full(len(verts), -1)
    remap[used] = np.arange(len(used))
    info = {
        "upper_slit": remap[upper_idx],
        "lower_slit": remap[lower_idx],
        "corners": remap[corners],
        "upper_inner": remap[upper_inner],
        "lower_inner": remap[lower_inner],
        "hair_w": hair_w[used],
    }
    return _Part(verts[used], remap[faces], colors[used], "skin"), info


def _almond(side: int, angle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) of the lid opening's contour at polar ``angle`` (radians) around the eye."""
    c, sn = np.cos(angle), np.sin(angle)
    return side * EYE_X + EYE_HALF_W * c, EYE_Y + 0.0008 * (1 - c**2) + EYE_HALF_H * sn


def _face_edges(
    faces: np.ndarray, *, within: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The distinct edges of triangles ``faces`` (m, 3) as sorted vertex pairs (k, 2), in
    lexicographic order, and how many faces share each; ``within``: only edges whose two
    vertices are among these. Sorted as one int64 key per edge (``np.unique(axis=0)`` sorts
    rows as records, several times slower on a 50,000-face head)."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    if within is not None:
        edges = edges[np.isin(edges, within).all(axis=1)]
    edges = edges.astype(np.int64)
    n = int(edges.max()) + 1 if len(edges) else 1
    key, counts = np.unique(edges[:, 0] * n + edges[:, 1], return_counts=True)
    return np.stack([key // n, key % n], axis=1), counts


def _edge_graph(n: int, faces: np.ndarray) -> tuple[sparse.csr_matrix, np.ndarray, np.ndarray]:
    """The mesh's vertex graph: (n, n) adjacency (1 per edge), each vertex's degree, and the
    vertices on the border (edges of one face only)."""
    uniq, counts = _face_edges(faces)
    adj = sparse.coo_matrix(
        (np.ones(2 * len(uniq)), (np.r_[uniq[:, 0], uniq[:, 1]], np.r_[uniq[:, 1], uniq[:, 0]])),
        shape=(n, n),
    ).tocsr()
    return adj, np.asarray(adj.sum(axis=1)).ravel(), np.unique(uniq[counts == 1])


def _smooth_eye_openings(verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Move the rim of each eye opening onto the almond contour and relax the skin around it
    (umbrella smoothing in x, y with the rim and the outer skin held), so the lid margin is a
    smooth curve rather than the grid's staircase. Returns the vertices and the rim indices."""
    n = len(verts)
    adj, degree, boundary = _edge_graph(n, faces)
    verts = verts.copy()
    rims = []
    for side in (1, -1):
        rel_x = (verts[:, 0] - side * EYE_X) / EYE_HALF_W
        rel_y = (verts[:, 1] - EYE_Y) / EYE_HALF_H
        rho = np.hypot(rel_x, rel_y)
        front = verts[:, 2] > 0
        rim = boundary[(rho[boundary] < 1.6) & front[boundary]]
        verts[rim, 0], verts[rim, 1] = _almond(side, np.arctan2(rel_y[rim], rel_x[rim]))
        band = np.nonzero(front & (rho < 2.2) & (degree > 1) & np.isin(np.arange(n), faces))[0]
        band = np.setdiff1d(band, rim)
        for _ in range(30):
            mean = (adj @ verts[:, :2]) / np.maximum(degree, 1)[:, None]
            verts[band, :2] = 0.5 * verts[band, :2] + 0.5 * mean[band]
        rims.append(rim)
    return verts, np.concatenate(rims)


def _eye_centre(side: int) -> np.ndarray:
    return np.array([side * EYE_X, EYE_Y, _eye_z()])


@cache
def _eye_z() -> float:
    # the eyeball's front sits 2 mm in front of the undeformed socket surface
    z_surface = HEAD_D * np.sqrt(max(0.0, 1 - (EYE_X / HEAD_W) ** 2 - (EYE_Y / HEAD_H) ** 2))
    z_surface += float(_front_surface(np.array(EYE_X), np.array(EYE_Y), np.array(z_surface)))
    return z_surface + 0.002 - EYE_R


def _eyeball(side: int) -> _Part:
    """A sphere whose rings are centred on the line of sight, so the iris and pupil edges are
    circles (rings on each edge); the iris darkens towards its rim (the limbal ring)."""
    centre = _eye_centre(side)
    # rings either side of the pupil's edge (12 degrees) and the iris' edge (36 degrees)
    alpha = np.radians(
        [0.5, 4, 8, 11.5, 12.5, 16, 20, 24, 28, 32, 35.5, 36.5, 40, 46, 54, 64, 75, 90, 110, 135,
         160, 179.5]
    )  # fmt: skip
    theta = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    a, t = np.meshgrid(alpha, theta, indexing="ij")
    d = np.stack([np.sin(a) * np.cos(t), np.sin(a) * np.sin(t), np.cos(a)], -1).reshape(-1, 3)
    faces = _grid_faces(len(alpha), len(theta), wrap=True)
    tri = d[faces]
    outward = np.einsum(
        "fi,fi->f", np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), tri.mean(1)
    )
    faces = np.where((outward < 0)[:, None], faces[:, ::-1], faces)
    # caps at the poles
    n = len(d)
    d = np.vstack([d, [[0, 0, 1], [0, 0, -1]]])
    ring0 = np.arange(len(theta))
    ring_last = (len(alpha) - 1) * len(theta) + ring0
    cap = [[n, ring0[i], ring0[(i + 1) % len(theta)]] for i in ring0]
    cap += [[n + 1, ring_last[(i + 1) % len(theta)], ring_last[i]] for i in ring0]
    cap = np.array(cap)
    tri = d[cap]
    outward = np.einsum(
        "fi,fi->f", np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), tri.mean(1)
    )
    cap = np.where((outward < 0)[:, None], cap[:, ::-1], cap)
    faces = np.vstack([faces, cap])
    ang = np.degrees(np.arccos(np.clip(d[:, 2], -1, 1)))
    colors = np.tile(SCLERA, (len(d), 1))
    iris = ang < 36
    limbal = np.clip((ang - 26) / 10, 0, 1)[:, None]
    colors[iris] = (IRIS * (1 - 0.55 * limbal) + 0.02 * limbal)[iris]
    colors[ang < 12] = PUPIL
    # the cornea bulges a little over the iris
    radius = EYE_R * (1 + 0.06 * np.clip(1 - ang / 36, 0, 1) ** 2)
    return _Part(
        centre + d * radius[:, None], faces, colors, f"eye_{'left' if side > 0 else 'right'}"
    )


def _mouth_parts(surface: np.ndarray, info: dict) -> list[_Part]:
    lip_z = float(surface[info["upper_slit"]][:, 2].max())
    centre = np.array([0.0, MOUTH_Y - 0.001, lip_z - 0.042])
    bag_v, bag_f = _sphere(centre, np.array([0.030, 0.015, 0.028]), 14, 24)
    bag = _Part(bag_v, bag_f[:, ::-1], np.tile(MOUTH, (len(bag_v), 1)), "mouth")

    def arch(y0: float, height: float, inset: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A closed band of teeth along an arc: vertices, outward-wound faces, colours (each
        tooth edged by a faint gap, darker towards the back of the mouth)."""
        ang = np.linspace(-0.95, 0.95, 49)
        radius = 0.024
        cz = lip_z - inset - radius
        rows = []
        for dy in (0.0, height):
            for depth in (0.0, 0.004):
                r = radius - depth
                rows.append(
                    np.stack(
                        [r * np.sin(ang), np.full_like(ang, y0 + dy), cz + r * np.cos(ang)], -1
                    )
                )
        # each side (front, top, back, bottom) has its own vertices: crisp edges, flat normals
        sides = ((0, 2), (2, 3), (3, 1), (1, 0))
        v = np.vstack([rows[k] for pair in sides for k in pair])
        n = len(ang)
        faces = []
        for s_i in range(len(sides)):
            a, b = 2 * s_i, 2 * s_i + 1
            for i in range(n - 1):
                faces += [
                    [a * n + i, b * n + i, a * n + i + 1],
                    [a * n + i + 1, b * n + i, b * n + i + 1],
                ]
        faces = np.array(faces)
        # wind every face outwards from the band's core line
        tri = v[faces]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        mid = tri.mean(axis=1)
        a_mid = np.arctan2(mid[:, 0], mid[:, 2] - cz)
        core = np.stack(
            [(radius - 0.002) * np.sin(a_mid), np.full(len(mid), y0 + height / 2),
             cz + (radius - 0.002) * np.cos(a_mid)], -1)  # fmt: skip
        flip = np.einsum("fi,fi->f", normal, mid - core) < 0
        faces[flip] = faces[flip][:, ::-1]
        a_all = np.tile(ang, 8)
        gap = _smoothstep(0.92, 1.0, np.cos(2 * np.pi * a_all / 0.30))
        shade = (1 - 0.30 * gap) * (1 - 0.40 * np.abs(a_all) / 0.95)
        return v, faces, TEETH * shade[:, None]

    up_v, up_f, up_c = arch(MOUTH_Y - 0.0022, 0.0095, 0.0080)  # shows 2 mm below the upper lip
    lo_v, lo_f, lo_c = arch(MOUTH_Y - 0.0078, 0.0060, 0.0135)
    tongue_v, tongue_f = _sphere(
        np.array([0.0, MOUTH_Y - 0.011, lip_z - 0.034]), np.array([0.016, 0.005, 0.016]), 10, 18
    )
    return [
        bag,
        _Part(up_v, up_f, up_c, "teeth_upper"),
        _Part(lo_v, lo_f, lo_c, "teeth_lower"),
        _Part(tongue_v, tongue_f, np.tile(TONGUE, (len(tongue_v), 1)), "tongue"),
    ]


def _body() -> list[_Part]:
    neck_v = []
    rows, cols = 16, 40
    ang = np.linspace(-np.pi, np.pi, cols, endpoint=False)
    for i, yy in enumerate(np.linspace(-0.07, -0.21, rows)):
        r = 0.051 + 0.014 * (i / rows) ** 2  # widening into the trapezius
        neck_v.append(
            np.stack([r * np.sin(ang), np.full(cols, yy), -0.014 + 0.92 * r * np.cos(ang)], -1)
        )
    neck_v = np.vstack(neck_v)
    neck_f = _grid_faces(rows, cols, wrap=True)[:, ::-1]  # rows go down here: flip the winding
    # the head shades the neck (the renderer casts no shadows): darkest under the jaw and
    # down past where the chin reaches with the jaw open (-0.111 m), fading to the shoulders
    under_jaw = _smoothstep(-0.17, -0.095, neck_v[:, 1]) * _smoothstep(-0.02, 0.03, neck_v[:, 2])
    neck_c = np.tile(SKIN * 0.95, (len(neck_v), 1)) * (1 - 0.6 * under_jaw)[:, None]
    torso_v, torso_f = _torso()
    return [
        _Part(neck_v, neck_f, neck_c, "neck"),
        _Part(torso_v, torso_f, np.tile(CLOTH, (len(torso_v), 1)), "torso"),
    ]


def _torso() -> tuple[np.ndarray, np.ndarray]:
    """Shoulders and chest: rounded-box cross sections (superellipses) that grow from the base
    of the neck along the slope of the trapezius to the shoulders, closed at the top."""
    rows, cols = 22, 48
    ang = np.linspace(-np.pi, np.pi, cols, endpoint=False)
    ys = np.linspace(-0.168, -0.42, rows)
    rings = []
    for yy in ys:
        spread = _smoothstep(-0.168, -0.240, yy)
        half_w = 0.042 + 0.164 * spread**0.7
        half_d = 0.040 + 0.064 * _smoothstep(-0.168, -0.26, yy)
        c, sn = np.cos(ang), np.sin(ang)
        k = 2.0 + 1.6 * spread  # round at the neck, boxier at the shoulders
        x = half_w * np.sign(sn) * np.abs(sn) ** (2 / k)
        z = -0.02 + half_d * np.sign(c) * np.abs(c) ** (2 / k)
        rings.append(np.stack([x, np.full(cols, yy), z], -1))
    verts = np.vstack([*rings, [[0.0, -0.168, -0.02]]])
    faces = _grid_faces(rows, cols, wrap=True)[:, ::-1]  # rows go down: flip the winding
    top = len(verts) - 1
    cap = np.stack([np.full(cols, top), np.arange(cols), (np.arange(cols) + 1) % cols], -1)
    return verts, np.vstack([faces, cap[:, ::-1]])


def _ear(side: int) -> _Part:
    """A flattened shell with a hollow (the concha) on its outer face, wider at the top than at
    the lobe, leaning back and flaring away from the head."""
    v, f = _sphere(np.zeros(3), np.array([0.0055, 0.031, 0.017]), 16, 26)
    outer = v[:, 0] > 0
    concha = np.exp(-0.5 * (((v[:, 1] + 0.004) / 0.010) ** 2 + ((v[:, 2] + 0.001) / 0.0065) ** 2))
    v[:, 0] -= 0.0075 * concha * outer
    v[:, 2] *= 1 - 0.30 * _smoothstep(0.0, -0.028, v[:, 1])
    lean, flare = np.radians(-12.0), np.radians(-38.0)
    rx = np.array([[1, 0, 0], [0, np.cos(lean), -np.sin(lean)], [0, np.sin(lean), np.cos(lean)]])
    ry = np.array(
        [[np.cos(flare), 0, np.sin(flare)], [0, 1, 0], [-np.sin(flare), 0, np.cos(flare)]]
    )
    v = v @ (ry @ rx).T
    colors = np.tile(EAR, (len(v), 1)) * (1 - 0.25 * (concha * outer))[:, None]
    if side < 0:
        v[:, 0] *= -1
        f = f[:, ::-1]
    v = v + np.array([side * 0.0765, -0.004, -0.014])
    return _Part(v, f, colors, f"ear_{'left' if side > 0 else 'right'}")


def _hair(skin: _Part, hair_w: np.ndarray) -> _Part:
    """A shell of hair over the painted scalp: thickest on the crown, thinning to nothing at
    the hairline, with faint strands."""
    v = skin.vertices
    keep = (hair_w > 0.3)[skin.faces].any(axis=1)
    faces = skin.faces[keep]
    used = np.unique(faces)
    remap = np.full(len(v), -1)
    remap[used] = np.arange(len(used))
    out = v[used] - np.array([0.0, -0.005, -0.012])
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    thick = 0.011 * _smoothstep(0.3, 0.95, hair_w[used])
    thick *= 1 + 0.5 * _smoothstep(0.02, 0.10, v[used, 1])
    # smooth the thickness over the shell (the grid is coarse at the sides, where a step in
    # thickness from one column to the next would stick out of the silhouette as a spike);
    # the shell's own border stays on the scalp
    adj, degree, _ = _edge_graph(len(used), remap[faces])
    border = hair_w[used] < 0.3
    for _ in range(12):
        thick = 0.5 * thick + 0.5 * (adj @ thick) / np.maximum(degree, 1)
        thick[border] = 0.0
    hv = v[used] + out * thick[:, None]
    streak = 1 + 0.12 * np.sin(90 * np.arctan2(v[used, 0], v[used, 2]) + 50 * v[used, 1])
    # the border onto the hairline itself: each border vertex moves to where hair_w crosses
    # 0.3 on its edges to the inside (averaged), so the edge follows the hairline's curve, not
    # the grid's triangles; its colour is the skin's there, a little covered by hair
    base = skin.colors[used].copy()
    e = adj.tocoo()
    w = hair_w[used]
    pick = border[e.row] & ~border[e.col]
    b_i, c_i = e.row[pick], e.col[pick]
    t = ((0.3 - w[b_i]) / np.maximum(w[c_i] - w[b_i], 1e-9))[:, None]
    cnt = np.bincount(b_i, minlength=len(used)).astype(float)
    moved = cnt > 0
    for arr, src in ((hv, v[used]), (base, skin.colors[used])):
        acc = np.zeros((len(used), 3))
        np.add.at(acc, b_i, src[b_i] + t * (src[c_i] - src[b_i]))
        arr[moved] = acc[moved] / cnt[moved, None]
    cover = np.where(border, 0.4, _smoothstep(0.3, 0.75, w))
    colors = _tint(base, HAIR * streak[:, None], cover)
    return _Part(hv, remap[faces], colors, "hair")


@cache
def _default_head_cached() -> Avatar:
    skin, info = _head_surface()
    parts = [
        skin,
        _eyeball(1),
        _eyeball(-1),
        *_mouth_parts(skin.vertices, info),
        *_body(),
        _ear(1),
        _ear(-1),
        _hair(skin, info["hair_w"]),
    ]
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts])
    verts = np.vstack([p.vertices for p in parts]).astype(np.float32)
    faces = np.vstack([p.faces + off for p, off in zip(parts, offsets, strict=False)])
    # the inner lips are seen from both sides: they get both windings (back faces are culled)
    two_sided = np.concatenate([info["upper_inner"], info["lower_inner"]])
    thin = np.isin(faces, two_sided).all(axis=1)
    faces = np.vstack([faces, faces[thin][:, ::-1]])
    colors = np.vstack([p.colors for p in parts]).astype(np.float32)
    part_index = {
        p.name: np.arange(off, off + len(p.vertices))
        for p, off in zip(parts, offsets, strict=False)
    }
    part_index["lips_inner"] = np.concatenate([info["upper_inner"], info["lower_inner"]])
    part_index["lip_edges"] = np.concatenate(
        [info["upper_slit"], info["lower_slit"], info["corners"]]
    )
    mid_upper = int(info["upper_slit"][np.argmin(np.abs(verts[info["upper_slit"], 0]))])
    mid_lower = int(info["lower_slit"][np.argmin(np.abs(verts[info["lower_slit"], 0]))])
    corners = info["corners"]
    left, right = (corners[1], corners[0]) if verts[corners[1], 0] > 0 else (corners[0], corners[1])
    landmarks = {
        "upper_lip": mid_upper,
        "lower_lip": mid_lower,
        "mouth_left": int(left),
        "mouth_right": int(right),
        "nose_tip": int(
            np.argmax(np.where(np.abs(verts[:, 0]) < 0.003, verts[:, 2], -1)[: len(skin.vertices)])
        ),
        "chin": int(
            np.argmin(
                np.where((np.abs(verts[:, 0]) < 0.004) & (verts[:, 2] > 0.05), verts[:, 1], 1)[
                    : len(skin.vertices)
                ]
            )
        ),
    }
    targets = _build_targets(verts, part_index, info)
    for name, delta in targets.items():
        targets[name] = delta.astype(np.float32)
    lid, margins = _lid_margins(verts, faces, part_index)
    landmarks.update(lid)
    part_index.update(margins)
    return Avatar(
        verts,
        faces,
        targets,
        landmarks,
        colors,
        "facelab default head",
        part_index,
        skeleton=_skeleton(verts, part_index),
        gloss=_gloss(len(verts), part_index),
        source={"kind": "default"},
    )


#: joint name, parent index, rest pivot (m)
_JOINTS = (
    ("root", -1, (0.0, -0.24, -0.02)),
    ("neck", 0, (0.0, -0.175, -0.015)),
    ("head", 1, (0.0, -0.045, -0.02)),  # about the ear lobes (atlanto-occipital joint)
    ("eye_left", 2, tuple(_eye_centre(1))),
    ("eye_right", 2, tuple(_eye_centre(-1))),
)


def _skeleton(v: np.ndarray, parts: dict[str, np.ndarray]) -> Skeleton:
    """Root (torso), neck, head and eye joints. The neck bends over its length (head weight
    rising from 0 at y = -0.12 m to 1 at -0.07 m, neck weight from the shoulders up); the
    face, jaw, teeth, ears and hair follow the head; each eyeball its eye joint."""
    n = len(v)
    y, z = v[:, 1], v[:, 2]
    f_head = _smoothstep(-0.12, -0.07, y)
    f_neck = _smoothstep(-0.205, -0.16, y)
    w_head = np.ones(n)
    neck = parts["neck"]
    w_head[neck] = f_head[neck]
    skin = parts["skin"]
    w_head[skin] = np.maximum(f_head[skin], _smoothstep(-0.01, 0.03, z[skin]))
    w_neck = (1 - w_head) * np.where(np.isin(np.arange(n), neck), f_neck, 1.0)
    w_root = 1 - w_head - w_neck
    joints = np.zeros((n, 4), np.int64)
    weights = np.zeros((n, 4))
    joints[:, 0], joints[:, 1], joints[:, 2] = 2, 1, 0
    weights[:, 0], weights[:, 1], weights[:, 2] = w_head, w_neck, w_root
    torso = parts["torso"]
    weights[torso] = [1.0, 0.0, 0.0, 0.0]
    joints[torso, 0] = 0
    for j, part in ((3, "eye_left"), (4, "eye_right")):
        joints[parts[part]] = [j, 0, 0, 0]
        weights[parts[part]] = [1.0, 0.0, 0.0, 0.0]
    return Skeleton(
        tuple(name for name, _, _ in _JOINTS),
        np.array([p for _, p, _ in _JOINTS]),
        np.array([c for _, _, c in _JOINTS]),
        joints,
        weights,
        {"neck": 1, "head": 2, "eye_left": 3, "eye_right": 4},
    )


def _gloss(n: int, parts: dict[str, np.ndarray]) -> np.ndarray:
    """Specular strength per vertex: wet eyes and lips shine, teeth and cloth are matte."""
    gloss = np.full(n, 0.35, np.float32)
    for part, value in (
        ("eye_left", 1.0), ("eye_right", 1.0), ("lips_inner", 0.6), ("teeth_upper", 0.12),
        ("teeth_lower", 0.12), ("tongue", 0.45), ("mouth", 0.0), ("hair", 0.5),
        ("ear_left", 0.25), ("ear_right", 0.25), ("torso", 0.05), ("neck", 0.25),
    ):  # fmt: skip
        gloss[parts[part]] = value
    return gloss


def default_head() -> Avatar:
    """The built-in head (cached; returns a shallow copy)."""
    h = _default_head_cached()
    return h.replace(targets=dict(h.targets), landmarks=dict(h.landmarks), parts=dict(h.parts))


def _lid_margins(
    verts: np.ndarray, faces: np.ndarray, parts: dict[str, np.ndarray]
) -> tuple[dict[str, int], dict[str, np.ndarray]]:
    """The eye openings' edges (the skin's boundary around each eye): landmarks
    ``upper_lid_*`` / ``lower_lid_*`` above and below each pupil, and parts ``lid_upper_*`` /
    ``lid_lower_*``, every margin vertex above / below the opening's midline."""
    skin = parts["skin"]
    uniq, counts = _face_edges(faces[np.isin(faces, skin).sum(axis=1) >= 2], within=skin)
    boundary = np.unique(uniq[counts == 1])
    landmarks, margins = {}, {}
    for side, label in ((1, "left"), (-1, "right")):
        near = boundary[
            (np.hypot(verts[boundary, 0] - side * EYE_X, verts[boundary, 1] - EYE_Y) < 0.016)
            & (verts[boundary, 2] > 0)
        ]
        col = near[np.abs(verts[near, 0] - side * EYE_X) < 0.003]
        landmarks[f"upper_lid_{label}"] = int(col[np.argmax(verts[col, 1])])
        landmarks[f"lower_lid_{label}"] = int(col[np.argmin(verts[col, 1])])
        upper = verts[near, 1] > EYE_Y + 0.0008  # the lids' bulge at the pupil (targets)
        margins[f"lid_upper_{label}"] = near[upper]
        margins[f"lid_lower_{label}"] = near[~upper]
    return landmarks, margins


# --------------------------------------------------------------------------- target fields


def _build_targets(
    v: np.ndarray, parts: dict[str, np.ndarray], info: dict
) -> dict[str, np.ndarray]:
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    n = len(v)
    skin = np.zeros(n, bool)
    skin[parts["skin"]] = True
    front = _smoothstep(0.02, 0.06, z) * skin

    upper_set = np.zeros(n, bool)
    upper_set[info["upper_slit"]] = True
    upper_set[info["upper_inner"]] = True
    lower_set = np.zeros(n, bool)
    lower_set[info["lower_slit"]] = True
    lower_set[info["lower_inner"]] = True
    corners = info["corners"]

    # lower face (jaw) weight: below the mouth line, fading up to the cheeks and back to the ears
    # the jaw's upper boundary is the mouth line near the lips and rises towards the cheeks
    boundary = MOUTH_Y + 0.012 * _smoothstep(0.024, 0.050, np.abs(x))
    # the lower lip and chin sit on the mandible: below the lips' middle the jaw's weight is
    # full within 1.5 mm of the mouth line; towards the cheeks the skin takes 8 mm to follow
    ramp = 0.0015 + 0.0065 * _smoothstep(0.012, 0.030, np.abs(x))
    below = _smoothstep(boundary + 0.0005, boundary - ramp, y)
    # soft lips: near the mouth the opening is lens-shaped, the corners stay put
    lens = np.clip(1 - (x / MOUTH_HALF_W) ** 2, 0, 1) ** 1.5
    near_mouth = np.exp(-0.5 * ((y - MOUTH_Y) / 0.010) ** 2) * np.exp(-0.5 * (x / 0.035) ** 8)
    jaw_w = below * _smoothstep(-0.055, 0.0, z) * skin
    jaw_w = jaw_w * (1 - near_mouth * (1 - (0.25 + 0.75 * lens)))
    jaw_w[lower_set] = 0.25 + 0.75 * lens[lower_set]
    jaw_w[info["upper_slit"]] = 0.0
    jaw_w[info["upper_inner"]] = 0.0
    jaw_w[corners] = 0.0
    for name in ("teeth_lower", "tongue"):
        jaw_w[parts[name]] = 1.0
    jaw_w[parts["mouth"]] = np.clip((MOUTH_Y + 0.004 - y[parts["mouth"]]) / 0.02, 0, 1) * 0.8

    # lip regions (skin around the mouth), split into upper and lower
    mouth_d = np.hypot(x / 0.030, (y - MOUTH_Y) / 0.017)
    lips = np.exp(-0.5 * mouth_d**4) * front
    lips[upper_set | lower_set] = 1.0
    lips[corners] = 1.0
    is_lower = (y < MOUTH_Y - 1e-5) | lower_set
    is_lower[info["upper_slit"]] = False
    is_lower[info["upper_inner"]] = False
    lower_lips = lips * is_lower
    upper_lips = lips * ~is_lower
    side_l = _smoothstep(-0.006, 0.006, x)  # the avatar's left half (+x)
    side_r = 1 - side_l
    corner_l = (
        np.exp(-0.5 * (((x - MOUTH_HALF_W) / 0.010) ** 2 + ((y - MOUTH_Y) / 0.011) ** 2)) * front
    )
    corner_r = (
        np.exp(-0.5 * (((x + MOUTH_HALF_W) / 0.010) ** 2 + ((y - MOUTH_Y) / 0.011) ** 2)) * front
    )
    # keep the inner lips moving with their edge
    for s in (corner_l, corner_r):
        s[info["upper_inner"]] = np.interp(
            x[info["upper_inner"]],
            x[info["upper_slit"]][np.argsort(x[info["upper_slit"]])],
            s[info["upper_slit"]][np.argsort(x[info["upper_slit"]])],
        )
        s[info["lower_inner"]] = np.interp(
            x[info["lower_inner"]],
            x[info["lower_slit"]][np.argsort(x[info["lower_slit"]])],
            s[info["lower_slit"]][np.argsort(x[info["lower_slit"]])],
        )

    # lip body: 0 on the slit edge and inner lips, 1 from 4 mm above/below it (so shapes that
    # press or roll the lips never push one lip edge across the other)
    lip_body = _smoothstep(0.0, 0.004, np.abs(y - MOUTH_Y)) * ~(upper_set | lower_set)

    t: dict[str, np.ndarray] = {}
    zero = np.zeros((n, 3))

    def field(
        dx: np.ndarray | float, dy: np.ndarray | float, dz: np.ndarray | float, w: np.ndarray
    ) -> np.ndarray:
        return np.stack(
            [
                np.broadcast_to(dx, (n,)) * w,
                np.broadcast_to(dy, (n,)) * w,
                np.broadcast_to(dz, (n,)) * w,
            ],
            -1,
        )

    # jaw
    ang = np.radians(-18.0)  # chin down and back
    rot = np.array([[1, 0, 0], [0, np.cos(ang), np.sin(ang)], [0, -np.sin(ang), np.cos(ang)]])
    swing = (v - HINGE) @ rot.T + HINGE - v
    # an opening jaw draws the mouth corners in (the lips stretch vertically)
    t["jawOpen"] = swing * jaw_w[:, None] + field(-0.30 * x, 0, 0, corner_l + corner_r)
    t["jawForward"] = field(0, 0, 0.006, jaw_w)
    t["jawLeft"] = field(0.006, 0, 0, jaw_w)
    t["jawRight"] = field(-0.006, 0, 0, jaw_w)
    lip_only_lower = lower_lips * _smoothstep(MOUTH_Y - 0.013, MOUTH_Y - 0.003, y)
    lip_only_lower[lower_set] = 1.0
    t["mouthClose"] = -t["jawOpen"] * lip_only_lower[:, None]

    # rounding: corners towards the midline, lips forward; funnel opens, pucker stays closed
    t["mouthFunnel"] = (
        field(-0.42 * x, 0, 0.011, lips)
        + field(0, 0.0015, 0, upper_lips)
        + field(0, -0.0020, 0, lower_lips)
    )
    # pursed lips press together: the upper lip comes down in front, the lower one tucks
    # behind it (alone, the lower edge passes up to 7 mm behind the upper lip; with the jaw
    # of an う it closes the gap)
    t["mouthPucker"] = (
        field(-0.50 * x, 0, 0.013, lips)
        + field(0, 0, 0.002, upper_lips + lower_lips)
        + field(0, -0.0050, 0.0015, upper_lips * _midlip(x))
        + field(0, 0.0050, -0.0015, lower_lips * _midlip(x))
    )
    t["mouthLeft"] = field(0.007, 0, 0, lips)
    t["mouthRight"] = field(-0.007, 0, 0, lips)
    for side, cw, sw in (("Left", corner_l, side_l), ("Right", corner_r, side_r)):
        sgn = 1.0 if side == "Left" else -1.0
        t[f"mouthSmile{side}"] = field(sgn * 0.008, 0.0075, -0.003, cw) + field(
            0, 0.0025, 0.001, _cheek(x, y, sgn) * front
        )
        t[f"mouthFrown{side}"] = field(sgn * 0.001, -0.0065, 0, cw)
        t[f"mouthDimple{side}"] = field(sgn * 0.002, 0.0005, -0.005, cw)
        # stretched lips thin and the lower lip is drawn down off the teeth
        t[f"mouthStretch{side}"] = field(sgn * 0.0190, -0.0025, -0.001, cw) + field(
            0, -0.0045, 0, lower_lips * sw * _midlip(x)
        )
        t[f"mouthPress{side}"] = field(0, 0.0022, -0.0005, lower_lips * sw * lip_body) + field(
            0, -0.0012, -0.0005, upper_lips * sw * lip_body
        )
        t[f"mouthLowerDown{side}"] = field(0, -0.0070, 0.0008, lower_lips * sw * _midlip(x))
        t[f"mouthUpperUp{side}"] = field(0, 0.0060, 0.0008, upper_lips * sw * _midlip(x))
    # rolls turn the lip inwards: back and towards the slit, the edge itself only goes back
    t["mouthRollLower"] = field(0, 0.0020, -0.0045, lip_only_lower * lip_body) + field(
        0, 0, -0.0045, lip_only_lower * (1 - lip_body)
    )
    upper_lip_only = upper_lips * _smoothstep(MOUTH_Y + 0.016, MOUTH_Y + 0.003, y)
    upper_lip_only[upper_set] = 1.0
    t["mouthRollUpper"] = field(0, -0.0020, -0.0045, upper_lip_only * lip_body) + field(
        0, 0, -0.0045, upper_lip_only * (1 - lip_body)
    )
    t["mouthShrugLower"] = field(0, 0.0025, 0.0035, lower_lips * lip_body) + field(
        0, 0, 0.0035, lower_lips * (1 - lip_body)
    )
    t["mouthShrugUpper"] = field(0, 0.0020, 0.0035, upper_lips)

    # eyes and lids
    for side, sgn in (("Left", 1), ("Right", -1)):
        ec = _eye_centre(sgn)
        eye = np.zeros(n, bool)
        eye[parts[f"eye_{side.lower()}"]] = True
        dxe = x - sgn * EYE_X
        d = np.clip(dxe / EYE_HALF_W, -1, 1)
        bulge = EYE_Y + 0.0008 * (1 - d**2)
        upper_margin = bulge + EYE_HALF_H * np.sqrt(1 - d**2)
        lower_margin = bulge - EYE_HALF_H * np.sqrt(1 - d**2)
        near = (np.abs(dxe) < 0.022) & skin & (z > 0.03)
        across = _smoothstep(0.019, 0.012, np.abs(dxe))
        upper_lid = near * (y > bulge) * _smoothstep(0.012, 0.004, y - upper_margin) * across
        lower_lid = near * (y <= bulge) * _smoothstep(-0.010, -0.003, y - lower_margin) * across
        # blink: the upper margin comes down to 0.5 mm above the lower margin; the lid skin
        # up to LID_EXTENT above it follows, compressed near the margin by a monotone map
        # (no fold), so the brow stays put; vertices stay on a shell around the eyeball
        gap = np.clip(upper_margin - lower_margin - 0.0005, 0.0, None)
        u = y - upper_margin
        lid_zone = near * (y > bulge) * (u >= -1e-4) * (u < LID_EXTENT)
        uu = np.clip(u / LID_EXTENT, 0.0, 1.0)
        g = gap / (2 * EYE_HALF_H - 0.0005)  # 1 mid-lid, 0 beyond the corners (map = identity)
        closed = lower_margin + 0.0005 * g + uu ** (1 + 0.6 * g) * (LID_EXTENT + gap)
        moved = v + np.stack([np.zeros(n), (closed - y) * lid_zone, np.zeros(n)], -1)
        rel = moved - ec
        dist = np.linalg.norm(rel, axis=1)
        shell = (
            ec + rel / np.maximum(dist, 1e-9)[:, None] * np.maximum(dist, EYE_R + 0.0014)[:, None]
        )
        blink = np.where((lid_zone > 0)[:, None], shell - v, 0.0)
        t[f"eyeBlink{side}"] = blink
        # a squint or a cheek raise lifts the lower lid by a share of the opening above it
        # (most mid-lid, nothing at the corners), as the blink lowers the upper one: any mix
        # of them closes the eye evenly along its length (facelab.stimuli.avatar.lids)
        lower_raise = lower_lid * g
        t[f"eyeSquint{side}"] = (
            0.30 * blink
            + field(0, 0.0022, 0.0005, lower_raise)
            + field(0, 0.0012, 0, _cheek(x, y, sgn) * front)
        )
        t[f"eyeWide{side}"] = field(0, 0.0025, 0.0006, upper_lid) + field(0, -0.0008, 0, lower_lid)
        # gaze: rotate the eyeball about its centre (25 degrees), lids follow a little
        for name, axis, deg in (
            ("LookUp", "x", -25),
            ("LookDown", "x", 25),
            ("LookIn", "y", -25 * sgn),
            ("LookOut", "y", 25 * sgn),
        ):
            a = np.radians(deg)
            if axis == "x":
                r = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
            else:
                r = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
            d = ((v - ec) @ r.T + ec - v) * eye[:, None]
            if name == "LookUp":
                d += field(0, 0.0012, 0, upper_lid)
            elif name == "LookDown":
                d += 0.30 * blink
            t[f"eye{name}{side}"] = d
        # brows
        bx = (x - sgn * (EYE_X + 0.002)) / 0.024
        by = (y - (EYE_Y + 0.016)) / 0.012
        brow = np.exp(-0.5 * (bx**4 + by**2)) * front
        inner = brow * _smoothstep(0.6, -0.6, sgn * bx)
        outer = brow * _smoothstep(-0.4, 0.8, sgn * bx)
        t[f"browDown{side}"] = field(-sgn * 0.0015, -0.0040, 0.0005, brow)
        t[f"browOuterUp{side}"] = field(0, 0.0055, 0, outer)
        t[f"_browInnerUp{side}"] = field(0, 0.0060, 0.0003, inner)
        # the cheek rises (AU6): the skin under the eye bunches up and forward, pushing the
        # lower lid up - the eye narrows from below, as in ARKit's reference
        under_eye = np.exp(-0.5 * (((x - sgn * 0.033) / 0.014) ** 2
                                   + ((y - (EYE_Y - 0.017)) / 0.009) ** 2)) * front  # fmt: skip
        under_eye = under_eye * (1 - lower_lid) * ~eye
        t[f"cheekSquint{side}"] = (
            field(0, 0.0030, 0.0008, _cheek(x, y, sgn) * front)
            + field(0, 0.0035, 0.0020, under_eye)
            + field(0, 0.0025, 0.0006, lower_raise)
        )
        nose_side = (
            np.exp(-0.5 * (((x - sgn * 0.010) / 0.006) ** 2 + ((y + 0.030) / 0.008) ** 2)) * front
        )
        t[f"noseSneer{side}"] = field(0, 0.0030, 0.0010, nose_side) + field(
            0, 0.0010, 0, upper_lips * (sgn * x > 0)
        )
    t["browInnerUp"] = t.pop("_browInnerUpLeft") + t.pop("_browInnerUpRight")

    # cheeks and tongue
    normal = np.where(skin[:, None], (v - np.array([0, -0.01, -0.01])), 0)
    normal /= np.maximum(np.linalg.norm(normal, axis=1), 1e-9)[:, None]
    puff = np.exp(-0.5 * (((np.abs(x) - 0.042) / 0.012) ** 2 + ((y + 0.040) / 0.016) ** 2)) * front
    t["cheekPuff"] = normal * 0.006 * puff[:, None] + field(0, 0, 0.002, lips * 0.5)
    tongue = np.zeros(n)
    tongue[parts["tongue"]] = 1.0
    t["tongueOut"] = field(0, -0.002, 0.026, tongue)

    out = {name: t[name] for name in ARKIT_NAMES}
    # lids slide over the eyeballs: no target may move skin into an eye
    for sgn in (1, -1):
        ec = _eye_centre(sgn)
        close = skin & (np.linalg.norm(v - ec, axis=1) < EYE_R + 0.012)
        for delta in out.values():
            moved = v[close] + delta[close]
            rel = moved - ec
            dist = np.linalg.norm(rel, axis=1)
            inside = dist < EYE_R + 0.0010
            if inside.any():
                fixed = ec + rel[inside] / np.maximum(dist[inside], 1e-9)[:, None] * (
                    EYE_R + 0.0010
                )
                idx = np.nonzero(close)[0][inside]
                delta[idx] = fixed - v[idx]
    for vis, mix in VISEME_MIXES.items():
        delta = zero.copy()
        for name, w in mix.items():
            delta += w * out[name]
        out[vis] = delta
    return out


def _cheek(x: np.ndarray, y: np.ndarray, sgn: float) -> np.ndarray:
    return np.exp(-0.5 * (((x - sgn * 0.038) / 0.013) ** 2 + ((y + 0.012) / 0.012) ** 2))


def _midlip(x: np.ndarray) -> np.ndarray:
    """Weight beside the midline (0 at the centre and corners)."""
    return np.exp(-0.5 * ((np.abs(x) - 0.008) / 0.010) ** 2)
