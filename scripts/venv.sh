#!/usr/bin/env bash
# Creates .venv (Python >= 3.11) and installs the project into it when pyproject.toml changed.
# Sourced by run.sh and test.sh; leaves VENV_PY pointing at the environment's python.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
PY="${PYTHON:-python3}"
if ! "$PY" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)' 2>/dev/null; then
  echo "error: $PY is not Python >= 3.11 (set PYTHON=/path/to/python3.11)" >&2
  exit 2
fi
if [ ! -x "$VENV/bin/python" ]; then
  echo "creating $VENV ..." >&2
  "$PY" -m venv "$VENV"
fi
STAMP="$VENV/.installed-$(sha256sum "$ROOT/pyproject.toml" | cut -c1-16)"
if [ ! -f "$STAMP" ]; then
  echo "installing the cell and its dependencies into $VENV (first run takes a minute) ..." >&2
  # uv resolves the same versions as pip and installs them in half the time (parallel downloads, unpacking and
  # bytecode compiling: about 20 s against 45 s on a fresh clone here; without the compiling, every first import
  # pays it later);
  # pip does it when uv cannot be had or fails.
  if ! { "$VENV/bin/python" -m pip install --quiet uv >&2 \
         && "$VENV/bin/python" -m uv pip install --quiet --compile-bytecode --python "$VENV/bin/python" \
              -e "$ROOT[test]" >&2; }; then
    echo "uv was not usable: installing with pip ..." >&2
    "$VENV/bin/python" -m pip install --quiet --upgrade pip >&2
    "$VENV/bin/python" -m pip install --quiet -e "$ROOT[test]" >&2
  fi
  rm -f "$VENV"/.installed-*
  touch "$STAMP"
fi
VENV_PY="$VENV/bin/python"
