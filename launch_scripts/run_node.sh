#!/usr/bin/env bash
# Start vlm_vpr_node without `ros2 launch` (pip-installed ROS 2 has no ros2 CLI).
#
#   launch_scripts/run_node.sh [--help] [--lifecycle] [PARAMS.yaml] [ros-args...]
#
# --lifecycle starts the managed variant (unconfigured; drive it through its lifecycle services).
# PARAMS.yaml defaults to launch_scripts/vlm_vpr_params.yaml; everything else is appended after
# --ros-args (it overrides the file), e.g.
#
#   launch_scripts/run_node.sh -p map_dir:=demo_out/map -p prior_provider:=fixed \
#       -p prior.lat:=48.85 -p prior.lon:=2.35 -r image:=/camera/image_raw
#
# The Python interpreter is $PYTHON, else the repository's .venv, else python3. `exec` keeps the
# node's PID equal to this script's, so `kill <pid>` (SIGINT/SIGTERM) stops the node cleanly.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(dirname "$here")"
py="${PYTHON:-}"
if [[ -z "$py" ]]; then
  if [[ -x "$repo/.venv/bin/python" ]]; then py="$repo/.venv/bin/python"; else py=python3; fi
fi
variant=()
if [[ $# -gt 0 && ( "$1" == "--help" || "$1" == "-h" ) ]]; then
  exec "$py" -m vlm_vpr_ros.ros.node --help  # the parameters, exit 0
fi
if [[ $# -gt 0 && "$1" == "--lifecycle" ]]; then
  variant=(--lifecycle)
  shift
fi
params="$here/vlm_vpr_params.yaml"
if [[ $# -gt 0 && ( "$1" == *.yaml || "$1" == *.yml ) ]]; then
  params="$1"
  shift
fi
if [[ ! -f "$params" ]]; then
  echo "run_node.sh: params file not found: $params" >&2
  exit 2
fi
exec "$py" -m vlm_vpr_ros.ros.node "${variant[@]}" --ros-args --params-file "$params" "$@"
