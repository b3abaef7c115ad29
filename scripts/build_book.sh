#!/usr/bin/env bash
# The README's book command: set up .venv from requirements.txt, then build the book into _build/html.
# Warnings are errors (-W), every reference must resolve (-n); notebooks are executed during the build.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/python -m ipykernel install --user --name python3 >/dev/null 2>&1 || true
.venv/bin/jupyter-book build . -W -n --keep-going "$@"
echo "book built: $(pwd)/_build/html/index.html"
