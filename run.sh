#!/usr/bin/env bash
# The main job: sets up .venv if needed, then runs the default task on the simulated cell.
# Extra arguments go to `main.py run`, e.g. ./run.sh --json
set -euo pipefail
cd "$(dirname "$0")"
source scripts/venv.sh
exec "$VENV_PY" main.py run peg-in-hole --cell sim "$@"
