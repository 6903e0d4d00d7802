"""``vlm-vpr localize`` (registered with the core sub-commands in :mod:`vlm_vpr_ros.cli.core`).

Every input and option is checked before any expensive work (the map, the descriptor model):
the prior provider is created first (a bad priors CSV or ``--prior-option`` is exit 2 at once),
``--out`` and ``--save-matches`` are checked against every input of the command
(:mod:`vlm_vpr_ros.files.outputs`). Heavy modules (the pipeline, cv2) are imported when used,
so ``vlm-vpr --help`` and the early refusals stay fast.
"""

from __future__ import annotations

import argparse
import logging
import os
from pathlib import Path
from typing import Sequence

from vlm_vpr_ros.cli.common import (descriptor_options, localizer_config, make_prior_provider,
                                    prior_inputs, status_policy, verification_config)
from vlm_vpr_ros.config import parse_kv
from vlm_vpr_ros.errors import ConfigError, DataError, MapError, OutputError
from vlm_vpr_ros.files.outputs import check_file_output, check_not_inside

log = logging.getLogger(__name__)


def localize_inputs(args: argparse.Namespace) -> list[str]:
    """Every path a ``localize`` run reads (files and folders): no output may be one of them."""
    paths = [args.queries, args.ground_truth, args.query_descriptors, args.images,
             args.reference_images, args.map, args.weights, *prior_inputs(args)]
    for opts in (args.feature_option, args.matcher_option):
        paths += [v for k, v in parse_kv(opts).items() if k == "weights" and isinstance(v, str)]
    return [str(p) for p in paths if p]


def localize_start(out: Path, resume: bool, overwrite: bool,
                   inputs: Sequence[str] = ()) -> list[dict]:
    """Check ``--out`` (and its ``.partial`` file) and return the rows kept from an earlier run
    (``--resume``). Never one of ``inputs`` (a results CSV given as the queries is still an
    input), never a file that is not a results CSV of ours."""
    from vlm_vpr_ros.localization.batch import is_results_csv, read_done_rows

    partial = out.with_name(out.name + ".partial")
    check_file_output(out, "--out", inputs, is_results_csv,
                      "a results CSV of 'vlm-vpr localize'")
    # the unfinished rows of an earlier run (our own name): never an input, else as before
    check_file_output(partial, "--out's unfinished file", inputs, Path.is_file,
                      "a results CSV of 'vlm-vpr localize'")
    if resume:
        source = partial if partial.is_file() else out if out.is_file() else None
        rows = read_done_rows(source) if source is not None else []
        if source is not None:
            log.info("resuming from %s: %d finished rows kept", source, len(rows))
        return rows
    if out.exists() and not overwrite:
        raise OutputError(f"{out} already exists; pass --resume to continue it or --overwrite "
                          "to replace it (the old file stays until the new one is complete)")
    if partial.is_file() and not overwrite:
        raise OutputError(f"an interrupted run left {partial}; pass --resume to continue it or "
                          "--overwrite to start over")
    return []


def cmd_localize(args: argparse.Namespace) -> int:
    from vlm_vpr_ros.files.csvio import read_file_column

    # -- every check before any expensive work (the map, the model) ----------------------------
    if args.query_descriptors and args.resume:  # one pass, written whole at the end
        raise DataError("--resume is for --images runs (streamed rows); a --query-descriptors "
                        "run writes its results at the end: run it again with --overwrite")
    files = read_file_column(args.queries)
    if not args.images and not args.query_descriptors:
        raise DataError("localize needs --images DIR (or --query-descriptors Q.npy)")
    if args.only_wrong and not args.save_matches:
        raise ConfigError("--only-wrong goes with --save-matches DIR")
    if args.only_wrong and not args.ground_truth:
        raise ConfigError("--only-wrong needs --ground-truth (which answers are wrong)")
    out = Path(args.out)
    inputs = localize_inputs(args)
    done = localize_start(out, args.resume, args.overwrite, inputs)
    finished = {r["file"] for r in done}
    todo = [f for f in files if f not in finished]
    check_save_matches(args, todo, inputs + [str(out)])
    gt = None
    if args.ground_truth and args.save_matches:
        from vlm_vpr_ros.evaluation.metrics import read_ground_truth

        gt = read_ground_truth(args.ground_truth)
    settings = {"localizer": localizer_config(args), "verification": verification_config(args),
                "status": status_policy(args), "descriptor_config": descriptor_options(args)}
    provider = make_prior_provider(args)  # a bad priors CSV or option: exit 2 here
    try:
        if args.query_descriptors:
            return _localize_descriptors(args, files, provider, settings)
        return _localize_images(args, files, done, todo, provider, settings, gt)
    finally:
        provider.close()


def _localize_images(args: argparse.Namespace, files: list[str], done: list[dict],
                     todo: list[str], provider, settings: dict, gt) -> int:
    from tqdm import tqdm

    from vlm_vpr_ros.localization.batch import ResultsStream, localize_files
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline

    pipe = LocalizationPipeline.open(args.map, descriptor=args.descriptor, **settings)
    pipe.map.open_submaps()  # a damaged map: exit 2 before the first query
    on_result = None
    if args.save_matches:
        from vlm_vpr_ros.evaluation.matches import MatchWriter

        on_result = MatchWriter(args.save_matches, pipe, gt, args.only_wrong)
    stream = ResultsStream(Path(args.out), [r for r in done if r["file"] in set(files)])
    try:
        for row in tqdm(localize_files(pipe, provider, args.images, todo, args.prior_timeout,
                                       on_result=on_result),
                        total=len(todo), desc="localize", unit="img", disable=None):
            stream.write(row)
    except OSError as exc:  # disk full / permissions while streaming
        from vlm_vpr_ros.files.atomic import describe_os_error

        raise OutputError(f"{describe_os_error(exc, stream.partial)}; {len(stream.rows)} "
                          f"rows kept there: continue with --resume") from None
    except KeyboardInterrupt:
        stream.close()
        log.warning("%d of %d rows kept in %s; run the same command with --resume to continue",
                    len(stream.rows), len(files), stream.partial)
        raise
    finally:
        stream.close()
    stream.finish(files)
    flagged = sum(1 for r in stream.rows if r.get("flags"))
    resumed = f", {len(stream.rows) - len(todo)} kept from the earlier run" if done else ""
    print(f"{len(stream.rows)} queries localized -> {args.out} ({flagged} with flags{resumed})")
    return 0


def _matches_only(d: Path) -> bool:
    """Whether folder ``d`` holds nothing but pictures as ``--save-matches`` writes them
    (plain ``.jpg`` files): the only folder whose pictures ``--overwrite`` may replace."""
    return all(p.suffix == ".jpg" and p.is_file() and not p.is_symlink() for p in d.iterdir())


def check_save_matches(args: argparse.Namespace, todo: list[str], inputs: list[str]) -> None:
    """``--save-matches DIR`` checked before any work: a folder (or a new name); not, not
    inside and not holding the map, the query images or the reference images; none of its
    pictures one of ``inputs``; holding none of the pictures this run would write unless
    ``--overwrite``, and then only in a folder of match pictures (never a user's folder)."""
    if not args.save_matches:
        return
    from vlm_vpr_ros.evaluation.matches import sheet_names

    d = Path(args.save_matches)
    if (d.exists() or d.is_symlink()) and not d.is_dir():
        raise OutputError(f"--save-matches {d} exists and is not a folder; it is left "
                          "untouched: choose a folder")
    check_not_inside(d, [args.map, args.images or None, args.reference_images or None],
                     what="--save-matches")
    if not d.is_dir():
        return
    names = sheet_names(todo).values()
    for inp in inputs:  # e.g. a queries CSV named like a picture, in that folder
        if os.path.realpath(os.path.dirname(os.path.abspath(inp))) == os.path.realpath(d) \
                and os.path.basename(inp) in names:
            raise OutputError(f"--save-matches {d} would write over the input {inp}; choose "
                              "another folder")
    clash = [n for n in names if os.path.lexists(d / n)]
    if clash and not args.overwrite:
        raise OutputError(f"--save-matches {d} already holds {len(clash)} of the pictures "
                          f"this run writes (e.g. {clash[0]}); pass --overwrite to replace "
                          "them or choose another folder")
    if clash and not _matches_only(d):
        raise OutputError(f"--save-matches {d} holds {clash[0]} and files that are not match "
                          "pictures; it is left untouched: --overwrite replaces pictures only "
                          "in a folder of match pictures, choose another folder")


def _localize_descriptors(args: argparse.Namespace, files: list[str], provider,
                          settings: dict) -> int:
    from tqdm import tqdm

    from vlm_vpr_ros.files.csvio import write_csv_atomic
    from vlm_vpr_ros.localization.batch import RESULT_FIELDS
    from vlm_vpr_ros.localization.localizer import Localizer
    from vlm_vpr_ros.localization.query_descriptors import (localize_descriptors,
                                                            open_query_descriptors)
    from vlm_vpr_ros.localization.verification.stage import Verifier
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    ref_map = ReferenceMap.load(args.map)
    if args.descriptor and args.descriptor != ref_map.descriptor_identity["name"]:
        raise MapError(f"the map at {args.map} was built with descriptor "
                       f"{ref_map.descriptor_identity['name']!r}, but {args.descriptor!r} was "
                       "requested")
    descs = open_query_descriptors(args.query_descriptors, len(files), ref_map.dim)
    ref_map.open_submaps()  # after the cheap checks of the query descriptors
    localizer = Localizer(ref_map, settings["localizer"])
    verifier = Verifier(ref_map, settings["verification"]) if args.images else None
    rows = list(tqdm(localize_descriptors(localizer, provider, files, descs, args.images,
                                          args.prior_timeout, verifier=verifier,
                                          policy=settings["status"]),
                     total=len(files), desc="localize", unit="query", disable=None))
    write_csv_atomic(args.out, RESULT_FIELDS, rows)
    # an interrupted --images run's rows (--overwrite was given): superseded now
    Path(args.out).with_name(Path(args.out).name + ".partial").unlink(missing_ok=True)
    flagged = sum(1 for r in rows if r.get("flags"))
    print(f"{len(rows)} queries localized -> {args.out} ({flagged} with flags)")
    return 0
