#!/usr/bin/env bash
# The web console's tests drive a real Chromium (tests/service/test_console.py). Playwright cannot
# download its own browser here, so Debian's package is used: installed when missing (apt-get, with
# sudo when not root). If it cannot be installed this fails loudly: the tests must not skip.
set -euo pipefail
for b in chromium chromium-browser google-chrome google-chrome-stable; do
    if command -v "$b" >/dev/null 2>&1; then
        exit 0
    fi
done
if [ -n "${GEOMATCH_CHROMIUM:-}" ] && [ -x "$GEOMATCH_CHROMIUM" ]; then
    exit 0
fi
echo "ensure_browser: no Chromium on PATH; installing Debian's chromium package"
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
    if command -v sudo >/dev/null 2>&1; then
        SUDO="sudo -n"
    else
        echo "ensure_browser: not root and no sudo: install Chromium (apt-get install chromium) or set" \
            "GEOMATCH_CHROMIUM; the web console's browser tests cannot run without it" >&2
        exit 1
    fi
fi
if ! command -v apt-get >/dev/null 2>&1; then
    echo "ensure_browser: no apt-get on this machine: install Chromium by hand or set GEOMATCH_CHROMIUM" >&2
    exit 1
fi
export DEBIAN_FRONTEND=noninteractive
if ! { $SUDO apt-get update -qq && $SUDO apt-get install -y -qq --no-install-recommends chromium; }; then
    echo "ensure_browser: apt-get could not install chromium; the web console's browser tests need it" >&2
    exit 1
fi
command -v chromium >/dev/null 2>&1 || { echo "ensure_browser: chromium still missing after install" >&2; exit 1; }
chromium --version 2>/dev/null || true
