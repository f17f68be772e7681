"""Does a face tracker nobody here wrote see the right mouth for each vowel, in every condition?

Two steps, two Python environments (MediaPipe 0.10.21 pins an older NumPy than facelab):

    .venv/bin/python scripts/face_tracker_check.py render --out DIR [--protocol P] [--avatar F]
    .venv-mediapipe/bin/python scripts/face_tracker_check.py track DIR

``render`` (facelab's venv) draws, for every condition of the protocol (default ``kato2021``)
and every vowel of its vowel stimulus, the frames within ±0.1 s of the vowel's peak exactly as
``facelab render`` draws them (the protocol's camera, 640x360 unless ``--size``), on the
protocol's avatar or ``--avatar FILE``; plus stills of a blink, a head turn and a gaze shift.
``track`` (MediaPipe's venv) runs MediaPipe Face Mesh on every frame and prints JSON (also
written to ``DIR/result.json``): per condition and vowel, the median inner-lip aperture
(landmarks 13/14) and mouth width (corners 61/291), each over the face height (10/152); and the
checks of Japanese articulation - あ the largest aperture, う the smallest, い the widest mouth,
emphasized あ at least 1.3x standard あ. It exits 1 when a frame has no face or a check fails.
It also runs MediaPipe face *detection* (short-range model) on every frame and still - the
head turned ±25° in yaw included (``still_yaw_m25``/``still_yaw_25``) - and reports its
confidence: median and minimum over the vowel frames, and per still (issue 37.3 compares
the default head with a real avatar by it).
``scripts/face_tracker_check.sh`` runs both, creating ``.venv-mediapipe`` when missing.

``clips`` (MediaPipe's venv) runs the detector on every frame of every clip of a
``facelab render`` folder, decoded from the MP4s participants see::

    facelab render protocols/kato2021.yaml --size 320x180 --out DIR
    .venv-mediapipe/bin/python scripts/face_tracker_check.py clips DIR [--below 0.92]
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

VOWEL_ORDER = "aiueo"


def render(out: Path, *, protocol_ref: str, avatar_file: str | None, size: str) -> None:
    from dataclasses import replace

    from PIL import Image

    from facelab.protocol import load_protocol
    from facelab.resources import protocol_path
    from facelab.stimuli.avatar.rig import HeadPose
    from facelab.stimuli.render.build import vowel_peaks
    from facelab.stimuli.render.inspect import sheet_poses
    from facelab.stimuli.render.renderer import Renderer
    from facelab.stimuli.render.scene import load_avatar, settings_for

    path = Path(protocol_ref) if protocol_ref.endswith(".yaml") else protocol_path(protocol_ref)
    protocol = load_protocol(path)
    if avatar_file is not None:
        rendering = protocol.rendering.model_copy(
            update={"avatar": str(Path(avatar_file).resolve())}
        )
        protocol = protocol.model_copy(update={"rendering": rendering})
    width, height = (int(v) for v in size.split("x"))
    settings = replace(settings_for(protocol), width=width, height=height)
    avatar = load_avatar(protocol, base_dir=path.parent)
    peaks = vowel_peaks(protocol, base_dir=path.parent, avatar=avatar)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    with Renderer(avatar, settings) as r:
        stills = sheet_poses(avatar)
        if avatar.skeleton is not None and "head" in avatar.skeleton.roles:
            stills += [("yaw m25", {}, HeadPose(yaw=-25)), ("yaw 25", {}, HeadPose(yaw=25))]
        for label, w, pose in stills:
            name = "still_" + "_".join(label.strip("/").split()[:2])
            Image.fromarray(r.frame(avatar.weight_vector(w), pose=pose)).save(out / f"{name}.png")
        for peak in peaks:
            for k, weights in enumerate(peak.window):
                name = f"{peak.condition}_{peak.vowel}_{k}.png"
                Image.fromarray(r.frame(weights)).save(out / name)
                rows.append({"frame": name, "condition": peak.condition, "vowel": peak.vowel})
    with open(out / "frames.csv", "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=["frame", "condition", "vowel"])
        writer.writeheader()
        writer.writerows(rows)
    (out / "about.json").write_text(
        json.dumps({"protocol": str(path), "avatar": avatar.name, "size": size}) + "\n"
    )
    print(f"wrote {len(rows)} vowel frames of {avatar.name} and the stills into {out}")


def _checks(table: dict[str, dict[str, dict[str, float]]]) -> dict[str, bool]:
    """Japanese articulation, per condition: あ opens most, う least, い is widest."""
    checks = {}
    for cond, vowels in table.items():
        if set(vowels) != set(VOWEL_ORDER):
            checks[f"{cond}: all five vowels measured"] = False
            continue
        ap = {v: vowels[v]["aperture"] for v in VOWEL_ORDER}
        wd = {v: vowels[v]["width"] for v in VOWEL_ORDER}
        checks[f"{cond}: a has the largest aperture"] = max(ap, key=ap.get) == "a"
        checks[f"{cond}: u has the smallest aperture"] = min(ap, key=ap.get) == "u"
        checks[f"{cond}: i has the widest mouth"] = max(wd, key=wd.get) == "i"
    if "standard" in table and "emphasized" in table:
        a_std = table["standard"].get("a", {}).get("aperture")
        a_emp = table["emphasized"].get("a", {}).get("aperture")
        if a_std and a_emp:
            checks["emphasized a >= 1.3x standard a"] = a_emp >= 1.3 * a_std
    return checks


def _face_detector() -> Callable[[Any], float]:
    """MediaPipe face detection (short range): an (H, W, 3) RGB image -> the best face's
    confidence (0 when it finds none). The same detector for the stills and the clips."""
    import mediapipe as mp

    detector = mp.solutions.face_detection.FaceDetection(
        model_selection=0, min_detection_confidence=0.1
    )
    return lambda img: max(
        (float(d.score[0]) for d in detector.process(img).detections or []), default=0.0
    )


def track(folder: Path) -> int:
    import mediapipe as mp
    import numpy as np
    from PIL import Image

    mesh = mp.solutions.face_mesh.FaceMesh(
        static_image_mode=True, max_num_faces=1, refine_landmarks=False
    )
    detect = _face_detector()

    def look(path: Path) -> tuple[tuple[float, float] | None, float]:
        """(aperture, width) from the face mesh (None without a face) and the detector's best
        score (0 when it finds no face), from one reading of the picture."""
        img = np.asarray(Image.open(path).convert("RGB"))
        score = detect(img)
        res = mesh.process(img)
        if not res.multi_face_landmarks:
            return None, score
        lm = res.multi_face_landmarks[0].landmark
        aspect = img.shape[0] / img.shape[1]

        def dist(i: int, j: int) -> float:
            return float(np.hypot(lm[i].x - lm[j].x, (lm[i].y - lm[j].y) * aspect))

        face = dist(10, 152)
        return (dist(13, 14) / face, dist(61, 291) / face), score

    stills = {p.stem.removeprefix("still_"): look(p) for p in sorted(folder.glob("still_*"))}
    frames = list(csv.DictReader((folder / "frames.csv").read_text(encoding="utf-8").splitlines()))
    found: dict[tuple[str, str], list[tuple[float, float]]] = {}
    missing = []
    scores = []
    for row in frames:
        m, score = look(folder / row["frame"])
        scores.append(score)
        if m is None:
            missing.append(row["frame"])
        else:
            found.setdefault((row["condition"], row["vowel"]), []).append(m)
    table: dict[str, dict[str, dict[str, float]]] = {}
    for (cond, vowel), values in found.items():
        a = np.asarray(values)
        table.setdefault(cond, {})[vowel] = {
            "aperture": round(float(np.median(a[:, 0])), 4),
            "width": round(float(np.median(a[:, 1])), 4),
            "frames": len(values),
        }
    table = {c: {v: table[c][v] for v in VOWEL_ORDER if v in table[c]} for c in table}
    checks = _checks(table)
    detection = {
        "model": "mediapipe face detection, short range",
        "vowel_frames_median": round(float(np.median(scores)), 3) if scores else None,
        "vowel_frames_min": round(float(np.min(scores)), 3) if scores else None,
        "stills": {name: round(score, 3) for name, (_, score) in stills.items()},
    }
    result = {
        "tracker": f"mediapipe {mp.__version__} face mesh (static images)",
        **json.loads((folder / "about.json").read_text()),
        "measure": "median over the frames within ±0.1 s of each vowel's peak; aperture = "
        "inner lips 13-14, width = corners 61-291, both / face height 10-152",
        "stills_found": f"{sum(m is not None for m, _ in stills.values())}/{len(stills)}",
        "vowel_frames_found": f"{len(frames) - len(missing)}/{len(frames)}",
        "frames_without_a_face": missing,
        "by_condition": table,
        "detection": detection,
        "checks": checks,
        "passed": not missing and all(checks.values()) and bool(checks),
    }
    text = json.dumps(result, indent=2, ensure_ascii=False)
    (folder / "result.json").write_text(text + "\n", encoding="utf-8")
    print(text)
    return 0 if result["passed"] else 1


def clips(folder: Path, *, below: float) -> int:
    """MediaPipe face detection (short range) on every frame of every clip a ``facelab render``
    folder lists (decoded by ffmpeg, as participants see them). Prints JSON (also written to
    ``FOLDER/face_detection.json``): per clip the median, minimum and the frames under
    ``below``; over all frames the same. Exits 1 when a frame has no face."""
    import subprocess

    import mediapipe as mp
    import numpy as np

    detect = _face_detector()
    rows = list(csv.DictReader((folder / "clips.csv").read_text(encoding="utf-8").splitlines()))
    per_clip = {}
    every = []
    for row in rows:
        w, h = int(row["width"]), int(row["height"])
        raw = subprocess.run(
            ["ffmpeg", "-v", "error", "-i", str(folder / row["path"]), "-f", "rawvideo",
             "-pix_fmt", "rgb24", "-"],
            check=True, capture_output=True,
        ).stdout  # fmt: skip
        frames = np.frombuffer(raw, np.uint8).reshape(-1, h, w, 3)
        scores = np.array([detect(f) for f in frames])
        every.append(scores)
        low = np.nonzero(scores < below)[0]
        per_clip[row["clip_id"]] = {
            "frames": len(scores),
            "median": round(float(np.median(scores)), 3),
            "min": round(float(scores.min()), 3),
            "min_frame": int(scores.argmin()),
            f"frames_below_{below}": len(low),
        }
    allscores = np.concatenate(every) if every else np.zeros(0)
    result = {
        "model": f"mediapipe {mp.__version__} face detection, short range",
        "folder": str(folder),
        "frames": len(allscores),
        "median": round(float(np.median(allscores)), 3) if len(allscores) else None,
        "min": round(float(allscores.min()), 3) if len(allscores) else None,
        f"frames_below_{below}": int((allscores < below).sum()),
        "frames_without_a_face": int((allscores == 0).sum()),
        "clips": per_clip,
    }
    text = json.dumps(result, indent=2)
    (folder / "face_detection.json").write_text(text + "\n", encoding="utf-8")
    print(text)
    return 0 if len(allscores) and result["frames_without_a_face"] == 0 else 1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("step", choices=["render", "track", "clips"])
    parser.add_argument("folder", nargs="?")
    parser.add_argument("--out")
    parser.add_argument("--protocol", default="kato2021")
    parser.add_argument("--avatar", help="a glTF/VRM file instead of the protocol's avatar")
    parser.add_argument("--size", default="640x360")
    parser.add_argument(
        "--below", type=float, default=0.92, help="clips: count the frames under this score"
    )
    args = parser.parse_args()
    folder = Path(args.out or args.folder or "results/face_tracker_check")
    if args.step == "clips":
        return clips(folder, below=args.below)
    if args.step == "render":
        render(folder, protocol_ref=args.protocol, avatar_file=args.avatar, size=args.size)
        return 0
    return track(folder)


if __name__ == "__main__":
    sys.exit(main())
