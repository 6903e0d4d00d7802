"""The typed relocalization interfaces of the node (``vlm_vpr_interfaces``), ROS edge only.

* service ``relocalize_typed`` (``vlm_vpr_interfaces/srv/Relocalize``): the options of the
  three Trigger services as fields (``next_frame``, ``no_prior``), a per-call ``timeout_s``
  (0: the node's ``relocalize_wait_s``), the answer typed (``vlm_vpr_interfaces/msg/Answer``:
  outcome, status, position, sigma, protection level, ``p_correct``, flags, the frame's stamp,
  the reason when there is no fix);
* action ``relocalize`` (``vlm_vpr_interfaces/action/Relocalize``): the same with feedback by
  stage (waiting for a frame, asking the prior, retrieving, verifying) and cancel; a goal
  whose ``timeout_s`` is not a positive finite number of at most ``MAX_TIMEOUT_S`` is rejected
  (WARN naming the reason: the action protocol carries none); a goal beyond the admission
  limit is accepted and aborted at once with ``OUTCOME_BUSY`` (:mod:`vlm_vpr_ros.ros.requests`).

Both use the node's one request QoS (:data:`~vlm_vpr_ros.ros.requests.REQUEST_QOS`), and every
goal ends (succeeded, aborted, cancelled) before the action server is destroyed
(:meth:`TypedRelocalize.destroy` waits for the callers in progress, :class:`CallGate`).

The waiting and the rules (who still waits, abandoned answers never published) are the pure
runtime's (:meth:`vlm_vpr_ros.runtime.worker.QueryRuntime.relocalize_request`); messages are
built by :mod:`msg_adapters.answer`. The Trigger services stay (the compatibility path).
"""

from __future__ import annotations

import time
from typing import Any

from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from vlm_vpr_interfaces.action import Relocalize as RelocalizeAction
from vlm_vpr_interfaces.srv import Relocalize as RelocalizeSrv

from msg_adapters.answer import answer_msg
from msg_adapters.navsat import fix_fields
from vlm_vpr_ros.ros.requests import DRAIN_S, REQUEST_QOS, CallGate, timeout_problem
from vlm_vpr_ros.runtime.relocalize import (STAGES, RelocalizeKind, RelocalizeResult,
                                            no_answer_text)

TYPED_SERVICE = "relocalize_typed"
ACTION = "relocalize"
#: after a goal's execute callback returned, rclpy sends its result from an executor task
RESULT_GRACE_S = 0.3


def kind_of(request: Any) -> RelocalizeKind:
    return RelocalizeKind("next" if request.next_frame else "latest", not request.no_prior)


class TypedRelocalize:
    """The typed service and the action of one node (made at configure, gone at cleanup)."""

    def __init__(self, node: Any, gate: CallGate) -> None:
        self.node = node
        self.gate = gate  # the node's callers in progress (shared with the Trigger services)
        self._last_end = -RESULT_GRACE_S  # when the latest goal's execute callback returned
        group = ReentrantCallbackGroup()
        self.service = node.create_service(RelocalizeSrv, TYPED_SERVICE, self._on_service,
                                           qos_profile=REQUEST_QOS, callback_group=group)
        self.action = ActionServer(node, RelocalizeAction, ACTION, self._execute,
                                   goal_callback=self._on_goal,
                                   handle_accepted_callback=self._on_accepted,
                                   cancel_callback=lambda _goal: CancelResponse.ACCEPT,
                                   goal_service_qos_profile=REQUEST_QOS,
                                   result_service_qos_profile=REQUEST_QOS,
                                   cancel_service_qos_profile=REQUEST_QOS,
                                   callback_group=group)

    def destroy(self) -> None:
        """Every caller in progress answered first (the runtime was stopped: they hear
        NOT_ACTIVE), then the results sent, then the service and the action server go."""
        self.gate.close()
        drained = self.gate.wait_idle(DRAIN_S)
        if not drained:
            self.node.get_logger().error(
                f"{self.gate.in_progress} relocalize callers still in progress after "
                f"{DRAIN_S:g} s: destroying the action server anyway")
        # rclpy sends a goal's result from a task the executor runs after the execute
        # callback returned: give it that moment (no public hook tells when it is sent)
        time.sleep(max(0.0, RESULT_GRACE_S - (time.monotonic() - self._last_end)))
        self.node.destroy_service(self.service)
        self.action.destroy()

    # -- helpers ----
    def _answer(self, res: RelocalizeResult, message: str = "") -> Any:
        node = self.node
        fields = None
        out = res.outcome
        if out is not None and out.hypothesis is not None:
            fields = fix_fields(out.hypothesis, node.policy)
        frame_id = (node.cfg.frame_id or out.frame.frame_id) if out is not None else ""
        if not message and out is None and res.code == "not_active" and not self.gate.open:
            message = ("the node is shutting down (cleanup, shutdown or a signal): the request "
                       "ended without an answer [not_active]")
        elif not message and out is None:
            message = no_answer_text(res, node.resolve_topic_name("fix"))
        return answer_msg(res, fields, frame_id, message)

    def _run(self, request: Any, wait_s: float, cancelled=None, on_stage=None
             ) -> RelocalizeResult:
        runtime = self.node.runtime
        if runtime is None or not self.node._active:
            return RelocalizeResult("not_active")
        return runtime.relocalize_request(kind_of(request), wait_s, cancelled, on_stage)

    # -- service ----
    def _on_service(self, request: Any, response: Any) -> Any:
        why = timeout_problem(request.timeout_s, allow_default=True)
        if why:
            self.node.get_logger().warning(f"{TYPED_SERVICE}: request rejected: {why}")
            response.answer = self._answer(RelocalizeResult("rejected"), why)
            return response
        if not self.gate.enter():  # closing: answered at once
            response.answer = self._answer(RelocalizeResult("not_active"))
            return response
        try:
            wait_s = float(request.timeout_s) or self.node.cfg.relocalize_wait_s
            response.answer = self._answer(self._run(request, wait_s))
        finally:
            self.gate.leave()
        return response

    # -- action ----
    def _on_goal(self, goal: Any) -> GoalResponse:
        why = timeout_problem(goal.timeout_s, allow_default=False)
        if not why and not self.gate.open:
            why = "the node is shutting down"
        if why:
            self.node.get_logger().warning(f"{ACTION} action: goal rejected: {why}")
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def _on_accepted(self, goal_handle: Any) -> None:
        """An accepted goal counts as in progress until its execute callback returned (its
        result is set then), so destroy() never cuts a goal short."""
        self.gate.enter(force=True)
        goal_handle.execute()

    def _execute(self, goal_handle: Any) -> Any:
        try:
            return self._execute_goal(goal_handle)
        finally:
            self._last_end = time.monotonic()
            self.gate.leave()

    def _execute_goal(self, goal_handle: Any) -> Any:
        t0 = time.monotonic()
        request = goal_handle.request

        def on_stage(name: str) -> None:
            fb = RelocalizeAction.Feedback(stage=STAGES.index(name), stage_name=name,
                                           elapsed_s=time.monotonic() - t0)
            goal_handle.publish_feedback(fb)

        if self.gate.open:
            res = self._run(request, float(request.timeout_s),
                            cancelled=lambda: goal_handle.is_cancel_requested,
                            on_stage=on_stage)
        else:  # accepted just before the node started closing
            res = RelocalizeResult("not_active")
        result = RelocalizeAction.Result(answer=self._answer(res))
        if res.code == "cancelled" and goal_handle.is_cancel_requested:
            goal_handle.canceled()
        elif res.code in ("answered", "failed"):
            goal_handle.succeed()
        else:  # no_frame, timeout, not_active, busy (not admitted: retry later)
            goal_handle.abort()
        return result
