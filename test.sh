#!/usr/bin/env bash
# The whole test suite: sets up .venv if needed, then runs pytest (extra arguments go to pytest).
# Two test processes (pytest-xdist: the machine has two cores), each test handed to whichever is free;
# `./test.sh -n 0` runs everything in this one process.
set -euo pipefail
cd "$(dirname "$0")"
source scripts/venv.sh
exec "$VENV_PY" -m pytest -n 2 --dist worksteal "$@"
