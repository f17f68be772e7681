#!/usr/bin/env bash
# The test command: set up (Debian packages, .venv), lint with ruff, run pytest.
# Display tests run on a virtual X screen (xvfb-run). Extra arguments go to pytest,
# e.g. `bash scripts/test.sh -m "not slow"` for the quick subset.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/setup.sh"
cd "$ROOT"
.venv/bin/ruff check .
export PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-egl}"
exec xvfb-run -a -s "-screen 0 1280x1024x24" .venv/bin/python -m pytest "$@"
