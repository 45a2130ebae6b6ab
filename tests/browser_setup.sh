#!/usr/bin/env bash
# Set-up for the annotation tool's browser tests (tests/test_annotate_browser.py): Debian's chromium
# from apt when it is missing. The playwright Python package comes from the [test] extra and carries
# its own driver; never `playwright install` (no browser download).
set -euo pipefail
if ! command -v chromium >/dev/null 2>&1; then
  SUDO=""
  if [ "$(id -u)" != "0" ]; then SUDO="sudo"; fi
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium >/dev/null
fi
chromium --version
