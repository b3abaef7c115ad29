#!/usr/bin/env bash
# The README's test command: set up .venv from requirements.txt and build the book (exactly as
# scripts/build_book.sh does: -W -n --keep-going into _build/html, every notebook executed as it is, so every
# assert in a chapter must hold), then run the unit tests and open the built site in headless Chromium
# (tests/test_site.py; it skips without Chromium unless PINNHJB_REQUIRE_SITE=1, which .ci/run sets).
# Then every notebook once more under strict nbval (every stored text output must come out again; cells whose
# output depends on a live training run or holds a widget are tagged nbval-ignore-output, and their asserts
# still run), with every loaded checkpoint's weights perturbed by a relative 1e-13 (PINNHJB_PERTURB_WEIGHTS,
# pinnhjb.storage): rounding noise of another CPU or BLAS must not change a printed number. (The build has
# already run them unperturbed; one nbval run, perturbed, checks both, which keeps CI within its time.)
# ruff (pinned in requirements.txt, settings in pyproject.toml) checks and format-checks the code first.
# The tests run even when the build or the linter fails, so one run reports both; the exit status is then a failure.
# pytest's exit code 5 (no tests collected) is turned into a failure.
# Both pytest runs use two processes (pytest-xdist; PINNHJB_TEST_WORKERS=N for N, 0 for none): the unit
# tests a file to a process (--dist loadfile: a file's module fixtures, such as the browser sweep, are set up
# once), the notebooks a notebook to a process (--dist loadscope: its cells in order, in one kernel). On CI's two
# cores this took the two runs from 13 + 7.5 to 9 + 3.5 minutes (2026-12-08); conftest.py keeps torch to one
# thread in each unit-test process.
set -uo pipefail
cd "$(dirname "$0")/.."
WORKERS=${PINNHJB_TEST_WORKERS:-2}
bash scripts/build_book.sh
build_rc=$?
if [ "$build_rc" -ne 0 ]; then
  echo "book build failed (exit $build_rc); running the tests anyway" >&2
  [ -x .venv/bin/python ] || exit 1
fi
echo "== ruff check, ruff format --check"
.venv/bin/ruff check . && .venv/bin/ruff format --check .
lint_rc=$?
if [ "$lint_rc" -ne 0 ] && [ "$build_rc" -eq 0 ]; then
  build_rc=$lint_rc
fi
.venv/bin/python -m pytest tests -n "$WORKERS" --dist loadfile "$@"
rc=$?
if [ "$rc" -eq 5 ]; then
  echo "pytest collected no tests: failing on purpose" >&2
  exit 1
fi
echo "== notebooks under strict nbval, checkpoint weights perturbed by a relative 1e-13 (PINNHJB_PERTURB_WEIGHTS)"
PINNHJB_PERTURB_WEIGHTS=1e-13 .venv/bin/python -m pytest notebooks --nbval --nbval-current-env -q \
  -n "$WORKERS" --dist loadscope "$@"
perturbed_rc=$?
if [ "$perturbed_rc" -eq 5 ]; then
  echo "pytest collected no notebooks in the perturbed run: failing on purpose" >&2
  perturbed_rc=1
fi
if [ "$rc" -eq 0 ]; then
  rc=$perturbed_rc
fi
if [ "$rc" -eq 0 ] && [ "$build_rc" -ne 0 ]; then
  exit "$build_rc"
fi
exit "$rc"
