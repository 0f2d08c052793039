#!/usr/bin/env bash
# The peers the calibration benchmark compares against, each where it can be installed:
# pyswarms in the project's venv; magyc (numpy < 2, gtsam, jax) in its own .venv-peers.
set -euo pipefail
VENV=${VENV:-.venv}
PEERS=${PEERS:-.venv-peers}
PYTHON=${PYTHON:-python3.11}
"$VENV/bin/python" -m pip install --quiet "pyswarms==1.3.0"
if [ ! -x "$PEERS/bin/python" ]; then
    "$PYTHON" -m venv "$PEERS"
fi
"$PEERS/bin/python" -m pip install --quiet "magyc==1.0.0"
echo "peers ready: pyswarms in $VENV, magyc in $PEERS"
