#!/usr/bin/env bash
# Shared set-up for ./run and ./test: a project venv with the pinned dependency set.
# Re-installs only when pyproject.toml or constraints.txt changed since the last install.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
extras="${1:-}"
python="${VLP_PYTHON:-python3}"
if [[ ! -x .venv/bin/python ]]; then
  "$python" -m venv .venv
fi
stamp=".venv/.vlp-installed${extras:+-$extras}"
want="$(cat pyproject.toml constraints.txt | sha256sum | cut -d' ' -f1)"
if [[ ! -f "$stamp" || "$(cat "$stamp")" != "$want" ]]; then
  .venv/bin/python -m pip install --quiet --disable-pip-version-check --upgrade pip
  spec="."
  [[ -n "$extras" ]] && spec=".[$extras]"
  .venv/bin/python -m pip install --quiet --disable-pip-version-check -c constraints.txt -e "$spec"
  # Compile the solver's numba kernels into their on-disk cache now, as part of installing,
  # so the first `vlp serve` after an install loads them instead of compiling them.
  OPENBLAS_NUM_THREADS=1 .venv/bin/python -c "from app.vlp.solvers import warm_up; warm_up()"
  echo "$want" > "$stamp"
fi
