#!/usr/bin/env bash
# The main job: set up (Debian packages, .venv), then `facelab demo` on the embedded
# defaults - render the study's clips, simulate participants, analyse, write the report.
# Extra arguments go to `facelab demo`, e.g. `bash scripts/demo.sh --out /tmp/demo`.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/setup.sh"
cd "$ROOT"
export PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-egl}"
exec .venv/bin/facelab demo "$@"
