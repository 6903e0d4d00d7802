"""Issue 43, the command line: every `--help` prints what its author wrote (no argparse
escape left over), `evaluate` of an empty results CSV says so, and `evaluate --geojson` never
writes over an input or a file of the user's."""

from __future__ import annotations

import argparse
import json

import pytest

from vlm_vpr_ros.cli import build_parser, main


def _parsers(parser: argparse.ArgumentParser, path: list[str]):
    yield " ".join(path), parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _parsers(sub, [*path, name])


def test_no_help_text_shows_a_doubled_percent_sign():
    seen = []
    for command, parser in _parsers(build_parser(), ["vlm-vpr"]):
        text = parser.format_help()  # what --help prints (argparse %-formats help strings)
        assert "%%" not in text and "%(" not in text, command
        seen.append(command)
    assert len(seen) > 20 and "vlm-vpr calibrate" in seen
    assert "68 % / 95 %" in dict(_parsers(build_parser(), ["vlm-vpr"]))[
        "vlm-vpr calibrate"].format_help()
