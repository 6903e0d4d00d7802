"""``vlm-vpr``: the command-line entry point. Each sub-command lives in its own module that
exposes ``register(subparsers)``; modules listed in ``_COMMAND_MODULES`` are loaded in order."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from vlm_vpr_ros import redact
from vlm_vpr_ros.errors import VlmVprError

log = logging.getLogger("vlm_vpr_ros")

_COMMAND_MODULES = (
    "vlm_vpr_ros.cli.core",      # build-map, localize, evaluate, descriptors, demo
    "vlm_vpr_ros.cli.weights",   # weights fetch / list (deep VPR models)
    "vlm_vpr_ros.cli.priors",    # priors score / ask (VLM)
    "vlm_vpr_ros.cli.bag",       # bag make, replay, evaluate-bag, ablate
    "vlm_vpr_ros.cli.map",       # map add / remove / info / verify / upgrade
    "vlm_vpr_ros.cli.distributed",  # describe (descriptor shards; local or Ray engine)
    "vlm_vpr_ros.cli.calibrate",  # calibrate (uncertainty radii on labelled queries)
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="vlm-vpr",
        description="VLM-guided visual place recognition: build geotagged maps, localize "
                    "images, score VLM priors and evaluate bags. Run 'vlm-vpr demo' first.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more log output (-vv for debug)")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for mod_name in _COMMAND_MODULES:
        try:
            mod = importlib.import_module(mod_name)
        except ModuleNotFoundError as exc:
            if exc.name != mod_name:
                raise
            continue
        mod.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # The CLI (not the library) configures logging; logs go to stderr so --json stays clean.
    # Default: our INFO messages, other libraries' warnings; -v: everything at INFO; -vv: DEBUG.
    root_level = {0: logging.WARNING, 1: logging.INFO}.get(args.verbose, logging.DEBUG)
    # Every record goes through the one redaction point (vlm_vpr_ros.redact): no key in a log.
    handler = logging.StreamHandler(sys.stderr)
    redact.install(handler, "%(levelname)s %(name)s: %(message)s")
    logging.basicConfig(level=root_level, handlers=[handler])
    logging.getLogger("vlm_vpr_ros").setLevel(
        logging.WARNING if args.quiet else min(root_level, logging.INFO))
    try:
        from vlm_vpr_ros.cli.validate import check_args

        check_args(args)  # every numeric option finite and in range, before any work
        rc = args.func(args)
    except VlmVprError as exc:
        log.error("%s", one_line(exc))
        return 2
    except KeyboardInterrupt:
        log.warning("interrupted")
        return 130
    except OSError as exc:  # disk full, permissions, a vanished file: one line, no traceback
        from vlm_vpr_ros.files.atomic import describe_os_error

        log.error("%s", describe_os_error(exc) if exc.filename else one_line(exc))
        log.debug("details", exc_info=True)
        return 2
    except Exception as exc:  # noqa: BLE001 - a bug: one line here, the traceback with -vv
        log.error("internal error %s: %s (please report it; -vv shows the traceback)",
                  type(exc).__name__, one_line(exc))
        log.debug("traceback", exc_info=True)
        return 1
    return int(rc or 0)


def one_line(exc: BaseException) -> str:
    """An exception's message on one line (newlines in paths or keys never split it)."""
    return " ".join(str(exc).split()) or type(exc).__name__


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
