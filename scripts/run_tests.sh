#!/usr/bin/env bash
# Runs the whole test suite in ./.venv. Extra arguments go to pytest (e.g. -k conformance).
set -uo pipefail
cd "$(dirname "$0")/.."
export AMENT_PREFIX_PATH="$(pwd)/.venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
export PYTHONUNBUFFERED=1
.venv/bin/python -m pytest -q -ra "$@"
rc=$?
if [ "$rc" -eq 5 ]; then echo "pytest collected no tests" >&2; fi
exit "$rc"
