#!/usr/bin/env bash
# Build the vlm_vpr_interfaces package (typed relocalize service/action, answer messages) with
# cmake + g++ against the PyPI ROS wheels in ./.venv and install it into the venv, the way
# colcon would on a ROS install (there: `colcon build --packages-select vlm_vpr_interfaces`).
# Skipped when up to date: a stamp holds the hash of the interface sources, this script and
# the venv's python; files `cmake --install` put into the venv are not pip's, so setup.sh
# removes the stamp whenever it creates a new venv.
set -euo pipefail
cd "$(dirname "$0")/.."
V="$(pwd)/.venv"
PY="$V/bin/python"
SRC=vlm_vpr_interfaces
STAMP="$V/share/vlm_vpr_interfaces/.vlm_vpr_build_stamp"
BUILD=${VLM_VPR_INTERFACES_BUILD:-build/vlm_vpr_interfaces}
for tool in cmake g++; do
  command -v "$tool" >/dev/null || { echo "$tool is required to build $SRC (apt-get install \
cmake g++)" >&2; exit 1; }
done
hash=$( (find "$SRC" -type f -print0 | sort -z | xargs -0 sha256sum; sha256sum "$0";
         "$PY" -c 'import sys; print(sys.version, sys.prefix)') | sha256sum | cut -d' ' -f1)
if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$hash" ] \
   && "$PY" -c 'import vlm_vpr_interfaces.action' 2>/dev/null; then
  echo "vlm_vpr_interfaces up to date"
  exit 0
fi
echo "building vlm_vpr_interfaces (cmake + g++, about a minute on 2 cores)"
export AMENT_PREFIX_PATH="$V" CMAKE_PREFIX_PATH="$V" PATH="$V/bin:$PATH"
rm -rf "$BUILD" && mkdir -p "$(dirname "$BUILD")"
# -DPython3_EXECUTABLE: the venv's interpreter (its site-packages, its NumPy headers);
# VLM_VPR_REPOINT_PY_HEADERS: the wheels' *__rosidl_generator_py targets name the include
# paths of the machine that built them (CMakeLists.txt re-points them at this interpreter's)
cmake -S "$SRC" -B "$BUILD" -DCMAKE_INSTALL_PREFIX="$V" -DCMAKE_BUILD_TYPE=Release \
  -DPython3_EXECUTABLE="$PY" -DVLM_VPR_REPOINT_PY_HEADERS=ON -DBUILD_TESTING=OFF \
  > "$BUILD.log" 2>&1 || { tail -20 "$BUILD.log" >&2; echo "cmake failed: $BUILD.log" >&2; exit 1; }
cmake --build "$BUILD" -j"$(nproc)" >> "$BUILD.log" 2>&1 \
  || { grep -m5 -B2 -A5 -i error "$BUILD.log" >&2; echo "build failed: $BUILD.log" >&2; exit 1; }
cmake --install "$BUILD" >> "$BUILD.log" 2>&1
"$PY" -c 'import vlm_vpr_interfaces.action, vlm_vpr_interfaces.msg, vlm_vpr_interfaces.srv'
echo "$hash" > "$STAMP"
echo "vlm_vpr_interfaces built and installed into $V"
