"""Does a face tracker nobody here wrote see the default head as a face, with the right mouths?

Two steps, two Python environments (MediaPipe 0.10.21 pins an older NumPy than facelab):

    .venv/bin/python scripts/face_tracker_check.py render --out DIR
    .venv-mediapipe/bin/python scripts/face_tracker_check.py track DIR

``render`` (facelab's venv) writes PNG frames of the default head into DIR: the five vowels
at full strength (the shipped standard Z), a blink, a head turn, a gaze shift, and every frame
of a spoken "あいうえお" clip (vowel_blend, standard Z) with the vowel the analyser heard in
each frame (``frames.csv``). ``track`` (MediaPipe's venv) runs MediaPipe Face Mesh on every
frame and prints JSON: the share of frames with a face found, and the inner-lip aperture
(landmarks 13/14) relative to the face height (landmarks 10/152) per still and per vowel.
``scripts/face_tracker_check.sh`` runs both, creating ``.venv-mediapipe`` when missing.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path


def render(out: Path) -> None:
    import numpy as np
    from PIL import Image

    from facelab.stimuli.avatar import default_head
    from facelab.stimuli.methods import DriveInput, drive
    from facelab.stimuli.render.clip import frame_weights
    from facelab.stimuli.render.inspect import sheet_poses
    from facelab.stimuli.render.renderer import Renderer, RenderSettings
    from facelab.stimuli.speech.analyser import analyze
    from facelab.stimuli.speech.track import VOWELS
    from facelab.stimuli.speech.tts import synthesize

    out.mkdir(parents=True, exist_ok=True)
    head = default_head()
    speech = synthesize("あ、い、う、え、お。")
    track = analyze(speech.samples, sample_rate=speech.sample_rate).compensated()
    bs = drive("vowel_blend", DriveInput(track=track), {"z": "standard", "gain": 1.0})
    fps = 30
    n = int(track.times[-1] * fps)
    weights = frame_weights(bs, head, fps=fps, n_frames=n, pad_s=0.0)
    vowels = track.vowels()
    rows = []
    with Renderer(head, RenderSettings(width=640, height=480, msaa=4)) as r:
        for label, w, pose in sheet_poses(head):
            name = (
                "still_"
                + label.strip("/").split()[0]
                + ("_" + label.split()[1] if " " in label else "")
            )
            Image.fromarray(r.frame(head.weight_vector(w), pose=pose)).save(out / f"{name}.png")
        for k in range(n):
            t = k / fps
            i = min(int(np.searchsorted(track.times, t)), len(track.times) - 1)
            heard = VOWELS[int(np.argmax(vowels[i]))] if vowels[i].max() > 0.5 else ""
            Image.fromarray(r.frame(weights[k])).save(out / f"clip_{k:04d}.png")
            rows.append({"frame": f"clip_{k:04d}.png", "t": round(t, 4), "vowel": heard})
    with open(out / "frames.csv", "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=["frame", "t", "vowel"])
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {len(rows)} clip frames and the stills into {out}")


def track(folder: Path) -> None:
    import mediapipe as mp
    import numpy as np
    from PIL import Image

    mesh = mp.solutions.face_mesh.FaceMesh(
        static_image_mode=True, max_num_faces=1, refine_landmarks=False
    )

    def aperture(path: Path) -> float | None:
        img = np.asarray(Image.open(path).convert("RGB"))
        res = mesh.process(img)
        if not res.multi_face_landmarks:
            return None
        lm = res.multi_face_landmarks[0].landmark
        face = np.hypot(lm[10].x - lm[152].x, (lm[10].y - lm[152].y) * img.shape[0] / img.shape[1])
        lips = np.hypot(lm[13].x - lm[14].x, (lm[13].y - lm[14].y) * img.shape[0] / img.shape[1])
        return float(lips / face)

    stills = {
        p.stem.removeprefix("still_"): aperture(p) for p in sorted(folder.glob("still_*.png"))
    }
    frames = list(csv.DictReader((folder / "frames.csv").read_text(encoding="utf-8").splitlines()))
    per_vowel: dict[str, list[float]] = {}
    found = 0
    for row in frames:
        a = aperture(folder / row["frame"])
        if a is not None:
            found += 1
            if row["vowel"]:
                per_vowel.setdefault(row["vowel"], []).append(a)
    result = {
        "tracker": f"mediapipe {mp.__version__} face mesh (static images)",
        "stills_found": f"{sum(v is not None for v in stills.values())}/{len(stills)}",
        "still_aperture_over_face_height": {
            k: None if v is None else round(v, 4) for k, v in stills.items()
        },
        "clip_frames_found": f"{found}/{len(frames)}",
        "clip_aperture_median_by_heard_vowel": {
            v: round(float(np.median(x)), 4) for v, x in sorted(per_vowel.items())
        },
        "clip_frames_per_vowel": {v: len(x) for v, x in sorted(per_vowel.items())},
    }
    s = result["still_aperture_over_face_height"]
    if all(s.get(v) is not None for v in "aeiu"):
        result["a > e > i,u (stills)"] = bool(s["a"] > s["e"] > max(s["i"], s["u"]))
    print(json.dumps(result, indent=2, ensure_ascii=False))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("step", choices=["render", "track"])
    parser.add_argument("folder", nargs="?")
    parser.add_argument("--out")
    args = parser.parse_args()
    folder = Path(args.out or args.folder or "results/face_tracker_check")
    render(folder) if args.step == "render" else track(folder)
    return 0


if __name__ == "__main__":
    sys.exit(main())
