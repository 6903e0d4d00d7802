"""The query worker's side of the asynchronous prior contract (pure, no ROS).

The worker asks the prior provider when a query starts (:func:`request_prior`: a future; a
provider that raises is a failed prior, never a failed query), computes the descriptor
meanwhile, then waits for the prior at most ``prior_timeout_s`` after the request
(:func:`await_prior`). Every way a prior can fail (timeout, shutdown, an exception, a wrong
answer type) comes back as a :meth:`PriorResult.failure` (:mod:`vlm_vpr_ros.priors.provider`):
the query then localizes by flagged global retrieval.
"""

from __future__ import annotations

import concurrent.futures as cf
import time
from typing import Callable

from vlm_vpr_ros.priors.provider import PriorProvider, PriorQuery, PriorResult


def request_prior(provider: PriorProvider, query: PriorQuery) -> "cf.Future[PriorResult]":
    """``provider``'s future answer for ``query`` (already failed if the request raised)."""
    try:
        return provider.request(query)
    except Exception as exc:  # noqa: BLE001 - failures are values (priors/provider.py)
        fut: cf.Future[PriorResult] = cf.Future()
        fut.set_result(PriorResult.failure(provider.name, f"error: {exc}"))
        return fut


def await_prior(provider_name: str, future: "cf.Future[PriorResult]", t_start: float,
                timeout_s: float, stopping: Callable[[], bool]) -> PriorResult:
    """Wait for the prior until ``timeout_s`` after its request at ``t_start`` (monotonic), or
    until ``stopping()`` (the runtime shuts down); the future is cancelled then."""
    deadline = t_start + timeout_s
    while not future.done():
        left = deadline - time.monotonic()
        if left <= 0 or stopping():
            future.cancel()
            reason = "timeout" if left <= 0 else "shutdown"
            return PriorResult.failure(provider_name, reason,
                                       latency_s=time.monotonic() - t_start)
        cf.wait([future], timeout=min(left, 0.2))
    try:
        result = future.result()
    except Exception as exc:  # noqa: BLE001 - includes CancelledError
        return PriorResult.failure(provider_name, f"error: {exc}",
                                   latency_s=time.monotonic() - t_start)
    if not isinstance(result, PriorResult):
        return PriorResult.failure(provider_name, "error: provider returned "
                                   f"{type(result).__name__}")
    return result
