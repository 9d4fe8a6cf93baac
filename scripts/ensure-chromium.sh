#!/usr/bin/env bash
# Install Debian's Chromium and its chromedriver when they are missing: the Swagger UI browser
# test (tests/e2e/test_swagger_ui.py) drives them through selenium. Needs root (apt-get).
set -euo pipefail
if [ -x /usr/bin/chromium ] && [ -x /usr/bin/chromedriver ]; then
  exit 0
fi
if [ "$(id -u)" -ne 0 ]; then
  echo "ensure-chromium: /usr/bin/chromium or /usr/bin/chromedriver is missing and we are not" \
    "root; install the Debian packages chromium and chromium-driver" >&2
  exit 1
fi
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq
apt-get install -y -qq --no-install-recommends chromium chromium-driver >/dev/null
