#!/usr/bin/env bash
# The path a new user takes: a fresh virtual environment, `pip install -e ".[test]"` resolving every dependency to
# the newest version pyproject.toml allows, then the test suite in that environment. Prints the time each step took
# and the versions pip resolved (docs/ci.md records them).
#   usage: bash .ci/fresh_venv.sh [pytest args...]      (default: -q, the whole suite)
#   MATCAP_CI_VENV=DIR   where to build it (default: a new temporary folder, removed afterwards)
set -euo pipefail
cd "$(dirname "$0")/.."
VENV="${MATCAP_CI_VENV:-$(mktemp -d "${TMPDIR:-/tmp}/matcap-fresh-venv.XXXXXX")}"
[ -n "${MATCAP_CI_VENV:-}" ] || trap 'rm -rf "$VENV"' EXIT
rm -rf "$VENV"
t0=$(date +%s)
python -m venv "$VENV"
# No cache, no machine site-packages: what a new user's first `pip install` resolves today.
# (grep drops pip's notes about this machine's local package folders that hold none of these packages)
"$VENV/bin/python" -m pip install -q --no-cache-dir -e ".[test]" 2>&1 | { grep -v "^WARNING: Location 'file:" || true; }
t1=$(date +%s)
echo "fresh venv: python -m venv + pip install -e .[test] took $((t1 - t0)) s"
echo "fresh venv: resolved versions:"
"$VENV/bin/python" -m pip list --format=freeze --exclude-editable | sed 's/^/  /'
# torch must be the CPU build: a CUDA build of torch 2.13.0 is several GB of nvidia-* wheels a CPU user never uses.
"$VENV/bin/python" - <<'PY'
import importlib.metadata as md
import torch
cuda = sorted(d.metadata["Name"] for d in md.distributions() if d.metadata["Name"].lower().startswith("nvidia"))
print(f"fresh venv: torch {torch.__version__}, CUDA build: {torch.version.cuda}, nvidia packages: {cuda or 'none'}")
if torch.version.cuda is not None or cuda:
    raise SystemExit("fresh venv: pip installed a CUDA build of torch; install the CPU build first "
                     "(README: `pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu`)")
PY
# Only the new environment's Python and the matcap it installed: not the machine's. pytest's last line (its
# count and time) stays the last line of the log.
PATH="$VENV/bin:$PATH" "$VENV/bin/python" -m pytest "${@:--q}"
