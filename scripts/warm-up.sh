#!/usr/bin/env bash
# Compile the solver's numba kernels into their disk cache (app.vlp.solvers.warm_up), or only
# load them when the cache already holds the current sources' kernels (a few seconds).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
OPENBLAS_NUM_THREADS=1 exec .venv/bin/python -c "from app.vlp.solvers import warm_up; warm_up()"
