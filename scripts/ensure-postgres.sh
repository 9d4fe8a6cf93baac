#!/usr/bin/env bash
# The test suite runs the registry on the real PostgreSQL at 127.0.0.1:5432 (database `test`).
# Start the local cluster when it does not answer; fail loudly if it cannot be reached.
set -euo pipefail
url="${VLP_TEST_POSTGRES_URL:-postgresql://postgres@127.0.0.1:5432/test}"
answers() { pg_isready -q -h 127.0.0.1 -p 5432 2>/dev/null; }
if ! answers; then
  if command -v pg_ctlcluster >/dev/null 2>&1 && [[ -d /etc/postgresql ]]; then
    pg_ctlcluster --skip-systemctl-redirect "$(ls /etc/postgresql | head -n1)" main start || true
  fi
  for _ in $(seq 1 30); do answers && break; sleep 1; done
fi
if ! answers; then
  echo "PostgreSQL at 127.0.0.1:5432 does not answer; the suite needs it ($url)" >&2
  exit 1
fi
