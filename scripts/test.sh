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
# The viewer's tests open its pages in a real browser, Debian's chromium: installed here when missing and we
# are root (as in CI, where its absence fails those tests; elsewhere they skip and say why).
if ! command -v chromium >/dev/null 2>&1 && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  DEBIAN_FRONTEND=noninteractive apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
fi
exec .venv/bin/python -m pytest "$@"
