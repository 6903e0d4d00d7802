"""Output safety: every folder the tools write is built next to its target and swapped in.

One module for the rules of ``build-map``, ``bag make``, ``evaluate-bag`` (and any later writer,
e.g. a v2 map build)::

    with StagedOutput(out, "map", overwrite) as stage:   # refuses unsafe targets up front
        build_into(stage.path)                          # stage.path: PARENT/.NAME.partial/NAME
        validate(stage.path)                            # e.g. ReferenceMap.load
        stage.commit()                                  # atomic swap; the old output goes last

* the old output stays untouched until the new one is complete and validated; if anything fails
  before :meth:`StagedOutput.commit`, the target is exactly as it was;
* ``overwrite`` only ever replaces a folder this tool wrote (a map manifest, a bag or an
  evaluation folder carrying :data:`MARKER`); anything else is refused with a message that does
  not suggest deleting it;
* :func:`check_not_inside` keeps outputs out of inputs (``evaluate-bag BAG --out BAG``), and
  :func:`check_file_output` is the same rule for every single-file output (``evaluate
  --geojson``, ``priors score --details``): never one of the inputs, never a user's file;
* the staging folder ``PARENT/.NAME.partial`` is fixed, so a resumable writer (the map build)
  finds its finished work there after a crash or a full disk;
* one writer at a time: :class:`~vlm_vpr_ros.files.lock.WriterLock` on ``PARENT/.NAME.lock``,
  the same lock that map edits (``map add/remove``) take, so a rebuild never swaps a map while
  an edit writes into it (and the other way round);
* write failures (disk full, permissions) become :class:`OutputError` with one clear line.
"""

from __future__ import annotations

import contextlib
import csv
import json
import logging
import os
import shutil
from pathlib import Path
from typing import Callable, Iterable

from vlm_vpr_ros import __version__
from vlm_vpr_ros.errors import OutputError
from vlm_vpr_ros.files.atomic import atomic_write_text, describe_os_error
from vlm_vpr_ros.files.lock import WriterLock, inside_lock

log = logging.getLogger(__name__)

#: marker file written into every bag / evaluation folder this tool creates
MARKER = ".vlm_vpr_output.json"
KINDS = ("map", "bag", "evaluation", "shards")


def _csv_header(path: Path) -> list[str]:
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            return next(csv.reader(fh), [])
    except (OSError, UnicodeDecodeError, csv.Error):
        return []


def check_file_output(out: str | os.PathLike[str], what: str,
                      inputs: Iterable[str | os.PathLike[str] | None] = (),
                      ours: Callable[[Path], bool] | None = None, kind: str = "a file") -> bool:
    """Before any work, the one check of every single-file output (a details CSV, a GeoJSON,
    an ablation's JSON): OutputError (one line, file untouched) when ``out`` is one of
    ``inputs`` (the same file by any path, links included), is a folder, or exists and is not
    ``kind`` this command wrote (``ours(path)`` False; None: no existing file is ours). An
    output of ours is replaced. Returns whether ``out`` exists."""
    p = Path(out)
    for inp in inputs:
        if inp is None:
            continue
        same = (_resolved(p) == _resolved(inp) or (
            os.path.lexists(p) and os.path.exists(inp) and os.path.exists(p)
            and os.path.samefile(p, inp)))
        if same:
            raise OutputError(f"{what} {out} is the input {inp}; choose another file")
    if p.is_dir():
        raise OutputError(f"{what} {out} is a folder; give a file name")
    if not os.path.lexists(p):
        return False
    if ours is None or not ours(p):
        raise OutputError(f"{what} {out} exists and is not {kind} this command wrote; it is "
                          "left untouched: choose another file")
    return True


def check_csv_output(out: str | os.PathLike[str], columns: list[str], what: str,
                     inputs: Iterable[str | os.PathLike[str] | None] = ()) -> None:
    """:func:`check_file_output` of a CSV with ``columns`` (one written before is ours)."""
    check_file_output(out, what, inputs, lambda p: _csv_header(p) == list(columns), "a CSV")


def written_by_us(path: Path, kind: str) -> bool:
    """Whether folder ``path`` is a ``kind`` output this tool wrote (safe to replace)."""
    marker = path / MARKER
    if marker.is_file():
        try:
            return json.loads(marker.read_text(encoding="utf-8")).get("kind") == kind
        except (OSError, ValueError, AttributeError):
            return False
    if kind == "map":
        try:
            manifest = json.loads((path / "manifest.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return False
        return isinstance(manifest, dict) and str(manifest.get("format", "")).startswith(
            "vlm_vpr_ros.map")
    if kind == "bag":  # bags made before the marker existed: metadata.yaml + our frames.csv
        return ((path / "metadata.yaml").is_file()
                and _csv_header(path / "frames.csv")[:3] == ["index", "stamp_ns", "file"])
    if kind == "evaluation":  # before the marker: frames.csv without / with stamp_ns
        return ((path / "summary.json").is_file()
                and _csv_header(path / "frames.csv")[:3] in (["index", "stamp", "key"],
                                                             ["index", "stamp", "stamp_ns"]))
    if kind == "shards":  # written by `vlm-vpr describe` before the marker existed
        return _shards_meta(path / "describe.json") or (path / ".progress" / "job.json").is_file()
    return False


def _shards_meta(path: Path) -> bool:
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and meta.get("format") == "vlm_vpr_ros.descriptors"


def write_marker(folder: Path, kind: str) -> None:
    # through a new file moved into place: a symbolic link at the name is replaced, never
    # followed (the folder may be a resumed one that was not created by this process)
    atomic_write_text(folder / MARKER, json.dumps({"kind": kind, "tool": "vlm_vpr_ros",
                                                   "version": __version__}) + "\n")


_WHAT = {"map": "a map (no vlm_vpr_ros manifest.json)",
         "bag": "a bag written by 'vlm-vpr bag make'",
         "evaluation": "an evaluation folder written by 'vlm-vpr evaluate-bag'",
         "shards": "a descriptor shard folder written by 'vlm-vpr describe'"}


_WRITER = {"map": "a map build", "bag": "bag make", "evaluation": "evaluate-bag",
           "shards": "describe"}
_NOUN = {"map": "a map", "bag": "a bag", "evaluation": "an evaluation",
         "shards": "descriptor shards of another job (other images or settings)"}


def check_target(target: Path, kind: str, overwrite: bool) -> bool:
    """Raise OutputError unless ``target`` may be written; True when it holds an old output."""
    if kind not in KINDS:
        raise ValueError(f"unknown output kind {kind!r}")
    if not target.exists() and not target.is_symlink():
        return False
    if not target.is_dir():
        raise OutputError(f"{target} exists and is not a folder; choose another --out")
    if not any(target.iterdir()):
        return False
    if not written_by_us(target, kind):
        raise OutputError(f"{target} exists and is not {_WHAT[kind]}; it is left untouched: "
                          "choose another --out")
    if not overwrite:
        raise OutputError(f"{target} already holds {_NOUN[kind]}; pass --overwrite to replace "
                          "it (the old one stays until the new one is complete)")
    return True


def _resolved(p: str | os.PathLike[str]) -> Path:
    return Path(os.path.abspath(os.path.realpath(p)))


def check_not_inside(out: str | os.PathLike[str],
                     inputs: Iterable[str | os.PathLike[str] | None], what: str = "--out",
                     allow_out_inside: bool = False) -> None:
    """Raise OutputError when ``out`` is or contains one of ``inputs`` (or lies inside one,
    unless ``allow_out_inside``)."""
    o = _resolved(out)
    for inp in inputs:
        if inp is None:
            continue
        i = _resolved(inp)
        if o == i or o in i.parents or (i in o.parents and not allow_out_inside):
            rel = "is" if o == i else ("is inside" if i in o.parents else "contains")
            raise OutputError(f"{what} {out} {rel} the input {inp}; outputs are never written "
                              "into inputs: choose another folder")


class StagedOutput:
    """Build an output folder next to its target, then swap it in atomically."""

    def __init__(self, target: str | os.PathLike[str], kind: str, overwrite: bool = False,
                 resumable: bool = False, marker: bool = False,
                 adopt: Callable[[Path], bool] | None = None) -> None:
        """``adopt(target)``: True when the target holds this writer's own unfinished work
        (written in place by an older version): it is then moved into the staging folder and
        resumed there (resumable writers only)."""
        self.target = Path(target)
        self.adopt = adopt
        self.kind, self.overwrite, self.resumable, self.marker = kind, overwrite, resumable, marker
        name = self.target.name
        if not name or name in (".", ".."):
            raise OutputError(f"{target}: not a usable output folder name")
        self.root = self.target.parent / f".{name}.partial"
        self.path = self.root / name  # the new output is built here
        # resumable scratch (kept after failures); never the output's own folder
        self.work = self.root / ("work" if name != "work" else ".work")
        self._lock = WriterLock(self.target, _WRITER[kind])
        self.committed = False

    # -- context manager -----
    def __enter__(self) -> "StagedOutput":
        self._lock.acquire()
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            old = self.root / ".old"
            if self._restore_old():  # a swap cut short by a crash
                log.warning("restored %s from an interrupted swap", self.target)
            elif old.exists() or old.is_symlink():  # the swap finished; its cleanup did not
                stale = self.root / f".old-stale{os.getpid()}"
                os.replace(old, stale)
                shutil.rmtree(stale)
            if (self.adopt is not None and self.resumable and self.target.is_dir()
                    and not self.path.exists() and self.adopt(self.target)):
                os.replace(self.target, self.path)
                log.info("resuming the unfinished %s in %s", self.kind, self.target)
        except OSError as exc:
            self._unlock()
            raise OutputError(describe_os_error(exc)) from None
        try:
            self.had_old = check_target(self.target, self.kind, self.overwrite)
        except OutputError:
            self._unlock()
            if not any(self.root.iterdir()):
                shutil.rmtree(self.root, ignore_errors=True)
            raise
        try:
            if self.path.exists() and not self.resumable:
                shutil.rmtree(self.path)
            self.path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            self._unlock()
            raise OutputError(describe_os_error(exc)) from None
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if not self.committed:
                self._clean_after_failure(exc_type)
        finally:
            self._unlock()

    def _restore_old(self) -> bool:
        """Put the old output back when a swap stopped between its two renames."""
        old = self.root / ".old"
        if old.is_dir() and not self.target.exists() and not self.target.is_symlink():
            os.replace(old, self.target)
            return True
        return False

    def _clean_after_failure(self, exc_type) -> None:
        """Keep resumable work (the next run continues it); drop everything else. The old
        output is put back first when the failure (Ctrl-C included) cut the swap short."""
        try:
            self._restore_old()
        except OSError as exc:  # keep everything: the next run restores it
            log.error("%s could not be put back from %s (%s); run the same command again",
                      self.target, self.root / ".old", exc)
            return
        if self.resumable and exc_type is not None:
            remove_temp_files(self.root)
            if not any(p.is_file() for p in self.root.rglob("*")):
                shutil.rmtree(self.root, ignore_errors=True)  # nothing done yet
                return
            log.info("partial output kept in %s; run the same command again to resume",
                     self.root)
            return
        shutil.rmtree(self.root, ignore_errors=True)

    def _unlock(self) -> None:
        self._lock.release()

    # -- the swap -----
    def commit(self, validate: Callable[[Path], object] | None = None) -> Path:
        """Validate the staged output, then move it into place (old output removed last)."""
        if validate is not None:
            validate(self.path)
        try:
            if self.marker:
                write_marker(self.path, self.kind)
            if self.target.is_dir() and any(self.target.iterdir()):
                # re-check: something may have appeared at the target while we were building
                check_target(self.target, self.kind, self.overwrite)
                # an edit by a user who could not lock beside the map holds the one inside
                with (inside_lock(self.target, _WRITER[self.kind]) if self.kind == "map"
                      else contextlib.nullcontext()):
                    try:
                        os.replace(self.target, self.root / ".old")
                        os.replace(self.path, self.target)
                    except BaseException:  # Ctrl-C too: never leave the target missing
                        self._restore_old()
                        raise
            else:
                if self.target.is_dir():
                    self.target.rmdir()
                os.replace(self.path, self.target)
        except OSError as exc:
            raise OutputError(describe_os_error(exc, self.target)) from None
        self.committed = True
        shutil.rmtree(self.root, ignore_errors=True)  # still locked: no writer is staging
        self._unlock()
        return self.target


def remove_temp_files(folder: Path) -> int:
    """Delete leftover ``.NAME.tmpPID`` files of interrupted atomic writes under ``folder``."""
    n = 0
    for p in folder.rglob(".*.tmp*"):
        try:
            if p.is_file():
                p.unlink()
                n += 1
        except OSError:
            pass
    return n
