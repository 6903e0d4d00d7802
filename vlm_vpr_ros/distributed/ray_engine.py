"""The Ray engine: a Ray Data actor pool describes images; fit, partition and index builds run
as Ray tasks. Ray is imported here only, and only when this engine is used.

- **Connecting**: no address starts a Ray on this machine (``ray.init``); ``auto`` joins the
  cluster this machine belongs to; ``HOST:PORT`` joins a cluster's GCS (a driver on a cluster
  node); ``ray://HOST:PORT`` uses Ray Client (a driver outside the cluster). An unreachable
  address fails within ``CONNECT_TIMEOUT_S`` with one line (exit 2 from the CLI).
- **Describing**: ``ray.data.from_arrow`` over the (row, id) list of unfinished shards →
  ``map_batches(_Describer, compute=ActorPoolStrategy(size=workers), num_gpus=…)``: each actor
  loads the model once (and the fitted state, broadcast through the object store), reads its
  images from the shared folder or object store, and returns descriptors; the driver streams
  the results (``iter_batches``) into shards. Ray restarts a killed actor and retries its
  batch; rows answered twice are ignored by the driver.
"""

from __future__ import annotations

import logging
import math
import socket
import time
from typing import Any, Iterator, Mapping
from urllib.parse import urlsplit

import numpy as np

from vlm_vpr_ros.descriptors import create_descriptor
from vlm_vpr_ros.distributed.engines import describe_items, fit_on_sample
from vlm_vpr_ros.errors import ConfigError, DescriptorError, VlmVprError
from vlm_vpr_ros.mapping.assemble import new_index
from vlm_vpr_ros.maps.format import check_descriptor_identity
from vlm_vpr_ros.maps.partition import make_partition

log = logging.getLogger(__name__)

#: seconds to wait for a --ray-address to answer before giving up with a clear error
CONNECT_TIMEOUT_S = 10.0
#: at most this many input blocks (each one task of the actor pool; retried as a unit)
MAX_BLOCKS = 4000


class RayEngineError(VlmVprError):
    """The Ray cluster cannot be reached or used."""


def import_ray() -> Any:
    try:
        import ray
    except ImportError as exc:
        raise ConfigError("--engine ray needs Ray: pip install 'ray[data,client]==2.60.0' "
                          "(listed in requirements.txt)") from exc
    return ray


def _host_port(address: str) -> tuple[str, int]:
    rest = address[len("ray://"):] if address.startswith("ray://") else address
    try:
        parts = urlsplit(f"//{rest}")
        host, port = parts.hostname, parts.port
    except ValueError:
        host = port = None
    if not host or not port:
        raise ConfigError(f"--ray-address {address!r}: expected auto, HOST:PORT or "
                          "ray://HOST:PORT")
    return host, port


def check_reachable(address: str, timeout: float = CONNECT_TIMEOUT_S) -> None:
    """RayEngineError (one line) unless HOST:PORT of ``address`` accepts a TCP connection."""
    host, port = _host_port(address)
    try:
        socket.create_connection((host, port), timeout=timeout).close()
    except OSError as exc:
        reason = "timed out" if isinstance(exc, TimeoutError) else (exc.strerror or str(exc))
        raise RayEngineError(f"cannot reach the Ray cluster at {address}: {reason} (is "
                             f"'ray start --head' running there, and the port open?)") from None


class RaySession:
    """A connection to Ray for one job; ``close()`` shuts down a Ray it started itself."""

    def __init__(self, opts) -> None:
        self.opts = opts
        self.ray: Any = None
        self.owned = False
        self.workers = 1

    def __enter__(self) -> "RaySession":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def start(self) -> None:
        ray = self.ray = import_ray()
        address = self.opts.ray_address
        if ray.is_initialized():
            log.info("using the Ray runtime already initialised in this process")
        elif address is None:
            kwargs = {"include_dashboard": False, "configure_logging": False,
                      "log_to_driver": False}
            if self.opts.workers:
                kwargs["num_cpus"] = int(math.ceil(self.opts.workers
                                                   * self.opts.num_cpus_per_worker))
            kwargs.update(self.opts.ray_init)
            ray.init(**kwargs)
            self.owned = True
        else:
            if address != "auto":
                check_reachable(address)
            t0 = time.monotonic()
            try:
                ray.init(address=address, configure_logging=False, log_to_driver=False)
            except (ConnectionError, RuntimeError, ValueError, TimeoutError,
                    ray.exceptions.RayError) as exc:
                first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
                raise RayEngineError(f"cannot connect to the Ray cluster at {address}: "
                                     f"{first}") from None
            log.info("connected to Ray at %s in %.1f s", address, time.monotonic() - t0)
        self._quiet_ray_data()
        self.workers = self._workers()

    def _quiet_ray_data(self) -> None:
        import ray.data

        ctx = ray.data.DataContext.get_current()
        ctx.enable_progress_bars = False  # the driver shows its own bar with images/s and ETA
        for attr in ("enable_operator_progress_bars", "print_on_execution_start",
                     "verbose_stats_logs"):
            if hasattr(ctx, attr):
                setattr(ctx, attr, False)
        logging.getLogger("ray.data").setLevel(logging.WARNING)

    def _workers(self) -> int:
        if self.opts.workers:
            return int(self.opts.workers)
        res = self.ray.cluster_resources()
        if self.opts.num_gpus_per_worker > 0:
            n = res.get("GPU", 0) / self.opts.num_gpus_per_worker
            if n < 1:
                raise RayEngineError(f"--num-gpus-per-worker {self.opts.num_gpus_per_worker}: "
                                     f"the cluster has {res.get('GPU', 0):g} GPUs")
        else:
            n = res.get("CPU", 1) / self.opts.num_cpus_per_worker
        return max(1, int(n))

    def close(self) -> None:
        if self.ray is not None and self.owned and self.ray.is_initialized():
            self.ray.shutdown()
        self.owned = False

    # -- the pieces of a job --------------------------------------------------------------------
    def describer(self, source) -> "RayDescriber":
        return RayDescriber(self, source)

    def partition(self, method: str, lat, lon, clusters: int, seed: int):
        """``make_partition`` as one Ray task."""
        task = self.ray.remote(num_cpus=1, max_retries=2)(make_partition)
        return self.ray.get(task.remote(method, np.asarray(lat), np.asarray(lon), clusters,
                                        seed))

    def build_indexes(self, kind: str, dim: int, parts: list[np.ndarray]) -> list[Any]:
        """One Ray task per submap builds its FAISS index (returned serialised)."""
        import faiss

        task = self.ray.remote(num_cpus=1, max_retries=2)(_index_bytes)
        refs = [task.remote(kind, dim, p) for p in parts]
        return [faiss.deserialize_index(b) for b in self.ray.get(refs)]


def _index_bytes(kind: str, dim: int, vectors: np.ndarray) -> np.ndarray:
    import faiss

    index = new_index(kind, dim)
    index.add(np.ascontiguousarray(vectors, dtype=np.float32))
    return faiss.serialize_index(index)


def _fit_task(name: str, config: Mapping[str, Any], source, sample_ids: list[str]):
    return fit_on_sample(create_descriptor(name, config), source, sample_ids)


class _Describer:
    """A Ray Data actor: loads the descriptor once, then describes batches of (row, id)."""

    def __init__(self, name: str, config: Mapping[str, Any], state: Mapping[str, np.ndarray],
                 identity: Mapping[str, Any], source) -> None:
        self.desc = create_descriptor(name, config)
        if state:
            self.desc.load_state(state)
        # A node with other weights (or another release) must not mix its descriptors in.
        check_descriptor_identity(identity, self.desc.identity())
        mine = self.desc.identity().get("weights_sha256")
        if mine != identity.get("weights_sha256"):
            raise DescriptorError(f"{name}: this worker's weights (sha256 {mine}) differ from "
                                  f"the driver's ({identity.get('weights_sha256')})")
        self.source = source

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, Any]:
        items = list(zip(batch["i"].tolist(), [str(x) for x in batch["id"]]))
        idx, ok, feats, reasons = describe_items(self.desc, self.source, items)
        return {"i": idx, "ok": ok, "desc": feats, "reason": np.array(reasons, dtype=object)}


class RayDescriber:
    """The describe engine on a :class:`RaySession`."""

    def __init__(self, session: RaySession, source) -> None:
        self.session, self.source = session, source
        self.workers = session.workers
        self.opts = session.opts

    def _worker_config(self, config: Mapping[str, Any]) -> dict[str, Any]:
        """Deep models on a GPU share: batches of --batch-size on the GPU Ray assigned."""
        cfg = dict(config)
        if self.opts.num_gpus_per_worker > 0 and "device" in cfg:
            if cfg.get("device") in (None, "auto"):
                cfg["device"] = "cuda"
            if cfg.get("batch_size") is None:
                cfg["batch_size"] = min(self.opts.batch_size, 1024)
        return cfg

    def fit(self, name: str, config: Mapping[str, Any], sample_ids: list[str]):
        """Fit once on the sample; the state then reaches every actor through the object
        store. ``fit_on="driver"`` (default) fits in this process, as the local build does:
        faiss k-means depends on the thread count, so this gives the local build's state bit
        for bit. ``"cluster"`` runs it as one Ray task (for drivers that cannot read the
        images, e.g. Ray Client from a laptop)."""
        t0 = time.monotonic()
        if self.opts.fit_on == "driver":
            state = fit_on_sample(create_descriptor(name, config), self.source, sample_ids)
        else:
            ray = self.session.ray
            task = ray.remote(num_cpus=1, max_retries=2)(_fit_task)
            state = ray.get(task.remote(name, dict(config), self.source, sample_ids))
        log.info("fitted %s on the %s in %.1f s", name, self.opts.fit_on,
                 time.monotonic() - t0)
        return state

    def map(self, items: list[tuple[int, str]], name: str, config: Mapping[str, Any],
            state: Mapping[str, np.ndarray], identity: Mapping[str, Any]) -> Iterator:
        import pyarrow as pa
        import ray.data

        if not items:
            return

        bs = self.opts.batch_size
        # Blocks of whole batches: each block is one actor task, retried as a unit.
        per_block = bs * max(1, math.ceil(len(items) / (bs * MAX_BLOCKS)))
        idx = np.array([i for i, _ in items], dtype=np.int64)
        ids = pa.array([r for _, r in items], type=pa.string())
        table = pa.table({"i": idx, "id": ids})
        blocks = [table.slice(s, per_block) for s in range(0, len(items), per_block)]
        ds = ray.data.from_arrow(blocks)
        ds = ds.map_batches(
            _Describer, batch_size=bs, batch_format="numpy",
            compute=ray.data.ActorPoolStrategy(size=self.workers),
            num_cpus=self.opts.num_cpus_per_worker,
            num_gpus=self.opts.num_gpus_per_worker or None,
            fn_constructor_kwargs={"name": name, "config": self._worker_config(config),
                                   "state": dict(state),
                                   "identity": dict(identity), "source": self.source})
        for out in ds.iter_batches(batch_size=None, batch_format="numpy"):
            yield (np.asarray(out["i"], np.int64), np.asarray(out["ok"], bool),
                   np.asarray(out["desc"], np.float32), [str(r) for r in out["reason"]])

    def close(self) -> None:
        self.session.close()
