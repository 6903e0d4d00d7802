#!/usr/bin/env bash
# Runs the whole test suite in ./.venv. Extra arguments go to pytest (e.g. -k conformance).
set -uo pipefail
cd "$(dirname "$0")/.."
export AMENT_PREFIX_PATH="$(pwd)/.venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
export PYTHONUNBUFFERED=1
# two workers by default (VLM_VPR_TEST_WORKERS=0: one process); each test file runs on one
# worker (--dist loadfile): module fixtures and a file's fixed ROS_DOMAIN_IDs stay together
workers="${VLM_VPR_TEST_WORKERS:-2}"
parallel=()
if [ "$workers" != "0" ] && .venv/bin/python -c "import xdist" 2>/dev/null; then
  parallel=(-n "$workers" --dist loadfile)
  # one OpenMP/BLAS thread per worker: two workers' spinning thread teams on two cores spent
  # 40 % of the CPU in the kernel and ran the suite slower than one process did
  export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}" OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}"
fi
.venv/bin/python -m pytest -q -ra "${parallel[@]}" "$@"
rc=$?
if [ "$rc" -eq 5 ]; then echo "pytest collected no tests" >&2; fi
exit "$rc"
