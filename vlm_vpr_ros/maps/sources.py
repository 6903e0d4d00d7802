"""Reader of precomputed descriptor sources (the shared contract of docs/planet_scale.md).

A source is
- one ``.npy`` file, ``(n, dim)`` float32, rows aligned with the coordinates CSV; or
- a folder of shards read in sorted file-name order: ``*.npy`` with an optional sidecar
  ``<stem>.ids.txt`` (UTF-8, one reference id per line = the CSV's ``file``), and/or
  ``*.parquet`` with columns ``id`` (string) and ``descriptor`` (list of float32); plus
  optionally ``describe.json`` (descriptor identity, fitted state file, skipped ids) and the
  state ``.npz`` it names.

Nothing is read into memory at open: ``.npy`` shards are memory-mapped after their header and
file size are checked (a truncated file is a :class:`DataError`, never a SIGBUS), Parquet shards
are streamed in batches.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from vlm_vpr_ros.config import choose
from vlm_vpr_ros.descriptors import available_descriptors, create_descriptor
from vlm_vpr_ros.descriptors.deep.specs import get_spec
from vlm_vpr_ros.errors import DataError, MapError
from vlm_vpr_ros.maps.format import check_descriptor_identity

log = logging.getLogger(__name__)

DESCRIBE = "describe.json"
DESCRIBE_FORMAT = "vlm_vpr_ros.descriptors"
CHUNK = 65536


def open_npy(path: Path) -> np.ndarray:
    """Memory-map a 2-D float ``.npy`` after checking that the file holds all its rows."""
    try:
        with open(path, "rb") as fh:
            major, _ = np.lib.format.read_magic(fh)
            read = (np.lib.format.read_array_header_1_0 if major == 1
                    else np.lib.format.read_array_header_2_0)
            shape, fortran, dtype = read(fh)
            offset = fh.tell()
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: not a readable .npy file ({exc})") from None
    if len(shape) != 2 or dtype.kind != "f" or fortran:
        raise DataError(f"{path}: expected a 2-D (n, dim) float32 C-order array, got "
                        f"{dtype}{shape}{' (Fortran order)' if fortran else ''}")
    need = offset + int(np.prod(shape)) * dtype.itemsize
    size = path.stat().st_size
    if size < need:
        raise DataError(f"{path}: truncated .npy ({size} bytes, its header needs {need} for "
                        f"{shape[0]} x {shape[1]} {dtype})")
    if shape[0] == 0:
        return np.zeros(shape, dtype)
    return np.load(path, mmap_mode="r", allow_pickle=False)


@dataclass
class Shard:
    path: Path
    n: int
    dim: int
    ids: list[str] | None
    array: np.ndarray | None = None  # memory-mapped .npy; None for Parquet

    def chunks(self, size: int = CHUNK) -> Iterator[tuple[int, np.ndarray]]:
        """(row offset within the shard, float32 rows)."""
        if self.array is not None:
            for s in range(0, self.n, size):
                yield s, np.asarray(self.array[s:s + size], dtype=np.float32)
            return
        pq = _pyarrow()
        start = 0
        for batch in pq.ParquetFile(self.path).iter_batches(batch_size=size,
                                                            columns=["descriptor"]):
            arr = _list_column(batch.column(0), self.dim, self.path)
            yield start, arr
            start += len(arr)


def _pyarrow():
    """pyarrow.parquet: an optional dependency (Parquet shards only), so it is imported by name
    and not declared in package.xml / requirements.txt."""
    import importlib

    try:
        pq = importlib.import_module("pyarrow.parquet")
    except ModuleNotFoundError:
        raise DataError("reading Parquet shards needs pyarrow (pip install pyarrow), or write "
                        ".npy shards") from None
    return pq


def _list_column(col: Any, dim: int, path: Path) -> np.ndarray:
    if hasattr(col, "combine_chunks"):  # pyarrow.ChunkedArray
        col = col.combine_chunks()
    if col.null_count:
        raise DataError(f"{path}: 'descriptor' has null rows")
    flat = np.asarray(col.flatten().to_numpy(zero_copy_only=False), dtype=np.float32)
    if len(col) and flat.size != len(col) * dim:
        raise DataError(f"{path}: descriptor rows are not all {dim}-D")
    return flat.reshape(len(col), dim)


def _parquet_shard(path: Path) -> Shard:
    pq = _pyarrow()
    try:
        pf = pq.ParquetFile(path)
    except Exception as exc:  # noqa: BLE001 - pyarrow raises several types for corrupt files
        raise DataError(f"{path}: not a readable Parquet file ({exc})") from None
    names = pf.schema_arrow.names
    if "id" not in names or "descriptor" not in names:
        raise DataError(f"{path}: Parquet shard needs columns 'id' and 'descriptor', has "
                        f"{names}")
    n = pf.metadata.num_rows
    ids = [str(x) for x in pf.read(columns=["id"]).column(0).to_pylist()]
    dim = 0
    if n:
        first = next(pf.iter_batches(batch_size=1, columns=["descriptor"])).column(0)
        dim = len(first[0].as_py())
    return Shard(path, n, dim, ids)


def _read_ids(path: Path, n: int) -> list[str]:
    try:
        ids = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: cannot read ids ({exc})") from None
    if len(ids) != n:
        raise DataError(f"{path}: {len(ids)} ids for {n} descriptor rows")
    return ids


@dataclass
class DescriptorSource:
    path: Path
    shards: list[Shard]
    dim: int
    describe: dict | None
    state: dict[str, np.ndarray]

    @property
    def n_rows(self) -> int:
        return sum(s.n for s in self.shards)

    @property
    def has_ids(self) -> bool:
        return bool(self.shards) and all(s.ids is not None for s in self.shards)

    @property
    def skipped(self) -> list:
        return list((self.describe or {}).get("skipped") or [])

    def single_array(self) -> np.ndarray | None:
        """The memory-mapped float32 array when the source is one aligned .npy (no copy)."""
        if len(self.shards) == 1 and self.shards[0].ids is None and \
                self.shards[0].array is not None and self.shards[0].array.dtype == np.float32:
            return self.shards[0].array
        return None

    def fingerprint(self) -> list:
        return [[str(s.path.name), s.path.stat().st_size, s.path.stat().st_mtime_ns]
                for s in self.shards] + [self.describe]


def open_source(path: str | Path) -> DescriptorSource:
    """Open a descriptor source (see the module docstring); DataError on any inconsistency."""
    path = Path(path)
    if path.is_file():
        if path.suffix != ".npy":
            raise DataError(f"{path}: a descriptor file must be .npy (or pass a folder of "
                            ".npy/.parquet shards)")
        arr = open_npy(path)
        return DescriptorSource(path, [Shard(path, arr.shape[0], arr.shape[1], None, arr)],
                                arr.shape[1], None, {})
    if not path.is_dir():
        raise DataError(f"descriptor source not found: {path}")
    files = sorted(p for p in path.iterdir() if p.suffix in (".npy", ".parquet")
                   and not p.name.startswith("."))
    shards = []
    for p in files:
        if p.suffix == ".npy":
            arr = open_npy(p)
            side = p.with_name(p.stem + ".ids.txt")
            ids = _read_ids(side, arr.shape[0]) if side.is_file() else None
            shards.append(Shard(p, arr.shape[0], arr.shape[1], ids, arr))
        else:
            shards.append(_parquet_shard(p))
    if not shards:
        raise DataError(f"{path}: no .npy or .parquet descriptor shards")
    dims = {s.dim for s in shards if s.n}
    if len(dims) > 1:
        raise DataError(f"{path}: shards have different dims {sorted(dims)}")
    with_ids = [s.ids is not None for s in shards]
    if any(with_ids) and not all(with_ids):
        missing = [s.path.name for s in shards if s.ids is None][:3]
        raise DataError(f"{path}: some shards carry ids and others do not (e.g. {missing}); "
                        "give every .npy shard a <stem>.ids.txt or none")
    describe, state = _describe(path)
    return DescriptorSource(path, shards, dims.pop() if dims else 0, describe, state)


def _describe(path: Path) -> tuple[dict | None, dict[str, np.ndarray]]:
    dp = path / DESCRIBE
    if not dp.is_file():
        return None, {}
    try:
        d = json.loads(dp.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataError(f"{dp}: unreadable ({exc})") from None
    if not isinstance(d, dict) or d.get("format") != DESCRIBE_FORMAT or d.get("version") != 1 \
            or not isinstance(d.get("descriptor"), dict):
        raise DataError(f"{dp}: expected {{\"format\": \"{DESCRIBE_FORMAT}\", \"version\": 1, "
                        "\"descriptor\": {...}}")
    state: dict[str, np.ndarray] = {}
    rel = d.get("descriptor_state")
    if rel:
        sp = path / str(rel)
        try:
            with np.load(sp, allow_pickle=False) as npz:
                state = {k: npz[k] for k in npz.files}
        except (OSError, ValueError) as exc:
            raise DataError(f"{sp}: cannot read the descriptor state ({exc})") from None
    return d, state


def descriptor_identity(name: str, source: DescriptorSource,
                        config: dict | None = None) -> tuple[dict, dict[str, np.ndarray]]:
    """Identity (for the manifest) and fitted state of registry descriptor ``name`` for these
    descriptors, without loading any model weights. Checks the name and dim against
    ``describe.json`` and the registry."""
    preset = choose(name, available_descriptors(), "descriptor")
    given = (source.describe or {}).get("descriptor")
    if given is not None and given.get("name") != name:
        raise MapError(f"{source.path}: descriptors were computed with {given.get('name')!r} "
                       f"(describe.json), not {name!r}")
    if preset.dim is None:  # fitted (codebook/PCA): the state defines the descriptor
        if not source.state:
            raise MapError(f"{name} is a fitted descriptor (codebook/PCA): {source.path} needs "
                           "describe.json with its descriptor_state .npz")
        desc = create_descriptor(name, {**((given or {}).get("config") or {}),
                                        **dict(config or {})})
        desc.load_state(source.state)
        ident = desc.identity()
        if given is not None:
            check_descriptor_identity(given, ident)
        state = source.state
    elif given is not None:
        ident, state = dict(given), {}
    else:
        ident, state = _deep_identity(name, dict(config or {})), {}
    dim = int(ident.get("dim") or 0)
    if preset.dim is not None and dim != preset.dim:
        raise DataError(f"{name} descriptors are {preset.dim}-D, describe.json says {dim}")
    if source.dim != dim:
        raise DataError(f"{source.path}: descriptors are {source.dim}-D, but {name} is "
                        f"{dim}-D")
    return ident, state


def _deep_identity(name: str, config: dict) -> dict:
    """The identity a deep descriptor would report, computed from its spec (no weights: the
    map records ``weights_sha256: null``, so any checkpoint of the release is accepted)."""
    from vlm_vpr_ros.descriptors.deep.torch_descriptor import DeepDescriptor, _check_resize

    spec = get_spec(name)
    d = DeepDescriptor.__new__(DeepDescriptor)
    d.spec, d.name, d.config = spec, spec.name, {}
    d.resize = _check_resize(spec, config.get("resize"))
    d.weights_sha256 = None
    return d.identity()


def read_aligned(source: DescriptorSource, ids: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """In-memory ``(feats (n, dim) float32, ok (n,) bool)`` aligned with ``ids`` (the CSV's
    ``file`` column): by id when the shards carry ids, else by order. Rows without a
    descriptor are zero and not ok. For small sources; mapping/build_descriptors.py streams large
    ones."""
    feats = np.zeros((len(ids), source.dim), np.float32)
    ok = np.zeros(len(ids), bool)
    if not source.has_ids:
        if source.n_rows != len(ids):
            raise DataError(f"{source.path}: {source.n_rows} descriptor rows but the "
                            f"coordinates CSV has {len(ids)} rows")
        pos = 0
        for shard in source.shards:
            for _, chunk in shard.chunks():
                feats[pos:pos + len(chunk)] = chunk
                pos += len(chunk)
        ok[:] = True
        return feats, ok
    where = {i: k for k, i in enumerate(ids)}
    for shard in source.shards:
        for off, chunk in shard.chunks():
            for ref, row in zip(shard.ids[off:off + len(chunk)], chunk):
                k = where.get(ref)
                if k is None:
                    raise DataError(f"{shard.path}: id {ref!r} is not in the coordinates CSV")
                if ok[k]:
                    raise DataError(f"{shard.path}: duplicate descriptor for id {ref!r}")
                feats[k], ok[k] = row, True
    return feats, ok
