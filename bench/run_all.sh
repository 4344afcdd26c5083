#!/usr/bin/env bash
# Fill the `## Daemon latency (lacuna bench)` section of bench/NOTEBOOK.md (the dated runs).
# Usage: bench/run_all.sh [--repeats N] [--seconds T]   (defaults 3 x 10 s; about 5 min per model)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
exec "$PY" bench/latency.py "$@"
