#!/usr/bin/env bash
# Create (or reuse) the virtual environment .venv and install shapecorr into it:
# torch==2.13.0 first (the CPU build on a machine without CUDA; install your CUDA build of torch first to
# keep it), then the package in editable mode with its dev extras (pytest).
# Environment: SHAPECORR_VENV=DIR to use another venv location.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${SHAPECORR_VENV:-.venv}
[ -x "$VENV/bin/python" ] || python3 -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --upgrade pip
"$VENV/bin/python" -m pip show torch >/dev/null 2>&1 || "$VENV/bin/python" -m pip install -q "torch==2.13.0"
"$VENV/bin/python" -m pip install -q -e ".[dev]"
