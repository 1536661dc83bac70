#!/usr/bin/env bash
# The README's test command (and what .ci/run calls): set up everything the tests need, then run the whole suite.
# Extra arguments go to pytest (e.g. `bash scripts/test.sh -m slow` for the long studies).
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
fi
.venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".[test]"
exec .venv/bin/python -m pytest "$@"
