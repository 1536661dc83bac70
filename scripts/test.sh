#!/usr/bin/env bash
# The README's test command (and what .ci/run calls): set up everything the tests need, then run the whole suite.
# Extra arguments go to pytest (e.g. `bash scripts/test.sh -m slow` for the long studies).
#
# The package is installed editable and built in place (no build isolation) with the build requirements of
# pyproject.toml installed in .venv, so the C++ extension's build tree (build/<wheel tag>/) stays valid between
# runs: a re-run rebuilds only what changed. The C++ compiler runs once per clone: an extension already installed
# in .venv (by the README's `pip install .`, or an earlier run) that was built from these sources with these
# settings is installed again as it is (CMakeLists.txt checks its build record; MULTIBODY_SIM_REUSE). Environment:
#   MULTIBODY_SIM_NATIVE=0      skip the C++ build (and run the Python kernel); the native tests then skip.
#   MULTIBODY_SIM_BUILD_LOCK=F  the lock file held (`flock`) while building, so that checkouts sharing a machine
#                               compile one at a time (~1 min and ~3 GiB per C++ file); default: a file in /tmp.
#   CI=true                     a failed C++ build fails the run (elsewhere the install falls back to Python).
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
fi
log=.venv/install.log
# pip's and the build's output goes to a log, shown whole when something fails: the run starts with the tests.
: >"$log"
quiet() { "$@" >>"$log" 2>&1 || { cat "$log"; echo "scripts/test.sh: failed: $*" >&2; exit 1; }; }
pip=(.venv/bin/python -m pip install --disable-pip-version-check)
quiet "${pip[@]}" --upgrade pip
if [ "${MULTIBODY_SIM_NATIVE:-}" = 0 ]; then
  quiet "${pip[@]}" -e ".[test]" --config-settings=wheel.cmake=false
else
  # The build requirements, the package's dependencies and the test extra's (pyproject.toml's lists, the extras it
  # names expanded), installed before the build so that the build lock is held for the build only; then what
  # scikit-build-core adds (cmake, ninja when the machine's are missing or too old).
  mapfile -t requires < <(.venv/bin/python -c '
import re
try:
    import tomllib
except ImportError:  # Python 3.10: the copy pip vendors
    from pip._vendor import tomli as tomllib
pyproject = tomllib.load(open("pyproject.toml", "rb"))
project, extras = pyproject["project"], pyproject["project"]["optional-dependencies"]
def expand(extra):
    for requirement in extras[extra]:
        own = re.fullmatch(r"multibody-sim\[(.+)\]", requirement)
        yield from (r for name in own.group(1).split(",") for r in expand(name)) if own else [requirement]
print("\n".join([*pyproject["build-system"]["requires"], *project["dependencies"], *expand("test")]))')
  quiet "${pip[@]}" "${requires[@]}"
  read -r -a requires <<<"$(.venv/bin/python -c '
from scikit_build_core.build import get_requires_for_build_editable
print(" ".join(get_requires_for_build_editable()))')"
  if [ "${#requires[@]}" -gt 0 ]; then quiet "${pip[@]}" "${requires[@]}"; fi
  lock=()
  if command -v flock >/dev/null 2>&1; then
    lock=(flock "${MULTIBODY_SIM_BUILD_LOCK:-${TMPDIR:-/tmp}/multibody-sim-build.lock}")
  fi
  reuse=$(.venv/bin/python -c '
import importlib.metadata, re
try:
    files = importlib.metadata.distribution("multibody-sim").files or []
except importlib.metadata.PackageNotFoundError:
    files = []
print(next((f.locate() for f in files if re.fullmatch(r"multibody_sim/_native\.[^/]*\.so", f.as_posix())), ""))')
  quiet "${lock[@]}" "${pip[@]}" --verbose --no-build-isolation -e ".[test]" \
    --config-settings="cmake.define.MULTIBODY_SIM_REUSE=$reuse"  # the build's output, for the log
  # A build that fell back to Python is said in one line (its output is in the log); under CI it fails the run.
  .venv/bin/python -c '
import os, sys
from multibody_sim import native
if not native.available:
    message = f"scripts/test.sh: the native kernel is not available: {native.why_unavailable} (see .venv/install.log)"
    sys.exit(message) if os.environ.get("CI") == "true" else print(message, file=sys.stderr)'
fi
# The viewer's tests open its pages in a real browser, Debian's chromium: installed here when missing and we
# are root (as in CI, where its absence fails those tests; elsewhere they skip and say why).
if ! command -v chromium >/dev/null 2>&1 && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  DEBIAN_FRONTEND=noninteractive apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
fi
exec .venv/bin/python -m pytest "$@"
