#!/usr/bin/env bash
# Build the documentation site into site/ (warnings are errors); open site/index.html.
# `bash scripts/docs.sh serve` serves it at http://127.0.0.1:8000 while you edit docs/.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/setup.sh"
cd "$ROOT"
if [ "${1:-}" = "serve" ]; then exec .venv/bin/mkdocs serve --strict -a 127.0.0.1:8000; fi
exec .venv/bin/mkdocs build --strict
