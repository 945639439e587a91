#!/usr/bin/env bash
# One-command set-up: system libraries, then matcap and its Python dependencies (editable install).
#   - libllvm19: Mitsuba's fast llvm_ad_rgb variant (older LLVMs abort; without it matcap falls back to scalar_rgb)
#   - chromium: headless browser for the gallery page test
#   - tools/node: the Khronos glTF validator (npm) used by the export tests
set -euo pipefail
cd "$(dirname "$0")"
if command -v apt-get >/dev/null 2>&1; then
    SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends libllvm19 chromium ffmpeg >/dev/null
fi
python -m pip install -q -e ".[test]"
if [ -f tools/node/package-lock.json ] && command -v npm >/dev/null 2>&1; then
    (cd tools/node && npm ci --silent --no-audit --no-fund)
fi
echo "matcap is installed: try 'matcap capture examples/bunny --linear --out bunny-maps'"
