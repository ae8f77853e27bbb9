#!/usr/bin/env bash
# Debian's chromium for the browser test of `aesplat view` and scripts/view_screenshot.py: installed with apt-get
# when missing (as root; nothing else is downloaded: no browser build of its own). Prints the version.
set -euo pipefail
if ! command -v chromium >/dev/null; then
  if [ "$(id -u)" -ne 0 ]; then
    echo "install_chromium: chromium is not installed; as root: apt-get install -y chromium" >&2
    exit 1
  fi
  command -v apt-get >/dev/null || { echo "install_chromium: no apt-get to install chromium" >&2; exit 1; }
  echo "install_chromium: installing chromium (apt-get)" >&2
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq chromium >/dev/null
fi
chromium --version 2>/dev/null | head -1
