"""The face tracker's side of the stimulus checks: runs in MediaPipe's own environment.

MediaPipe 0.10.21 pins an older NumPy than facelab, so ``scripts/setup.sh`` gives it a venv of
its own (``.venv-mediapipe``) and facelab runs this file there as a child process
(:mod:`facelab.stimuli.checks.face_tracker`). It imports nothing of facelab: only the standard
library, NumPy and MediaPipe.

Input: requests on stdin, one line of JSON each, until stdin closes (facelab keeps the process
for its later checks)::

    {"id": 7, "clips": [{"path": "a.mp4", "width": 640, "height": 360, "grey": "a.npy"}, ...]}

``width`` x ``height`` is the size the clip is decoded at (ffmpeg scales it: every clip is
measured at one analysis size, whatever it was rendered at). Output: one line of JSON on
stdout per request, per clip and per frame, from MediaPipe face *detection* (short range)
and Face *Mesh* (video mode, one face, 468 landmarks)::

    {"id": 7, "tracker": "mediapipe 0.10.21", "clips": [{"path", "frames",
      "detection": [score...],                 # best face's confidence, 0 without a face
      "box": [[x0, y0, x1, y1] | null ...],    # the face mesh's box, fractions of the frame
      "aperture": [a | null ...],              # inner lips 13-14 / face height 10-152
      "width": [w | null ...],                 # mouth corners 61-291 / face height
      "face_height": [h | null ...]}]}         # 10-152 in frame heights

Distances are measured in pixels (x scaled by the frame's aspect), so they do not depend on
the frame's shape. A clip that cannot be decoded gets ``"error"`` instead of the lists. With
``"grey"``, the decoded frames are also saved there as a NumPy array (n, height/2, width/2)
uint8 of grey levels (every other pixel of every other row), so that facelab compares clips
without decoding them again.
"""

from __future__ import annotations

import json
import subprocess
import sys


def _frames(path: str, width: int, height: int):
    """The clip's frames (height, width, 3) uint8 RGB, decoded by ffmpeg as they are read."""
    import numpy as np

    size = width * height * 3
    proc = subprocess.Popen(
        ["ffmpeg", "-v", "error", "-nostdin", "-threads", "1", "-i", path, "-vf",
         f"scale={width}:{height}:flags=area", "-f", "rawvideo", "-pix_fmt", "rgb24", "-"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )  # fmt: skip
    while True:
        data = proc.stdout.read(size)
        if len(data) < size:
            break
        yield np.frombuffer(data, np.uint8).reshape(height, width, 3)
    err = proc.stderr.read().decode("utf-8", "replace").strip()
    if proc.wait() != 0:
        raise RuntimeError(err[-300:] or f"ffmpeg exit {proc.returncode}")


def _measure(clip: dict) -> dict:
    import mediapipe as mp
    import numpy as np

    width, height = int(clip["width"]), int(clip["height"])
    detector = mp.solutions.face_detection.FaceDetection(
        model_selection=0, min_detection_confidence=0.1
    )
    mesh = mp.solutions.face_mesh.FaceMesh(
        static_image_mode=False, max_num_faces=1, refine_landmarks=False,
        min_detection_confidence=0.3, min_tracking_confidence=0.3,
    )  # fmt: skip
    out: dict = {"path": clip["path"], "detection": [], "box": [],
                 "aperture": [], "width": [], "face_height": []}  # fmt: skip
    greys = []
    for img in _frames(clip["path"], width, height):
        if clip.get("grey"):  # every other pixel of every other row, ITU-R BT.601 weights
            rgb = img[::2, ::2].astype(np.uint16)
            greys.append(((77 * rgb[..., 0] + 150 * rgb[..., 1] + 29 * rgb[..., 2]) >> 8)
                         .astype(np.uint8))  # fmt: skip
        found = detector.process(img).detections or []
        out["detection"].append(round(max((float(d.score[0]) for d in found), default=0.0), 4))
        res = mesh.process(img)
        if not res.multi_face_landmarks:
            for key in ("box", "aperture", "width", "face_height"):
                out[key].append(None)
            continue
        lm = res.multi_face_landmarks[0].landmark
        xy = np.array([(p.x * width, p.y * height) for p in lm])

        def dist(i: int, j: int, xy=xy) -> float:
            return float(np.hypot(*(xy[i] - xy[j])))

        face = max(dist(10, 152), 1e-6)
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        box = (lo[0] / width, lo[1] / height, hi[0] / width, hi[1] / height)
        out["box"].append([round(float(v), 4) for v in box])
        out["aperture"].append(round(dist(13, 14) / face, 5))
        out["width"].append(round(dist(61, 291) / face, 5))
        out["face_height"].append(round(face / height, 5))
    detector.close()
    mesh.close()
    out["frames"] = len(out["detection"])
    if clip.get("grey"):
        np.save(clip["grey"], np.stack(greys) if greys else
                np.zeros((0, height // 2, width // 2), np.uint8))  # fmt: skip
    return out


def _without_plotting() -> None:
    """Let ``import mediapipe`` skip Matplotlib. MediaPipe's package imports its drawing
    helpers, which import ``matplotlib.pyplot`` - about half of the 0.8 s that importing
    MediaPipe takes, paid by every tracker process; the tracker never draws. Empty modules
    stand in for Matplotlib in this process only (a drawing helper called by mistake fails
    on a missing attribute)."""
    import types

    if "matplotlib" in sys.modules:
        return
    package = types.ModuleType("matplotlib")
    package.__path__ = []  # a package: ``import matplotlib.pyplot`` looks in it
    package.pyplot = types.ModuleType("matplotlib.pyplot")
    sys.modules["matplotlib"], sys.modules["matplotlib.pyplot"] = package, package.pyplot


def main() -> int:
    _without_plotting()
    import mediapipe as mp

    for line in sys.stdin:
        request = json.loads(line)
        results = []
        for clip in request["clips"]:
            try:
                results.append(_measure(clip))
            except (RuntimeError, ValueError, OSError) as exc:
                results.append({"path": clip["path"], "error": str(exc)})
        answer = {"id": request.get("id"), "tracker": f"mediapipe {mp.__version__}",
                  "clips": results}
        sys.stdout.write(json.dumps(answer) + "\n")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
