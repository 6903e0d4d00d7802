"""``vlm-vpr describe``: reference images → descriptor shards, with the local or the Ray engine.

The job is the same for both engines (only *where* images are described differs):

1. the images folder/URI and the CSV's ids are checked; the shard folder is written like every
   output of this tool (:class:`~vlm_vpr_ros.files.outputs.StagedOutput`): under the folder's
   writer lock, into ``PARENT/.NAME.partial/NAME`` (resumed when it holds the same job, see
   :mod:`~vlm_vpr_ros.distributed.shards`) and swapped in when complete. ``--overwrite``
   replaces only a shard folder this tool wrote, never a user's folder or an input (``--out``
   may not be, contain or lie inside the images folder); a finished folder of the same job is
   "up to date";
2. a stateful descriptor (``vlad_rootsift``) is fitted ONCE on the same sample as the local
   ``build-map`` (:func:`vlm_vpr_ros.mapping.build_images.fit_sample_indices`) and its state is
   saved, then sent to every worker;
3. the images of unfinished shards are described in batches; a shard is written as soon as all
   its rows are back, so a killed run loses at most the shards in flight;
4. ``describe.json`` is written last.

Unreadable images, and images on which the descriptor raises, are skipped and listed with the
reason (in the shard records and ``describe.json``), never the whole job.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from vlm_vpr_ros.descriptors import GlobalDescriptor, create_descriptor
from vlm_vpr_ros.distributed import ENGINES
from vlm_vpr_ros.distributed.ray_engine import RaySession
from vlm_vpr_ros.distributed.shards import (DEFAULT_SHARD_SIZE, ShardStore, finished_job,
                                            job_fingerprint, plan_shards, unfinished_job)
from vlm_vpr_ros.distributed.engines import Engine, LocalEngine
from vlm_vpr_ros.files.outputs import StagedOutput, check_not_inside
from vlm_vpr_ros.mapping.build_images import fit_sample_indices
from vlm_vpr_ros.mapping.image_sources import ImageSource, is_uri
from vlm_vpr_ros.errors import ConfigError, DescriptorError

log = logging.getLogger(__name__)

#: seconds between progress log lines when there is no terminal for the bar
LOG_EVERY_S = 30.0


@dataclass
class DescribeOptions:
    """How to run a describe job (the CLI's engine options)."""

    engine: str = "local"
    #: None: start a Ray on this machine; "auto", "HOST:PORT" or "ray://HOST:PORT": join one
    ray_address: str | None = None
    #: actors (Ray) describing in parallel; None: one per CPU (or per GPU share) of the cluster
    workers: int | None = None
    #: images per batch handed to a worker (and per forward pass of a deep model on GPU)
    batch_size: int = 16
    num_gpus_per_worker: float = 0.0
    num_cpus_per_worker: float = 1.0
    shard_size: int = DEFAULT_SHARD_SIZE
    #: where a stateful descriptor is fitted: "driver" (this process, bit-identical to the
    #: local build) or "cluster" (one Ray task, when the driver cannot read the images)
    fit_on: str = "driver"
    progress: bool = True
    #: extra ``ray.init`` arguments for a Ray started here (e.g. object_store_memory)
    ray_init: dict[str, Any] = field(default_factory=dict)

    def validate(self) -> None:
        if self.engine not in ENGINES:
            raise ConfigError(f"unknown engine {self.engine!r}; choices: {', '.join(ENGINES)}")
        if self.workers is not None and self.workers < 1:
            raise ConfigError(f"--workers must be >= 1, got {self.workers}")
        if not 1 <= self.batch_size <= 4096:
            raise ConfigError(f"--batch-size must be 1..4096, got {self.batch_size}")
        if self.num_gpus_per_worker < 0 or self.num_cpus_per_worker <= 0:
            raise ConfigError("--num-gpus-per-worker must be >= 0 and CPUs per worker > 0")
        if self.fit_on not in ("driver", "cluster"):
            raise ConfigError(f"--fit-on must be driver or cluster, got {self.fit_on!r}")
        if self.shard_size < 1:
            raise ConfigError(f"--shard-size must be >= 1, got {self.shard_size}")
        if self.engine == "local" and (self.ray_address or self.num_gpus_per_worker):
            raise ConfigError("--ray-address and --num-gpus-per-worker need --engine ray")


@dataclass
class DescribeResult:
    folder: Path
    rows: int
    described: int
    skipped: list[dict]
    resumed_shards: int
    computed_images: int
    seconds: float
    workers: int
    engine: str
    identity: dict
    #: seconds of the describe phase alone (no start-up, no fit)
    describe_seconds: float = 0.0

    @property
    def images_per_s(self) -> float:
        return self.computed_images / self.seconds if self.seconds > 0 else 0.0

    @property
    def describe_images_per_s(self) -> float:
        t = self.describe_seconds
        return self.computed_images / t if t > 0 else 0.0

    def summary(self) -> str:
        return (f"described {self.described}/{self.rows} images -> {self.folder} "
                f"({len(self.skipped)} skipped, {self.resumed_shards} shards resumed): "
                f"{self.computed_images} images in {self.seconds:.1f} s = "
                f"{self.images_per_s:.2f} img/s with {self.workers} {self.engine} worker(s)")


# -- the job --------------------------------------------------------------------------------------
def describe_to_shards(images: str | Path, ids: Sequence[str], out: str | Path,
                       descriptor: str | GlobalDescriptor = "vlad_rootsift",
                       descriptor_config: Mapping[str, Any] | None = None,
                       options: DescribeOptions | None = None, overwrite: bool = False,
                       engine: Engine | None = None, staged: bool = True,
                       inputs: Sequence[str | Path] = ()) -> DescribeResult:
    """Describe ``images/<id>`` for every id into the shard folder ``out`` (resumable).

    ``descriptor`` may be an already created descriptor (it is fitted in place when it needs
    it). ``engine``: an open engine (``build-map --engine ray`` passes its Ray session);
    by default one is made from ``options``. ``staged=False`` writes into ``out`` directly
    (a build's own scratch folder, already under the map's lock). ``inputs``: other input
    files (the coordinates CSV) that ``out`` must not be, contain or lie inside.
    """
    opts = options or DescribeOptions()
    opts.validate()
    t_start = time.monotonic()
    desc = descriptor if isinstance(descriptor, GlobalDescriptor) \
        else create_descriptor(descriptor, descriptor_config)
    source = ImageSource(images)
    source.check()
    ids = list(ids)
    if not ids:
        raise ConfigError("no reference ids to describe")
    fingerprint = job_fingerprint(ids, desc.identity(), opts.shard_size)
    if not staged:
        res = _describe_into(Path(out), source, ids, desc, opts, fingerprint, overwrite,
                             engine, t_start)
        log.info("%s", res.summary())
        return res
    local = _local_path(str(images)) if is_uri(images) else Path(images)
    check_not_inside(out, [local, *inputs])
    done = finished_job(Path(out), fingerprint)
    if done is not None:
        log.info("descriptor shards %s are up to date", out)
        return DescribeResult(Path(out), len(ids), done["described"], done["skipped"],
                              int(done.get("shards", 0)), 0, time.monotonic() - t_start, 0,
                              opts.engine, dict(done["descriptor"]))
    with StagedOutput(out, "shards", overwrite, resumable=True, marker=True,
                      adopt=lambda p: unfinished_job(p, fingerprint)) as stage:
        # the staging folder is this tool's own: other work found there is replaced
        res = _describe_into(stage.path, source, ids, desc, opts, fingerprint, True, engine,
                             t_start)
        stage.commit()
    res.folder = Path(out)
    log.info("%s", res.summary())
    return res


def _describe_into(folder: Path, source: ImageSource, ids: list[str], desc: GlobalDescriptor,
                   opts: DescribeOptions, fingerprint: str, overwrite: bool,
                   engine: Engine | None, t_start: float) -> DescribeResult:
    """The job proper, in a folder that is this job's own (resumed when it holds it)."""
    own_engine = engine is None
    if engine is None:  # first: a cluster that cannot be reached leaves nothing behind
        engine = make_engine(opts, desc, source)
    try:
        store = ShardStore(folder)
        store.open(fingerprint, len(ids), opts.shard_size, overwrite)
        state: dict[str, np.ndarray] = {}
        if desc.needs_fit:
            saved = store.load_state()
            if saved is None:
                sample = [ids[i] for i in fit_sample_indices(len(ids), desc)]
                log.info("fitting %s on %d sample images", desc.name, len(sample))
                saved = engine.fit(desc.name, desc.config, sample)
                store.save_state(saved)
            else:
                log.info("resumed the fitted %s state", desc.name)
            desc.load_state(saved)
            state = desc.state_arrays()
        identity = desc.identity()
        plan = plan_shards(len(ids), opts.shard_size)
        done = store.done()
        pending = [(s, e) for s, e in plan if s not in done]
        computed, t_describe = _run(engine, store, ids, pending, desc, state, identity, opts,
                        n_done=sum(e - s for s, e in plan if s in done))
        meta = store.finish(identity, desc.needs_fit, len(ids))
    finally:
        if own_engine:
            engine.close()
    return DescribeResult(folder, len(ids), meta["described"], meta["skipped"],
                          len(plan) - len(pending), computed, time.monotonic() - t_start,
                          engine.workers, opts.engine, identity, t_describe)


def _run(engine: Engine, store: ShardStore, ids: Sequence[str],
         pending: list[tuple[int, int]], desc: GlobalDescriptor, state, identity,
         opts: DescribeOptions, n_done: int) -> tuple[int, float]:
    """Describe the rows of the pending shards; write each shard when its rows are all back."""
    if not pending:
        return 0, 0.0
    size, dim = opts.shard_size, desc.dim
    items = [(i, ids[i]) for s, e in pending for i in range(s, e)]
    buf: dict[int, dict] = {s: {"end": e, "feats": np.zeros((e - s, dim), np.float32),
                                "ok": np.zeros(e - s, bool), "seen": np.zeros(e - s, bool),
                                "reasons": [""] * (e - s), "left": e - s} for s, e in pending}
    bar = _bar(len(ids), n_done, opts.progress)
    t0, computed = time.monotonic(), 0
    last_log, todo = t0, len(items)
    try:
        for idx, ok, feats, reasons in engine.map(items, desc.name, desc.config, state, identity):
            for i, good, f, why in zip(idx.tolist(), ok, feats, reasons):
                s = (i // size) * size
                b = buf.get(s)
                if b is None or b["seen"][i - s]:
                    continue  # a retried batch answered twice: the first answer is kept
                b["feats"][i - s], b["ok"][i - s], b["reasons"][i - s] = f, good, why
                b["seen"][i - s] = True
                b["left"] -= 1
                if b["left"] == 0:
                    _write(store, ids, s, b)
                    del buf[s]
            computed += len(idx)
            if bar is not None:
                bar.update(len(idx))
            now = time.monotonic()
            if opts.progress and (bar is None or bar.disable) and now - last_log >= LOG_EVERY_S:
                # no terminal (a cluster job's log): a line with the same figures as the bar
                rate = computed / (now - t0)
                log.info("describe: %d/%d images, %.2f img/s, ETA %s", n_done + computed,
                         len(ids), rate, _hms((todo - computed) / max(rate, 1e-9)))
                last_log = now
    finally:
        if bar is not None:
            bar.close()
    missing = sum(b["left"] for b in buf.values())
    if missing:
        raise DescriptorError(f"{missing} images were not returned by the {opts.engine} engine;"
                              " re-run to describe them (finished shards are kept)")
    dt = time.monotonic() - t0
    log.info("described %d images in %.1f s (%.2f img/s)", computed, dt, computed / max(dt, 1e-9))
    return computed, dt


def _write(store: ShardStore, ids: Sequence[str], s: int, b: dict) -> None:
    keep = np.flatnonzero(b["ok"])
    skipped = [{"id": ids[s + k], "reason": b["reasons"][k]}
               for k in range(len(b["ok"])) if not b["ok"][k]]
    store.write(s, b["end"], [ids[s + k] for k in keep], b["feats"][keep], skipped)


def _local_path(uri: str) -> Path | None:
    """The folder of a ``file://`` URI (remote sources are no local input: None)."""
    import urllib.parse

    u = urllib.parse.urlparse(uri)
    return Path(urllib.parse.unquote(u.path)) if u.scheme == "file" else None


def _hms(seconds: float) -> str:
    s = int(seconds)
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


def _bar(total: int, initial: int, enabled: bool):
    if not enabled:
        return None
    from tqdm import tqdm

    # images/s and ETA of this run (``initial`` = rows of resumed shards)
    return tqdm(total=total, initial=initial, desc="describe", unit="img", smoothing=0.1,
                disable=None, dynamic_ncols=True)


def make_engine(opts: DescribeOptions, desc: GlobalDescriptor, source: ImageSource) -> Any:
    if opts.engine == "local":
        return LocalEngine(desc, source, opts.batch_size)

    session = RaySession(opts)
    try:
        session.start()
        return session.describer(source)
    except BaseException:
        session.close()
        raise
