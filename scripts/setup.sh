#!/usr/bin/env bash
# One command installs everything vlm_vpr_ros needs into ./.venv (Debian/Ubuntu, Python 3.11+).
# torch is installed on its own, pinned, so no resolver can ever pull the multi-GB CUDA build.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
"$PY" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)' \
  || { echo "Python 3.11+ required (found $("$PY" --version))" >&2; exit 1; }
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
# CPU build of torch 2.13.0; on a CUDA machine set TORCH_SPEC to your wheel/index of choice.
.venv/bin/python -m pip install -q "${TORCH_SPEC:-torch==2.13.0}"
.venv/bin/python -m pip install -q -r requirements.txt
# The package itself (editable): console scripts vlm-vpr / vlm_vpr_node, share/ data files.
.venv/bin/python -m pip install -q --no-deps --no-build-isolation -e .
echo "vlm_vpr_ros installed in $(pwd)/.venv — activate with: source .venv/bin/activate"
