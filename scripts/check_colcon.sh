#!/usr/bin/env bash
# Check that `colcon build` (the path of a ROS install) builds vlm_vpr_interfaces here, against
# the PyPI ROS wheels in ./.venv (no ROS install needed), in a throw-away workspace, and that
# rclpy can use the types from colcon's install space: a message serialization round trip, a
# service call and an action goal with feedback, in one process. Nothing is installed into
# .venv (the types come from the workspace's install/, sourced like on a robot).
#
# colcon: $COLCON when set, else `colcon` on PATH, else colcon is pip-installed into a
# temporary venv (the versions this was measured with; needs the package index).
# KEEP=1 keeps the workspace (its build log) instead of deleting it.
set -euo pipefail
cd "$(dirname "$0")/.."
V="$(cd .venv && pwd -P)"
PY="$V/bin/python"
SRC="$(pwd)/vlm_vpr_interfaces"
WORK=$(mktemp -d "${TMPDIR:-/tmp}/vlm_vpr_colcon.XXXXXX")
if [ "${KEEP:-0}" = 1 ]; then echo "workspace kept: $WORK"; else trap 'rm -rf "$WORK"' EXIT; fi
for tool in cmake g++; do
  command -v "$tool" >/dev/null || { echo "$tool is required (apt-get install cmake g++)" >&2
                                      exit 1; }
done
COLCON=${COLCON:-$(command -v colcon || true)}
if [ -z "$COLCON" ]; then
  echo "colcon not found: installing it into $WORK/colcon-venv (not into .venv)"
  "$PY" -m venv "$WORK/colcon-venv"
  "$WORK/colcon-venv/bin/pip" install -q colcon-core==0.21.3 colcon-cmake==0.2.30 \
    colcon-ros==0.5.0 colcon-library-path==0.2.1 colcon-package-selection==0.2.10 \
    colcon-parallel-executor==0.4.0 colcon-output==0.2.15 > "$WORK/pip.log" 2>&1 \
    || { tail -5 "$WORK/pip.log" >&2; echo "pip could not install colcon (no package index?)" >&2
         exit 1; }
  COLCON="$WORK/colcon-venv/bin/colcon"
fi
mkdir -p "$WORK/ws/src"
cp -r "$SRC" "$WORK/ws/src/"
cd "$WORK/ws"
# like scripts/build_interfaces.sh: the venv is the underlay (its ament index, its CMake
# packages, its python); the wheels' *__rosidl_generator_py targets are re-pointed at it
export AMENT_PREFIX_PATH="$V" CMAKE_PREFIX_PATH="$V" PATH="$V/bin:$PATH"
t0=$(date +%s)
nice -n 10 "$COLCON" build --base-paths src/vlm_vpr_interfaces \
  --event-handlers console_direct+ \
  --cmake-args -DPython3_EXECUTABLE="$PY" -DVLM_VPR_REPOINT_PY_HEADERS=ON \
  -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release > colcon.log 2>&1 \
  || { tail -30 colcon.log >&2; echo "colcon build failed (log: $WORK/ws/colcon.log; KEEP=1" \
       "keeps it)" >&2; exit 1; }
echo "colcon build: $(grep -m1 '^Summary:' colcon.log), $(( $(date +%s) - t0 )) s wall" \
     "(colcon at $COLCON)"
set +u
. install/setup.sh
set -u
export VLM_VPR_WS_INSTALL="$WORK/ws/install" ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-91}
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
"$PY" - <<'EOF'
import math
import os
import threading
import time

import rclpy
from rclpy.action import ActionClient, ActionServer
from rclpy.executors import MultiThreadedExecutor
from rclpy.serialization import deserialize_message, serialize_message

import vlm_vpr_interfaces
from vlm_vpr_interfaces.action import Relocalize as RelocalizeAction
from vlm_vpr_interfaces.msg import Answer, Candidate
from vlm_vpr_interfaces.srv import Relocalize

where = os.path.realpath(vlm_vpr_interfaces.__file__)
assert where.startswith(os.path.realpath(os.environ["VLM_VPR_WS_INSTALL"])), where
a = Answer(outcome=Answer.OUTCOME_ANSWERED, success=True, status=Answer.STATUS_FIX,
           latitude=37.7749, longitude=-122.4194, sigma_m=12.5, protection_m=math.nan,
           flags=["no_prior"], reference_id="ref.jpg",
           candidates=[Candidate(rank=1, reference_id="ref.jpg", inliers=42)])
b = deserialize_message(serialize_message(a), Answer)
assert (b.latitude, b.longitude, b.sigma_m, list(b.flags)) == (37.7749, -122.4194, 12.5,
                                                              ["no_prior"])
assert math.isnan(b.protection_m) and b.candidates[0].inliers == 42

rclpy.init()
node = rclpy.create_node("vlm_vpr_colcon_check")


def serve(req, resp):
    resp.answer = Answer(outcome=Answer.OUTCOME_ANSWERED, latitude=1.0 + req.timeout_s,
                         reason="no_prior" if req.no_prior else "")
    return resp


def act(goal):
    for stage in range(4):
        goal.publish_feedback(RelocalizeAction.Feedback(stage=stage, stage_name=f"s{stage}"))
    goal.succeed()
    return RelocalizeAction.Result(answer=Answer(latitude=goal.request.timeout_s))


node.create_service(Relocalize, "colcon_check_relocalize", serve)
ActionServer(node, RelocalizeAction, "colcon_check_action", act)
ex = MultiThreadedExecutor()
ex.add_node(node)
threading.Thread(target=ex.spin, daemon=True).start()
cli = node.create_client(Relocalize, "colcon_check_relocalize")
assert cli.wait_for_service(timeout_sec=10), "service not found"
r = cli.call(Relocalize.Request(no_prior=True, timeout_s=2.0), timeout_sec=10)
assert r.answer.latitude == 3.0 and r.answer.reason == "no_prior", r
ac = ActionClient(node, RelocalizeAction, "colcon_check_action")
assert ac.wait_for_server(timeout_sec=10), "action server not found"
stages = []
fut = ac.send_goal_async(RelocalizeAction.Goal(timeout_s=5.0),
                         feedback_callback=lambda f: stages.append(f.feedback.stage))
t_end = time.monotonic() + 10
while not fut.done() and time.monotonic() < t_end:
    time.sleep(0.05)
res = fut.result().get_result_async()
while not res.done() and time.monotonic() < t_end:
    time.sleep(0.05)
assert res.result().result.answer.latitude == 5.0 and stages == [0, 1, 2, 3], stages
ex.shutdown()
node.destroy_node()
rclpy.shutdown()
print(f"types from {os.path.dirname(where)}: serialization round trip, service call, action "
      f"goal with {len(stages)} feedback stages: ok")
EOF
