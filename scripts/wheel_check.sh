#!/usr/bin/env bash
# The release as a pip user gets it: build maglog's wheel from this checkout, install it
# with plain `pip install` (no extras, no editable install, nothing of the source tree on
# the path) into a new virtual environment, and run the commands a new user runs first:
# --help, a board project, the short scenario on the model backend, and the calibration of
# the card it wrote. Run by CI after `make test` (which set up .venv with the build tools).
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-$VENV/bin/python}

work=$(mktemp -d "${TMPDIR:-/tmp}/maglog-wheel.XXXXXX")
trap 'rm -rf "$work"' EXIT
say() { echo "wheel-check: $*"; }

# Build from a copy: the build's egg-info and build/ folders stay out of the checkout.
mkdir "$work/src"
cp setup.py pyproject.toml README.md "$work/src/"
for root in hw sw sim calib cli; do
  cp -r "$root" "$work/src/$root"
done
find "$work/src" -name __pycache__ -prune -exec rm -rf {} +
"$PYTHON" -m pip wheel --quiet --no-deps --no-build-isolation --wheel-dir "$work/dist" "$work/src"
wheel=$(ls "$work"/dist/maglog-*.whl)
say "built $(basename "$wheel")"

"$PYTHON" -m venv "$work/venv"
"$work/venv/bin/python" -m pip install --quiet --upgrade pip
"$work/venv/bin/python" -m pip install --quiet "$wheel"
say "installed into a new venv"

# From an empty folder, so that nothing of the checkout can be imported.
mkdir "$work/run"
cd "$work/run"
maglog="$work/venv/bin/maglog"
"$maglog" --help >/dev/null
"$maglog" --version
"$maglog" hdl build --board de0nano -o board >/dev/null
test -s board/maglog_board.qsf
"$maglog" simulate short --backend model -o flight/card.img --quiet >/dev/null
test -s flight/card.img
"$maglog" calibrate flight/card.img --attitude flight/attitude.csv --out report >/dev/null
test -s report/parameters.json
# An installed maglog names remedies that work for it: no scripts/setup.sh.
if "$maglog" hdl resources --yosys /nonexistent/yosys 2>err.txt; then
  echo "wheel-check: hdl resources ran without Yosys" >&2; exit 1
fi
if grep -q "setup.sh" err.txt; then
  echo "wheel-check: an installed maglog points at scripts/setup.sh: $(cat err.txt)" >&2; exit 1
fi
say "maglog --help, hdl build, simulate short --backend model, calibrate: all ran"
