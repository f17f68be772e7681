#!/usr/bin/env bash
# Idempotent set-up for facelab on Debian with Python >= 3.11:
#   1. Debian packages that facelab's stages need, installed with apt-get only when missing;
#   2. a virtual environment in .venv with every dependency of facelab[all] at the versions and
#      hashes pinned in requirements/lock.txt, then facelab itself (editable, no dependencies);
#      reinstalled only when pyproject.toml or the lock file changes;
#   3. the stimulus checks' face tracker (MediaPipe, which pins an older NumPy) in a venv of its
#      own, .venv-mediapipe, from requirements/tracker-lock.txt, likewise.
# The lock files are made by scripts/lock.sh (see there to update them).
# Sourced by scripts/demo.sh and scripts/test.sh; safe to run again at any time.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"

# ffmpeg: clip encoding; libegl1 + libgl1-mesa-dri: offscreen rendering (EGL);
# open-jtalk + naist-jdic: phoneme timing; xvfb + xauth: PsychoPy windows without a screen;
# xdotool + x11-xserver-utils (xmodmap): the scripted participant of `facelab run --simulate`
# (real X clicks and keys; typed kana get keycodes of their own first);
# fonts-noto-cjk: Japanese text in windows and figures; libsndfile1/libportaudio2: audio I/O;
# chromium + chromium-driver: simulated online participants and the browser tests;
# postgresql: the online database at scale (the tests start one in a temporary folder);
# g++: builds the meshoptimizer decoder (compressed glTF avatars; PyPI has no wheel);
# espeak-ng: a second, formant-synthesis Japanese voice family for training and judging the
# viseme analyser on voices other than OpenJTalk's (bench visemes, tests).
APT_PACKAGES=(
  ffmpeg libegl1 libgl1-mesa-dri libglu1-mesa
  open-jtalk open-jtalk-mecab-naist-jdic
  xvfb xauth xdotool x11-xserver-utils fonts-noto-cjk
  libsndfile1 libportaudio2 libasound2
  chromium chromium-driver postgresql espeak-ng g++
)
# npm installs jsPsych for `facelab serve` (from the pinned lockfile); Debian's nodejs/npm
# only when no node is on PATH (a machine may have Node from elsewhere).
if ! command -v npm >/dev/null 2>&1; then APT_PACKAGES+=(nodejs npm); fi

log() { printf '[facelab setup] %s\n' "$*" >&2; }

missing=()
for pkg in "${APT_PACKAGES[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$pkg")
  fi
done
if ((${#missing[@]})); then
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then
    if command -v sudo >/dev/null 2>&1; then SUDO="sudo"; else
      log "missing Debian packages: ${missing[*]}"
      log "run as root (or install sudo): apt-get install ${missing[*]}"
      exit 1
    fi
  fi
  log "installing Debian packages: ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get update -qq >/dev/null
  $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

PYTHON="${PYTHON:-}"
if [ -z "$PYTHON" ]; then
  for candidate in python3.11 python3.12 python3; do
    if command -v "$candidate" >/dev/null 2>&1 &&
       "$candidate" -c 'import sys; sys.exit(not ((3, 11) <= sys.version_info[:2] < (3, 13)))'; then
      PYTHON="$(command -v "$candidate")"; break
    fi
  done
fi
if [ -z "$PYTHON" ]; then
  log "facelab needs Python 3.11 or 3.12 (psychopy supports < 3.13); none found on PATH"
  exit 1
fi

if [ ! -x "$VENV/bin/python" ]; then
  log "creating virtual environment $VENV with $PYTHON"
  "$PYTHON" -m venv "$VENV"
fi

LOCK="$ROOT/requirements/lock.txt"
PIP_PIN="$ROOT/requirements/pip.txt"
STAMP="$VENV/.facelab-installed"
WANT="$(cat "$ROOT/pyproject.toml" "$LOCK" "$PIP_PIN" | sha256sum | cut -d' ' -f1)"
if [ ! -f "$STAMP" ] || [ "$(cat "$STAMP")" != "$WANT" ]; then
  log "installing facelab and its pinned dependencies into .venv (log: .venv/pip.log)"
  if ! { "$VENV/bin/python" -m pip install -q --require-hashes -r "$PIP_PIN" &&
         "$VENV/bin/python" -m pip install -q --require-hashes -r "$LOCK" &&
         "$VENV/bin/python" -m pip install -q --no-deps -e "$ROOT"; } >"$VENV/pip.log" 2>&1; then
    grep -v "is ignored: it is neither a file nor a directory" "$VENV/pip.log" | tail -40 >&2
    log "pip install failed; see .venv/pip.log"
    exit 1
  fi
  echo "$WANT" >"$STAMP"
fi

TRACKER_VENV="$ROOT/.venv-mediapipe"
TRACKER_STAMP="$TRACKER_VENV/.facelab-installed"
TRACKER_LOCK="$ROOT/requirements/tracker-lock.txt"
TRACKER_WANT="$(cat "$TRACKER_LOCK" "$PIP_PIN" | sha256sum | cut -d' ' -f1)"
if [ ! -f "$TRACKER_STAMP" ] || [ "$(cat "$TRACKER_STAMP")" != "$TRACKER_WANT" ]; then
  log "installing the face tracker (MediaPipe) for the stimulus checks into .venv-mediapipe"
  [ -x "$TRACKER_VENV/bin/python" ] || "$PYTHON" -m venv "$TRACKER_VENV"
  if ! { "$TRACKER_VENV/bin/python" -m pip install -q --require-hashes -r "$PIP_PIN" &&
         "$TRACKER_VENV/bin/python" -m pip install -q --require-hashes -r "$TRACKER_LOCK"; } \
       >"$TRACKER_VENV/pip.log" 2>&1; then
    tail -20 "$TRACKER_VENV/pip.log" >&2
    log "pip install of the face tracker failed; see .venv-mediapipe/pip.log"
    exit 1
  fi
  echo "$TRACKER_WANT" >"$TRACKER_STAMP"
fi

WEB="$ROOT/experiment/online/web"
WEB_STAMP="$WEB/node_modules/.facelab-lock"
WEB_WANT="$(sha256sum "$WEB/package-lock.json" | cut -d' ' -f1)"
if [ ! -f "$WEB_STAMP" ] || [ "$(cat "$WEB_STAMP")" != "$WEB_WANT" ]; then
  log "installing jsPsych for facelab serve (npm ci, pinned lockfile)"
  if ! (cd "$WEB" && npm ci --no-audit --no-fund --loglevel=error >"$VENV/npm.log" 2>&1); then
    tail -20 "$VENV/npm.log" >&2
    log "npm ci failed; see .venv/npm.log"
    exit 1
  fi
  echo "$WEB_WANT" >"$WEB_STAMP"
fi

# facelab's own modules compiled to bytecode here, once: a Python started with
# PYTHONDONTWRITEBYTECODE set (as some environments do) reads __pycache__ but never writes it,
# so every process - each command, render child, test worker - compiled facelab from source
# again (0.3-0.4 CPU-s a `facelab validate`); up-to-date files are skipped
(cd "$ROOT" && "$VENV/bin/python" -m compileall -q -j 0 -x '/node_modules/' \
  core stimuli analysis experiment >/dev/null) || log "compiling facelab to bytecode failed; it runs from source"
