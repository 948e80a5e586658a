#!/usr/bin/env bash
# The install a user does, proved in virtual environments that see nothing of this machine's Python packages
# (created without --system-site-packages), each dependency resolved by pip from the registry as declared in
# pyproject.toml (torch pinned as the README pins it):
#   1. the README's steps in the checkout: `pip install torch==2.13.0 && pip install -e ".[dev]"`, then
#      `v2vsim run intersection --frames 3`;
#   2. the wheel: `pip wheel --no-deps -w dist .`, installed into a second fresh venv, then the same run from a
#      temporary folder outside the checkout.
# An import that pyproject.toml does not declare fails here, whatever the machine's own Python carries.
#   scripts/clean_install.sh [WORK_DIR]     (default: a new temporary folder, removed at the end)
set -euo pipefail
cd "$(dirname "$0")/.."
REPO=$PWD
PYTHON=${PYTHON:-python3}
WORK=${1:-$(mktemp -d -t v2vsim-clean-XXXXXX)}
[ $# -ge 1 ] || trap 'rm -rf "$WORK"' EXIT
mkdir -p "$WORK"
# A PYTHONPATH or a user site would let the image's packages back in.
unset PYTHONPATH PYTHONHOME
export PYTHONNOUSERSITE=1 PIP_DISABLE_PIP_VERSION_CHECK=1
RUN=(run intersection --frames 3 --set output.rerun=false)

step() { printf '\n== %s (%s)\n' "$1" "$(date +%T)"; }
# pip, without the lines this machine's pip configuration adds for every package (an index folder it lacks)
pip() { command pip "$@" 2>&1 | { grep -v 'is ignored: it is neither a file nor a directory' || true; }; }

fresh_venv() {  # fresh_venv DIR: a venv that cannot see the system's site-packages; fails if it can
  "$PYTHON" -m venv "$1"
  "$1/bin/python" - <<'PY'
import sys
assert sys.prefix != sys.base_prefix, "not a virtual environment"
leak = [p for p in sys.path if "site-packages" in p and not p.startswith(sys.prefix)]
assert not leak, f"the venv sees site-packages outside itself: {leak}"
PY
}

step "1. the README's install steps in a fresh venv"
fresh_venv "$WORK/venv_readme"
(
  . "$WORK/venv_readme/bin/activate"
  pip install -q torch==2.13.0 && pip install -q -e ".[dev]"
  step "1. v2vsim ${RUN[*]} (in the checkout)"
  out="$WORK/readme_run"
  v2vsim "${RUN[@]}" --out "$out"
  python -c "import json,sys; m=json.load(open(sys.argv[1])); print('status', m['status'], '| methods', len(m['methods']))" "$out/metrics.json"
)

step "2. the wheel, installed into a second fresh venv"
rm -rf "$WORK/dist"
"$WORK/venv_readme/bin/pip" wheel -q --no-deps -w "$WORK/dist" "$REPO"
fresh_venv "$WORK/venv_wheel"
(
  . "$WORK/venv_wheel/bin/activate"
  pip install -q torch==2.13.0 && pip install -q "$WORK"/dist/v2vsim-*.whl
  mkdir -p "$WORK/elsewhere" && cd "$WORK/elsewhere"
  step "2. v2vsim ${RUN[*]} (from $PWD)"
  python -c "import v2vsim, models.zoo as z; print('v2vsim from', v2vsim.__file__, '| zoo', z.WEIGHTS_DIR)"
  v2vsim "${RUN[@]}"
  python -c "import json; m=json.load(open('runs/intersection/metrics.json')); print('status', m['status'], '| methods', len(m['methods']))"
)
step "clean install: both ok"
