"""Impression stimuli (seed 001, Horii et al.): a learned impression direction in an expression
space, graded levels along it, and eased clips from neutral to the edited expression.

The model, per expression (``fit_impression``):

* samples s_m (N, D): displacements of person m's expression from that person's neutral face -
  ARKit coefficients (D = 52; without a ``neutral`` row the rest pose, all zeros) or mesh
  vertices (D = 3V, a common topology);
* PCA (eq. 1): s̄ the mean displacement, U (K, D) the first K principal axes (K given, or the
  fewest explaining ``variance`` of the variance; K ≤ samples − 1), f_m = U (s_m − s̄);
* the impression direction w (K,), a unit vector in PCA coordinates, by ``svm`` (the seed: the
  normal of a linear SVM between the two label classes), ``mean_diff`` (class means' difference)
  or ``ridge`` (ridge regression on a continuous rating); its sample-space direction
  d = Uᵀ w (D,) is what the model file stores per ARKit name;
* δ: by default one SD of the training projections f_m · w (sample-space units along d);
* leave-one-person-out cross-validation: accuracy (classes) or R² (ratings).

Levels (eq. 2): f̂ = f + q·δ·w, i.e. in sample space ŝ = s̄ + Uᵀ f + q·δ·d (f = 0: the mean
face of the expression; a person's f to start from that person). With ``orthogonal_to_speech``
d is first made orthogonal to the mouth shapes the speech methods use (the columns of the
shipped Z matrices, ARKit space), so an impression can be raised on a talking face without
changing its visemes; d then leaves the PCA subspace and the edit is applied in sample space.

Clips (eq. 3 with eq. 4): X̂_i = X_neutral + e(i / frames)·ŝ. **The easing e replaces the
linear factor i/frame of eq. 3.** e is eq. 4's sigmoid 1/(1 + exp(−k x)) evaluated on
x = 2·i/frames − 1 ∈ [−1, 1] and normalised to run from exactly 0 to exactly 1 (k = 5, the
seed's value, by default); ``linear`` and ``smoothstep`` are the alternatives. A clip has
separate onset (neutral → expression), hold and offset (expression → neutral) durations.
ARKit frames are clipped to [0, 1]; the *realised* level is the clipped face's projection on
d divided by δ.
"""

from __future__ import annotations

import functools
import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from facelab.errors import StageError
from facelab.formats import IMPRESSION_FORMAT
from facelab.stimuli.arkit import ARKIT_NAMES, canonical_arkit_name
from facelab.stimuli.capture.zmatrix import load_z
from facelab.textfiles import read_json, read_rows, read_text

__all__ = [
    "DIRECTION_METHODS",
    "EASINGS",
    "VISIBLE_CHANGE",
    "ExpressionModel",
    "ExpressionSamples",
    "ImpressionModel",
    "ease",
    "envelope",
    "envelope_at",
    "fit_impression",
    "level_visibility",
    "read_arkit_samples",
    "read_vertex_samples",
    "samples_from_captures",
    "speech_basis",
]

DIRECTION_METHODS = ("svm", "mean_diff", "ridge")
EASINGS = ("sigmoid", "linear", "smoothstep")
MODEL_FORMAT = IMPRESSION_FORMAT


# ----------------------------------------------------------------------------- samples


@dataclass(frozen=True)
class ExpressionSamples:
    """One row per (person, expression) sample, displacements from the person's neutral.

    space ``arkit`` (channels: the 52 ARKit names) or ``vertices`` (channels empty; D = 3V);
    persons, expressions (N,) str; labels {column: (N,) str or float}; s (N, D) float64;
    neutral {person: (D,)} the neutral face each displacement is measured from; faces (F, 3)
    for vertex space; sha256 of the input file(s).
    """

    space: str
    persons: np.ndarray
    expressions: np.ndarray
    labels: dict[str, np.ndarray]
    s: np.ndarray
    channels: tuple[str, ...]
    neutral: dict[str, np.ndarray]
    sha256: str
    source: str
    faces: np.ndarray | None = None


def _label_array(values: list[str]) -> np.ndarray:
    """Floats when every value is a number, else strings."""
    try:
        return np.array([float(v) for v in values])
    except ValueError:
        return np.array(values, dtype=object)


def read_arkit_samples(path: Path) -> ExpressionSamples:
    """A CSV with columns ``person, expression, <label columns…>, <52 ARKit names>`` (any
    exporter spelling of the ARKit names). A row with expression ``neutral`` gives that
    person's neutral face; without one the rest pose (zeros) is the neutral."""
    path = Path(path)
    text = read_text(path)
    rows = read_rows(path)
    if not rows:
        raise StageError(f"{path}: no rows")
    header = list(rows[0])
    for need in ("person", "expression"):
        if need not in header:
            raise StageError(f"{path}: no {need!r} column (expected person, expression, ...)")
    arkit_of = {c: canonical_arkit_name(c) for c in header}
    arkit_cols = {arkit_of[c]: c for c in header if arkit_of[c] in ARKIT_NAMES}
    missing = [n for n in ARKIT_NAMES if n not in arkit_cols]
    if missing:
        raise StageError(
            f"{path}: missing ARKit columns {', '.join(missing[:6])}"
            + (f" and {len(missing) - 6} more" if len(missing) > 6 else "")
        )
    label_cols = [c for c in header if c not in ("person", "expression") and not arkit_of[c]]
    values = np.zeros((len(rows), 52))
    for i, row in enumerate(rows, start=2):
        for j, name in enumerate(ARKIT_NAMES):
            raw = row[arkit_cols[name]]
            try:
                v = float(raw)
            except (TypeError, ValueError):
                raise StageError(
                    f"{path}:{i}: column {arkit_cols[name]!r}: {raw!r} is not a number"
                ) from None
            if not 0.0 <= v <= 1.0 or not np.isfinite(v):
                raise StageError(f"{path}:{i}: column {arkit_cols[name]!r}: {v} is outside [0, 1]")
            values[i - 2, j] = v
    persons = np.array([r["person"].strip() for r in rows], dtype=object)
    expressions = np.array([r["expression"].strip() for r in rows], dtype=object)
    seen: set[tuple[str, str]] = set()
    for i, key in enumerate(zip(persons, expressions, strict=True), start=2):
        if not key[0] or not key[1]:
            raise StageError(f"{path}:{i}: empty person or expression")
        if key in seen:
            raise StageError(
                f"{path}:{i}: a second row for person {key[0]!r}, expression {key[1]!r}"
            )
        seen.add(key)
    neutral = {p: np.zeros(52) for p in set(persons)}
    for i in np.nonzero(expressions == "neutral")[0]:
        neutral[persons[i]] = values[i]
    keep = expressions != "neutral"
    s = values[keep] - np.stack([neutral[p] for p in persons[keep]])
    labels = {
        c: _label_array([rows[i][c].strip() for i in np.nonzero(keep)[0]]) for c in label_cols
    }
    return ExpressionSamples(
        "arkit",
        persons[keep],
        expressions[keep],
        labels,
        s,
        ARKIT_NAMES,
        neutral,
        hashlib.sha256(text.encode("utf-8")).hexdigest(),
        str(path),
    )


def samples_from_captures(index: Path, *, window_s: float = 0.1, fps: float = 60.0) -> list[dict]:
    """Face captures reduced to one row per (person, expression): an index CSV with columns
    ``person, expression, <label columns…>, capture, time_s`` names a Live Link Face (or
    generic ARKit) capture CSV, relative to the index, and the time (s from the capture's
    start) of the expression; the row is the mean of the coefficients over
    [time_s, time_s + window_s] (the nearest frame when the window holds none). Returns rows
    for :func:`read_arkit_samples`' CSV (``person, expression, labels…, 52 ARKit names``)."""
    from facelab.stimuli.capture.measure_z import read_capture

    index = Path(index)
    rows = read_rows(index)
    if not rows or not {"person", "expression", "capture", "time_s"} <= set(rows[0]):
        raise StageError(
            f"{index}: expected columns person, expression, <labels...>, capture, time_s"
        )
    labels = [c for c in rows[0] if c not in ("person", "expression", "capture", "time_s")]
    captures: dict[str, object] = {}
    out = []
    for i, row in enumerate(rows, start=2):
        path = index.parent / row["capture"]
        if row["capture"] not in captures:
            captures[row["capture"]] = read_capture(path, fps=fps)
        cap = captures[row["capture"]]
        try:
            t0 = float(row["time_s"])
        except ValueError:
            raise StageError(f"{index}:{i}: time_s {row['time_s']!r} is not a number") from None
        if not cap.times[0] <= t0 <= cap.times[-1]:
            raise StageError(
                f"{index}:{i}: time_s {t0} is outside {row['capture']} (0-{cap.times[-1]:.2f} s)"
            )
        inside = (cap.times >= t0) & (cap.times <= t0 + window_s)
        values = (
            cap.coeffs[inside].mean(axis=0)
            if inside.any()
            else cap.coeffs[int(np.argmin(np.abs(cap.times - t0)))]
        )
        coeffs = {
            n: round(float(np.clip(v, 0, 1)), 6) for n, v in zip(ARKIT_NAMES, values, strict=True)
        }
        out.append(
            {
                "person": row["person"],
                "expression": row["expression"],
                **{c: row[c] for c in labels},
                **coeffs,
            }
        )
    return out


def _read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) vertices and (F, 3) faces of a glTF/GLB/OBJ/PLY mesh, order as stored."""
    suffix = path.suffix.lower()
    if suffix in (".gltf", ".glb", ".vrm"):
        from facelab.stimuli.avatar.gltf import read_gltf

        a = read_gltf(path)
        return a.neutral.astype(np.float64), a.faces
    if suffix == ".obj":  # read here: vertex order must be kept exactly as stored
        verts, faces = [], []
        try:
            for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
                parts = line.split()
                if not parts:
                    continue
                if parts[0] == "v":
                    verts.append([float(v) for v in parts[1:4]])
                elif parts[0] == "f":
                    idx = [int(p.split("/")[0]) for p in parts[1:]]
                    idx = [i - 1 if i > 0 else len(verts) + i for i in idx]
                    faces += [[idx[0], idx[j], idx[j + 1]] for j in range(1, len(idx) - 1)]
        except ValueError as exc:
            raise StageError(f"{path}: not a readable OBJ file ({exc})") from None
        if not verts:
            raise StageError(f"{path}: no vertices")
        return np.asarray(verts, np.float64), np.asarray(faces, np.int64).reshape(-1, 3)
    if suffix == ".ply":
        import trimesh

        try:
            mesh = trimesh.load(path, force="mesh", process=False)
        except Exception as exc:  # trimesh raises many kinds for broken files
            raise StageError(
                f"{path}: cannot read the mesh ({type(exc).__name__}: {exc})"
            ) from None
        return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    raise StageError(f"{path}: expected a .gltf/.glb/.obj/.ply mesh")


def read_vertex_samples(index: Path) -> ExpressionSamples:
    """An index CSV ``person, expression, <label columns…>, file``: one mesh per person and
    expression, all with one topology; each person needs a ``neutral`` row (displacements are
    measured from it). ``file`` is relative to the index's folder."""
    index = Path(index)
    text = read_text(index)
    rows = read_rows(index)
    if not rows or not {"person", "expression", "file"} <= set(rows[0]):
        raise StageError(f"{index}: expected columns person, expression, <labels...>, file")
    h = hashlib.sha256(text.encode("utf-8"))
    meshes, faces = [], None
    for i, row in enumerate(rows, start=2):
        path = index.parent / row["file"]
        if not path.is_file():
            raise StageError(f"{index}:{i}: mesh file {row['file']!r} not found")
        v, f = _read_mesh(path)
        if meshes and v.shape != meshes[0].shape:
            raise StageError(
                f"{index}:{i}: {row['file']} has {len(v)} vertices, the first mesh "
                f"{len(meshes[0])}: all meshes need one topology"
            )
        faces = f if faces is None else faces
        meshes.append(v)
        h.update(path.read_bytes())
    persons = np.array([r["person"].strip() for r in rows], dtype=object)
    expressions = np.array([r["expression"].strip() for r in rows], dtype=object)
    neutral = {persons[i]: meshes[i].reshape(-1) for i in np.nonzero(expressions == "neutral")[0]}
    lacking = sorted(set(persons) - set(neutral))
    if lacking:
        raise StageError(f"{index}: no neutral mesh for {', '.join(lacking[:5])}")
    keep = expressions != "neutral"
    s = np.stack([meshes[i].reshape(-1) - neutral[persons[i]] for i in np.nonzero(keep)[0]])
    label_cols = [c for c in rows[0] if c not in ("person", "expression", "file")]
    labels = {
        c: _label_array([rows[i][c].strip() for i in np.nonzero(keep)[0]]) for c in label_cols
    }
    return ExpressionSamples(
        "vertices", persons[keep], expressions[keep], labels, s, (), neutral, h.hexdigest(),
        str(index), faces,
    )  # fmt: skip


# ----------------------------------------------------------------------------- easing


#: The smallest change between two levels taken as visible: a tenth of an ARKit coefficient's
#: range in the channel that moves most (vertex samples: 2 mm). An assumption, not a
#: perceptual measurement: below it, levels looked alike in rendered frames here (at δ = one SD
#: the shipped model's q = 0 / 0.5 / 1 differed by 0.13/255 in mean pixel value).
VISIBLE_CHANGE = {"arkit": 0.10, "vertices": 0.002}


def level_visibility(model: ImpressionModel) -> list[str]:
    """Per expression, what q = 1 shows on the model's mean neutral face: the largest change
    (against :data:`VISIBLE_CHANGE`) and the headroom (the level from which a channel clips),
    with a warning and the ``--step`` range that is both visible and unclipped when either
    falls short."""
    lines = []
    limit = VISIBLE_CHANGE[model.space]
    unit = "" if model.space == "arkit" else " m"
    for e in model.expressions:
        change, where = model.level_change(e, 1.0)
        room, channel = model.headroom(e)
        unclipped = np.abs(model.model(e).delta * model.model(e).direction).max() * room
        line = f"{e}: q = 1 moves {where} by {change:.3g}{unit} (taken as visible from {limit:g})"
        line += "; no channel clips" if not math.isfinite(room) else (
            f"; {channel} clips from q = {room:.2f}")  # fmt: skip
        lines.append(line)
        if change < limit and unclipped >= limit:
            lines.append(f"warning: {e}: q = 0, 0.5, 1 will look alike; refit with --step S, "
                         f"S from {limit:g} to {unclipped:.2f} (visible and unclipped at "
                         "q = 1)")  # fmt: skip
        elif change < limit:
            lines.append(f"warning: {e}: the mean face has room for a change of "
                         f"{unclipped:.3f} before {channel} clips, below the {limit:g} taken "
                         "as visible: this expression cannot show the impression visibly "
                         "without clipping")  # fmt: skip
        elif room < 1.0:
            lines.append(f"warning: {e}: clipping eats the levels above q = {room:.2f} "
                         f"({channel} held at its limit); refit with --step at most "
                         f"{unclipped:.2f} to keep q = 1 unclipped")  # fmt: skip
    return lines


def ease(x: np.ndarray | float, *, kind: str = "sigmoid", k: float = 5.0) -> np.ndarray:
    """Easing e(x) on x in [0, 1], e(0) = 0, e(1) = 1 (see the module docstring)."""
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    if kind == "linear":
        return x
    if kind == "smoothstep":
        return x * x * (3 - 2 * x)
    if kind == "sigmoid":
        if k <= 0:
            raise StageError(f"sigmoid easing needs k > 0, got {k}")

        def sig(t: np.ndarray | float) -> np.ndarray:
            return 1.0 / (1.0 + np.exp(-k * np.asarray(t)))

        lo, hi = sig(-1.0), sig(1.0)
        return (sig(2 * x - 1) - lo) / (hi - lo)
    raise StageError(f"unknown easing {kind!r}; expected one of {', '.join(EASINGS)}")


def envelope_at(
    t: np.ndarray,
    *,
    onset_s: float,
    hold_s: float,
    offset_s: float,
    lead_s: float = 0.0,
    kind: str = "sigmoid",
    k: float = 5.0,
) -> np.ndarray:
    """Expression weight e at times t (s): 0 before ``lead_s``, eased onset, 1 while held,
    eased offset, 0 after."""
    if min(onset_s, hold_s, offset_s, lead_s) < 0:
        raise StageError("onset, hold, offset and lead durations must be >= 0")
    t = np.asarray(t, np.float64) - lead_s
    rise = ease(t / onset_s, kind=kind, k=k) if onset_s > 0 else (t >= 0).astype(float)
    after = t - onset_s - hold_s
    fall = (
        1 - ease(after / offset_s, kind=kind, k=k) if offset_s > 0 else (after <= 0).astype(float)
    )
    return np.where(t < 0, 0.0, np.where(after > 0, fall, rise))


def envelope(
    *,
    fps: int,
    onset_s: float,
    hold_s: float,
    offset_s: float,
    lead_s: float = 0.0,
    kind: str = "sigmoid",
    k: float = 5.0,
) -> np.ndarray:
    """(T,) expression weight per frame: ``lead_s`` neutral, eased onset, hold, eased offset
    (back to neutral), and a last neutral frame. T = round((lead+onset+hold+offset) fps) + 1.
    Durations are checked by :func:`envelope_at`."""
    n = round((lead_s + onset_s + hold_s + offset_s) * fps) + 1
    return envelope_at(
        np.arange(n) / fps, onset_s=onset_s, hold_s=hold_s, offset_s=offset_s, lead_s=lead_s,
        kind=kind, k=k,
    )  # fmt: skip


# ----------------------------------------------------------------------------- the model


@dataclass
class ExpressionModel:
    """The seed's model for one expression (shapes in the module docstring)."""

    expression: str
    mean: np.ndarray  # (D,) s̄
    basis: np.ndarray  # (K, D) U, orthonormal rows
    explained: np.ndarray  # (K,) share of variance per axis
    w: np.ndarray  # (K,) unit impression vector in PCA coordinates
    direction: np.ndarray  # (D,) unit direction in sample space (Uᵀw, or orthogonalised)
    delta: float  # δ, sample-space units along direction
    coef: np.ndarray  # (K,) decision function on f: coef·f + intercept
    intercept: float
    n: int
    cv: dict = field(default_factory=dict)

    def project(self, s: np.ndarray) -> np.ndarray:
        """PCA coordinates f (.., K) of displacements s (.., D) (eq. 1)."""
        return (np.asarray(s) - self.mean) @ self.basis.T

    def decision(self, s: np.ndarray) -> np.ndarray:
        """The direction model's decision value (SVM margin, centred mean-difference
        projection, or predicted rating) for displacements s (.., D)."""
        return self.project(s) @ self.coef + self.intercept

    def edited(self, q: float, *, f: np.ndarray | None = None) -> np.ndarray:
        """ŝ (D,) = s̄ + Uᵀ f + q·δ·d (eq. 2 in sample space; f = 0: the mean expression)."""
        start = self.mean + (f @ self.basis if f is not None else 0.0)
        return start + q * self.delta * self.direction


@dataclass
class ImpressionModel:
    """Models per expression, with what they were fitted on."""

    space: str
    channels: tuple[str, ...]
    label: str
    method: str
    positive: str | None
    k_rule: str
    orthogonal_to_speech: bool
    data_sha256: str
    source: str
    expressions: dict[str, ExpressionModel]
    neutral_mean: np.ndarray  # (D,) mean neutral face (ARKit: coefficients; vertices: positions)
    faces: np.ndarray | None = None
    svm_c: float | None = None
    step: float | None = None  # δ chosen so that q = 1 moves the largest channel by this much

    def model(self, expression: str) -> ExpressionModel:
        if expression not in self.expressions:
            raise StageError(
                f"the impression model has no expression {expression!r}; it has "
                f"{', '.join(self.expressions)}"
            )
        return self.expressions[expression]

    def _face(self, m: ExpressionModel, level: float, base: np.ndarray) -> np.ndarray:
        """The mean face of ``m`` at ``level`` on ``base`` (ARKit: clipped to [0, 1])."""
        full = base + m.edited(level)
        return np.clip(full, 0.0, 1.0) if self.space == "arkit" else full

    def _largest(self, diff: np.ndarray) -> tuple[float, str]:
        """(size, where) of the largest entry of a face difference: a channel, or a vertex."""
        if self.space == "arkit":
            i = int(np.argmax(np.abs(diff)))
            return float(abs(diff[i])), self.channels[i]
        moved = np.linalg.norm(diff.reshape(-1, 3), axis=1)
        i = int(np.argmax(moved))
        return float(moved[i]), f"vertex {i}"

    def headroom(
        self, expression: str, *, neutral: np.ndarray | None = None
    ) -> tuple[float, str]:
        """(q, channel): the highest level whose face no ARKit channel clips (the base
        expression's headroom along the direction; channels moving under 5 % of the
        largest are left out), and the channel that reaches its limit there; (inf, "") for
        vertex models, which do not clip."""
        m = self.model(expression)
        if self.space != "arkit":
            return math.inf, ""
        base = (self.neutral_mean if neutral is None else neutral) + m.mean
        step = m.delta * m.direction
        room = np.full(len(step), math.inf)
        # a channel that barely moves (under 5 % of the largest) clipping eats no level
        moving = np.abs(step) >= 0.05 * np.abs(step).max()
        up, down = moving & (step > 1e-12), moving & (step < -1e-12)
        room[up] = (1.0 - base[up]) / step[up]
        room[down] = (0.0 - base[down]) / step[down]
        room = np.maximum(room, 0.0)
        i = int(np.argmin(room))
        return float(room[i]), self.channels[i] if np.isfinite(room[i]) else ""

    def level_change(
        self,
        expression: str,
        q: float,
        *,
        q_from: float = 0.0,
        neutral: np.ndarray | None = None,
    ) -> tuple[float, str]:
        """(size, where) of the largest change of the face between levels ``q_from`` and
        ``q`` (the mean face of the expression on ``neutral``, default the model's mean
        neutral; ARKit faces clipped to [0, 1]): ARKit coefficient units and the channel's
        name, or metres and the vertex."""
        m = self.model(expression)
        base = self.neutral_mean if neutral is None else neutral
        return self._largest(self._face(m, q, base) - self._face(m, q_from, base))

    def frames(
        self, expression: str, q: float, env: np.ndarray, *, neutral: np.ndarray | None = None
    ) -> tuple[np.ndarray, dict]:
        """(T, D) faces X̂ = X_neutral + e·ŝ for an envelope (T,) and facts about the clip:
        intended and realised level, the decision value of the last frame at full strength.
        ARKit faces are clipped to [0, 1]."""
        m = self.model(expression)
        base = self.neutral_mean if neutral is None else neutral
        full = base + m.edited(q)
        clipped = self._face(m, q, base)
        s_real, s_zero = clipped - base, self._face(m, 0.0, base) - base
        q_real = float((s_real - s_zero) @ m.direction / m.delta) if m.delta else 0.0
        frames = base + env[:, None] * s_real[None, :]
        change, where = self._largest(s_real - s_zero)
        info = {
            "expression": expression,
            "q_intended": float(q),
            "q_realised": round(q_real, 6),
            "clipped_channels": int(np.sum(np.abs(full - clipped) > 1e-9)),
            # the realised level in a visible unit: the largest change from q = 0
            "change_from_q0": round(change, 6),
            "change_unit": "ARKit coefficient" if self.space == "arkit" else "m",
            "changed_most": where,
            "decision_value": round(float(m.decision(frames[np.argmax(env)] - base)), 6),
            "headroom_q": round(self.headroom(expression, neutral=neutral)[0], 6),
        }
        return frames, info

    # ---------------------------------------------------------------- JSON
    def to_json(self) -> dict:
        def named(vec: np.ndarray) -> dict | list:
            if self.space == "arkit":
                return {n: round(float(v), 8) for n, v in zip(self.channels, vec, strict=True)}
            return [round(float(v), 8) for v in vec]

        return {
            "format": MODEL_FORMAT,
            "space": self.space,
            "label": self.label,
            "method": self.method,
            "svm_c": self.svm_c,
            "positive": self.positive,
            "k_rule": self.k_rule,
            "orthogonal_to_speech": self.orthogonal_to_speech,
            "data_sha256": self.data_sha256,
            "source": self.source,
            "delta_units": (
                "one SD of the training projections on the direction "
                if self.step is None
                else f"q = 1 moves the largest channel by {self.step:g} "
            )
            + ("(ARKit coefficient units)" if self.space == "arkit" else "(metres)"),
            "step": self.step,
            "directions": {e: named(m.direction) for e, m in self.expressions.items()},
            "delta": {e: m.delta for e, m in self.expressions.items()},
            "cv": {e: m.cv for e, m in self.expressions.items()},
            "neutral_mean": named(self.neutral_mean),
            "faces": None if self.faces is None else self.faces.tolist(),
            "pca": {
                e: {
                    "n": m.n,
                    "k": len(m.basis),
                    "explained": [float(v) for v in m.explained],
                    "mean": named(m.mean),
                    "basis": [named(u) for u in m.basis],
                    "w": [float(v) for v in m.w],
                    "coef": [float(v) for v in m.coef],
                    "intercept": float(m.intercept),
                }
                for e, m in self.expressions.items()
            },
        }

    @classmethod
    def from_json(cls, data: dict, *, where: str = "model") -> ImpressionModel:
        if not isinstance(data, dict) or data.get("format") != MODEL_FORMAT:
            raise StageError(f"{where}: not a facelab impression model ({MODEL_FORMAT})")
        space = data.get("space")
        if space not in ("arkit", "vertices"):
            raise StageError(f"{where}: 'space' is {space!r}; expected 'arkit' or 'vertices'")
        channels = ARKIT_NAMES if space == "arkit" else ()

        def vec(v: dict | list) -> np.ndarray:
            if isinstance(v, dict):
                return np.array([float(v[n]) for n in ARKIT_NAMES])
            return np.asarray(v, np.float64)

        try:
            models = {}
            for e, p in data["pca"].items():
                models[e] = ExpressionModel(
                    e,
                    vec(p["mean"]),
                    np.stack([vec(u) for u in p["basis"]]),
                    np.asarray(p["explained"]),
                    np.asarray(p["w"]),
                    vec(data["directions"][e]),
                    float(data["delta"][e]),
                    np.asarray(p["coef"]),
                    float(p["intercept"]),
                    int(p["n"]),
                    data["cv"][e],
                )
            model = cls(
                space, channels, data["label"], data["method"], data.get("positive"),
                data["k_rule"], bool(data["orthogonal_to_speech"]), data["data_sha256"],
                data.get("source", ""), models, vec(data["neutral_mean"]),
                None if data.get("faces") is None else np.asarray(data["faces"], np.int64),
                data.get("svm_c"), data.get("step"),
            )  # fmt: skip
            model.check()
            return model
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise StageError(
                f"{where}: malformed impression model ({type(exc).__name__}: {exc})"
            ) from None

    def check(self) -> None:
        """Raise ValueError unless every array has its documented shape (D the sample
        dimension, K the PCA axes of each expression) and finite values, δ is positive and
        the direction a unit vector - a hand-edited model would otherwise render NaN faces
        or fail deep inside numpy."""
        d = len(self.neutral_mean)
        if self.space == "arkit" and d != len(ARKIT_NAMES):
            raise ValueError(f"neutral_mean has {d} values; expected {len(ARKIT_NAMES)}")
        arrays: list[tuple[str, np.ndarray, tuple[int, ...]]] = [
            ("neutral_mean", self.neutral_mean, (d,))
        ]
        for e, m in self.expressions.items():
            k = len(m.basis)
            arrays += [
                (f"{e}: mean", m.mean, (d,)),
                (f"{e}: basis", m.basis, (k, d)),
                (f"{e}: explained", m.explained, (k,)),
                (f"{e}: w", m.w, (k,)),
                (f"{e}: direction", m.direction, (d,)),
                (f"{e}: coef", m.coef, (k,)),
                (f"{e}: delta", np.asarray(m.delta), ()),
                (f"{e}: intercept", np.asarray(m.intercept), ()),
            ]
        for name, array, shape in arrays:
            array = np.asarray(array)
            if array.shape != shape or array.dtype.kind not in "fiu":
                raise ValueError(f"{name} has shape {array.shape}; expected {shape}")
            if not np.isfinite(array).all():
                raise ValueError(f"{name} holds non-finite values")
        for e, m in self.expressions.items():
            if m.delta <= 0:
                raise ValueError(f"{e}: delta is {m.delta}; expected > 0")
            if abs(float(np.linalg.norm(m.direction)) - 1.0) > 1e-4:
                raise ValueError(f"{e}: direction is not a unit vector")

    @classmethod
    def load_cached(cls, path: Path) -> ImpressionModel:
        """:meth:`load`, remembered per (path, size, modification time)."""
        path = Path(path)
        try:
            st = path.stat()
        except OSError as exc:
            raise StageError(f"{path}: cannot read the impression model ({exc})") from None
        return _load_cached(str(path.resolve()), st.st_size, st.st_mtime_ns)

    @classmethod
    def load(cls, path: Path) -> ImpressionModel:
        path = Path(path)
        data = read_json(path, what="impression model")
        return cls.from_json(data, where=str(path))


@functools.lru_cache(maxsize=16)
def _load_cached(path: str, size: int, mtime_ns: int) -> ImpressionModel:
    del size, mtime_ns  # part of the cache key only
    return ImpressionModel.load(Path(path))


def speech_basis() -> np.ndarray:
    """(R, 52) orthonormal rows spanning the mouth shapes of the speech methods: the columns
    of the shipped Z matrices (standard and emphasized)."""
    cols = np.hstack([load_z("standard"), load_z("emphasized")])  # (52, 10)
    q, r = np.linalg.qr(cols)
    keep = np.abs(np.diag(r)) > 1e-9
    return q[:, keep].T


def _pca(
    s: np.ndarray, *, k: int | None, variance: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean (D,), basis (K, D), explained share (K,) of samples s (N, D)."""
    mean = s.mean(axis=0)
    centred = s - mean
    _, sv, vt = np.linalg.svd(centred, full_matrices=False)
    var = sv**2
    share = var / var.sum() if var.sum() > 0 else np.zeros_like(var)
    limit = max(1, min(len(s) - 1, int(np.sum(share > 1e-12))))
    if k is None:
        k = int(np.searchsorted(np.cumsum(share), variance) + 1)
    if not 1 <= k <= limit:
        raise StageError(f"K = {k}: must be between 1 and {limit} (samples - 1, non-zero axes)")
    return mean, vt[:k], share[:k]


def _direction(
    f: np.ndarray, y: np.ndarray, method: str, *, svm_c: float = 0.1
) -> tuple[np.ndarray, np.ndarray, float]:
    """(w unit (K,), coef (K,), intercept) from PCA coordinates f (N, K) and labels y."""
    if method == "svm":
        from sklearn.svm import SVC

        # one overall scale (not per axis: whitening would turn the normal) so that C = 1
        # means the same on data of any units
        scale = float(np.sqrt(np.mean(np.sum((f - f.mean(axis=0)) ** 2, axis=1)))) or 1.0
        clf = SVC(kernel="linear", C=svm_c).fit(f / scale, y)
        coef = clf.coef_.ravel().astype(float) / scale
        intercept = float(clf.intercept_[0])
    elif method == "mean_diff":
        mu1, mu0 = f[y == 1].mean(axis=0), f[y == 0].mean(axis=0)
        coef = mu1 - mu0
        intercept = -float(coef @ (mu1 + mu0) / 2)
    elif method == "ridge":
        from sklearn.linear_model import Ridge

        reg = Ridge(alpha=1.0).fit(f, y)
        coef = reg.coef_.ravel().astype(float)
        intercept = float(reg.intercept_)
    else:
        raise StageError(
            f"unknown method {method!r}; expected one of {', '.join(DIRECTION_METHODS)}"
        )
    norm = float(np.linalg.norm(coef))
    if norm == 0:
        raise StageError("the labels carry no direction (all samples alike)")
    return coef / norm, coef, intercept


def fit_impression(
    samples: ExpressionSamples,
    *,
    label: str,
    method: str = "svm",
    k: int | None = None,
    variance: float = 0.9,
    positive: str | None = None,
    expressions: Sequence[str] | None = None,
    orthogonal_to_speech: bool = False,
    svm_c: float = 0.1,
    step: float | None = None,
) -> ImpressionModel:
    """Fit the seed's model per expression (see the module docstring).

    ``step``: instead of one SD of the projections, δ is chosen so that q = 1 moves the
    largest channel of the direction by ``step`` (ARKit coefficient units; metres for vertex
    samples) - a level with a visible meaning (:data:`VISIBLE_CHANGE`).

    ``label`` names a column: two classes for ``svm``/``mean_diff`` (``positive`` names the
    class the direction points to; default ``high`` if present, else the larger value in sort
    order), numbers for ``ridge``. Leave-one-person-out CV per expression. ``svm_c``: the
    SVM's C on PCA scores divided by their overall RMS (one scalar, so the normal is not
    turned); 0.1 recovered the synthetic database's true direction best (cosine 0.90-0.95
    against 0.79-0.89 at C = 0.3), with LOPO accuracy 0.70-0.90.
    """
    if label not in samples.labels:
        raise StageError(
            f"{samples.source}: no label column {label!r}; label columns: "
            f"{', '.join(samples.labels) or 'none'}"
        )
    if method not in DIRECTION_METHODS:
        raise StageError(
            f"unknown method {method!r}; expected one of {', '.join(DIRECTION_METHODS)}"
        )
    if orthogonal_to_speech and samples.space != "arkit":
        raise StageError("orthogonal_to_speech needs ARKit space (the speech shapes are ARKit)")
    raw = samples.labels[label]
    numeric = raw.dtype != object
    if method == "ridge":
        if not numeric:
            raise StageError(f"method ridge needs numeric ratings in {label!r}")
        y_all = raw.astype(float)
        pos = None
    else:
        classes = sorted({str(v) for v in raw})
        if len(classes) != 2:
            raise StageError(
                f"method {method} needs two classes in {label!r}, found {len(classes)}: "
                f"{', '.join(classes[:6])}"
            )
        pos = positive if positive is not None else ("high" if "high" in classes else classes[1])
        if pos not in classes:
            raise StageError(
                f"--positive {pos!r} is not a class of {label!r} ({', '.join(classes)})"
            )
        y_all = np.array([1 if str(v) == pos else 0 for v in raw])
    wanted = list(expressions) if expressions else sorted(set(samples.expressions))
    basis_speech = speech_basis() if orthogonal_to_speech else None
    models = {}
    for expr in wanted:
        rows = np.nonzero(samples.expressions == expr)[0]
        if len(rows) < 4:
            raise StageError(f"expression {expr!r}: {len(rows)} samples; at least 4 are needed")
        s, y, persons = samples.s[rows], y_all[rows], samples.persons[rows]
        if method != "ridge" and len(set(y.tolist())) < 2:
            raise StageError(f"expression {expr!r}: every sample is in one class of {label!r}")
        mean, basis, share = _pca(s, k=k, variance=variance)
        f = (s - mean) @ basis.T
        w, coef, intercept = _direction(f, y, method, svm_c=svm_c)
        direction = w @ basis
        if basis_speech is not None:
            direction = direction - (direction @ basis_speech.T) @ basis_speech
            n = np.linalg.norm(direction)
            if n < 1e-9:
                raise StageError(f"expression {expr!r}: the direction lies in the speech shapes")
            direction = direction / n
        proj = (s - mean) @ direction
        delta = float(np.std(proj, ddof=1))
        if not delta > 0:
            raise StageError(f"expression {expr!r}: the samples do not vary along the direction")
        if step is not None:
            largest = (
                np.abs(direction).max()
                if samples.space == "arkit"
                else np.linalg.norm(direction.reshape(-1, 3), axis=1).max()
            )
            delta = float(step / largest)
        cv = _cross_validate(s, y, persons, method=method, k=len(basis), svm_c=svm_c)
        cv["variance_explained"] = round(float(share.sum()), 4)
        models[expr] = ExpressionModel(
            expr, mean, basis, share, w, direction, delta, coef, intercept, len(rows), cv
        )
    neutral_mean = np.mean(np.stack(list(samples.neutral.values())), axis=0)
    return ImpressionModel(
        samples.space,
        samples.channels,
        label,
        method,
        pos,
        f"k={k}" if k is not None else f"variance>={variance}",
        orthogonal_to_speech,
        samples.sha256,
        samples.source,
        models,
        neutral_mean,
        samples.faces,
        svm_c if method == "svm" else None,
        step,
    )


def _cross_validate(
    s: np.ndarray, y: np.ndarray, persons: np.ndarray, *, method: str, k: int, svm_c: float
) -> dict:
    """Leave-one-person-out: PCA and direction refitted without the person, then scored on
    them; accuracy (and balanced accuracy) for classes, R² and Pearson r for ratings."""
    predictions = np.zeros(len(y), float)
    people = sorted(set(persons.tolist()))
    if len(people) < 3:
        return {"scheme": "leave-one-person-out", "note": "fewer than 3 people: not run"}
    for p in people:
        test = persons == p
        train = ~test
        if method != "ridge" and len(set(y[train].tolist())) < 2:
            predictions[test] = np.nan
            continue
        kk = min(k, int(train.sum()) - 1)
        mean, basis, _ = _pca(s[train], k=kk, variance=1.0)
        f = (s[train] - mean) @ basis.T
        _, coef, b = _direction(f, y[train], method, svm_c=svm_c)
        predictions[test] = ((s[test] - mean) @ basis.T) @ coef + b
    ok = np.isfinite(predictions)
    out: dict = {"scheme": "leave-one-person-out", "folds": len(people)}
    if method == "ridge":
        resid = np.sum((y[ok] - predictions[ok]) ** 2)
        total = np.sum((y[ok] - y[ok].mean()) ** 2)
        out["r2"] = round(float(1 - resid / total), 4) if total > 0 else None
        out["r"] = round(float(np.corrcoef(y[ok], predictions[ok])[0, 1]), 4)
    else:
        hit = (predictions[ok] > 0).astype(int) == y[ok]
        out["accuracy"] = round(float(np.mean(hit)), 4)
        recalls = [float(np.mean(hit[y[ok] == c])) for c in (0, 1) if np.any(y[ok] == c)]
        out["balanced_accuracy"] = round(float(np.mean(recalls)), 4)
    return out
