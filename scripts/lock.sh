#!/usr/bin/env bash
# Re-resolve the pinned, hashed Python lock files that scripts/setup.sh installs from:
#   requirements/lock.txt          facelab[all] (pyproject.toml) for CPython 3.11 on x86-64 Linux
#   requirements/tracker-lock.txt  the face tracker's own environment (requirements/tracker.in)
# Run it after changing a dependency in pyproject.toml or requirements/tracker.in, then run
# scripts/setup.sh (it reinstalls when a lock file changes) and the tests, and commit the locks.
# Uses uv (installed from PyPI into .venv-tools on first use); resolves against PyPI itself, so
# the hashes are the files PyPI serves. `bash scripts/lock.sh --upgrade` moves every pin to the
# newest version the bounds in pyproject.toml allow; without it, existing pins are kept.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
TOOLS="$ROOT/.venv-tools"
if [ ! -x "$TOOLS/bin/uv" ]; then
  python3 -m venv "$TOOLS"
  "$TOOLS/bin/python" -m pip install -q "uv>=0.5"
fi
common=(--generate-hashes --python-version 3.11 --python-platform x86_64-manylinux_2_28
        --index-url https://pypi.org/simple --no-header "$@")
cd "$ROOT"
"$TOOLS/bin/uv" pip compile pyproject.toml --extra all "${common[@]}" \
  --output-file requirements/lock.txt >/dev/null
"$TOOLS/bin/uv" pip compile requirements/tracker.in "${common[@]}" \
  --output-file requirements/tracker-lock.txt >/dev/null
echo "requirements/lock.txt: $(grep -c '^[A-Za-z0-9].*==' requirements/lock.txt) pins;" \
     "requirements/tracker-lock.txt: $(grep -c '^[A-Za-z0-9].*==' requirements/tracker-lock.txt) pins"
