#!/usr/bin/env bash
# Render every vowel of kato2021 in every condition and let MediaPipe Face Mesh (0.10.21,
# offline, CPU) measure the mouths; exits 1 when the vowels are not articulated in order.
# MediaPipe pins an older NumPy, so it lives in its own venv (.venv-mediapipe, made by setup.sh).
# Usage: bash scripts/face_tracker_check.sh [FOLDER [--avatar FILE] [--protocol P] [--size WxH]]
#        (FOLDER defaults to results/face_tracker_check)
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh >/dev/null
folder="${1:-results/face_tracker_check}"
shift || true
export PYOPENGL_PLATFORM=egl
.venv/bin/python scripts/face_tracker_check.py render --out "$folder" "$@"
.venv-mediapipe/bin/python scripts/face_tracker_check.py track "$folder"
