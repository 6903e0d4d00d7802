"""The ``map_reload`` service's logic (pure, no ROS): re-read the map from its folder and swap
it in between two queries; on any failure the current map stays in use.

Active node: the running :class:`~vlm_vpr_ros.runtime.worker.QueryRuntime` swaps it
(:meth:`~vlm_vpr_ros.runtime.worker.QueryRuntime.reload_map`: the running query finishes on the
map it started with). Inactive (lifecycle): the loaded pipeline is replaced, used from the next
activate. One reload at a time (:class:`MapReloader`): a call during a reload is answered at
once, busy, so a burst of callers never queues behind a slow reload.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from vlm_vpr_ros.errors import VlmVprError
from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
from vlm_vpr_ros.redact import redact

log = logging.getLogger(__name__)
#: the answer to a map_reload call made while a reload runs
BUSY = ("busy: a map reload is already running; call map_reload again when it has answered "
        "to read changes made since it started")


def reload_pipeline(pipe: LocalizationPipeline) -> tuple[LocalizationPipeline | None, str]:
    """``pipe``'s map re-read from disk, or (None, why, redacted) on any failure: the
    ``map_reload`` service answers it and the node keeps its current map."""
    try:
        return pipe.reloaded(), ""
    except (VlmVprError, OSError) as exc:
        log.error("map reload failed, keeping the current map: %s", exc)
        return None, redact(exc)
    except Exception as exc:  # noqa: BLE001 - a service call must not stop the node
        log.exception("map reload failed, keeping the current map")
        return None, redact(f"internal error {type(exc).__name__}: {exc}")


def reloaded_text(old: LocalizationPipeline, new: LocalizationPipeline, took_s: float) -> str:
    """The one-line answer of a reload that swapped ``old``'s map for ``new``'s."""
    om, nm = old.map, new.map
    return (f"map {nm.path} reloaded in {took_s:.1f} s: {om.n_references} -> "
            f"{nm.n_references} references, {len(om.submaps)} -> {len(nm.submaps)} submaps "
            f"(generation {om.manifest.get('generation', 0)} -> "
            f"{nm.manifest.get('generation', 0)})")


class MapReloader:
    """One node's map reloads: one at a time, a second caller answered :data:`BUSY` at once."""

    def __init__(self) -> None:
        self._running = threading.Lock()

    def reload(self, runtime: Any, pipeline: LocalizationPipeline | None, map_dir: str
               ) -> tuple[bool, str, LocalizationPipeline | None]:
        """(success, one-line answer, the pipeline the node uses from now on; None: keep the
        one it has). ``runtime``: the active node's QueryRuntime (it swaps the map), None
        while inactive (``pipeline``, the loaded one, is replaced; None: nothing is loaded)."""
        if not self._running.acquire(blocking=False):
            return False, BUSY, None
        try:
            if runtime is not None:
                ok, text = runtime.reload_map()
                return ok, text, runtime.pipeline
            new, why = (reload_pipeline(pipeline) if pipeline is not None
                        else (None, "no map loaded: configure first"))
            if new is None:
                return False, f"map reload failed: {why}", None
            return True, (f"map {map_dir} reloaded: {new.map.n_references} references (used "
                          "from the next activate)"), new
        finally:
            self._running.release()
