#!/usr/bin/env bash
# The whole test suite: sets up .venv if needed, then runs pytest (extra arguments go to pytest).
set -euo pipefail
cd "$(dirname "$0")"
source scripts/venv.sh
exec "$VENV_PY" -m pytest "$@"
