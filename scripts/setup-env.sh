#!/usr/bin/env bash
# Shared set-up for ./run and ./test: a project venv with the pinned dependency set.
# Re-installs only when pyproject.toml or constraints.txt changed since the last install.
#
# scripts/setup-env.sh [EXTRAS] [--no-warm-up]
#   EXTRAS        optional dependencies to install too (./test: dev)
#   --no-warm-up  install only; the caller compiles the solver's kernels itself
#                 (scripts/warm-up.sh), e.g. beside other work as ./test does
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
extras=""
warm_up=yes
for arg in "$@"; do
  case "$arg" in
    --no-warm-up) warm_up=no ;;
    -*) echo "setup-env.sh: unknown option $arg" >&2; exit 2 ;;
    *) extras="$arg" ;;
  esac
done
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
  if [[ $warm_up == yes ]]; then
    scripts/warm-up.sh
  fi
  echo "$want" > "$stamp"
fi
