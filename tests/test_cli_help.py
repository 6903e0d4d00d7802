"""Every option and positional argument of every `vlm-vpr` command has a help text (the parser
tree walked, so a new option without help fails here)."""

from __future__ import annotations

import argparse

from vlm_vpr_ros.cli import build_parser


def _walk(parser: argparse.ArgumentParser, path: list[str]):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _walk(sub, [*path, name])
        elif not isinstance(action, argparse._HelpAction):
            yield " ".join(path), action


def test_every_option_has_help():
    seen, missing = 0, []
    for command, action in _walk(build_parser(), ["vlm-vpr"]):
        seen += 1
        if action.help == argparse.SUPPRESS:
            continue
        if not (action.help or "").strip():
            missing.append(f"{command} {'/'.join(action.option_strings) or action.dest}")
    assert seen > 150 and not missing, missing


def test_bag_make_help_names_every_option(capsys):
    import pytest

    with pytest.raises(SystemExit):
        build_parser().parse_args(["bag", "make", "--help"])
    text = capsys.readouterr().out
    for opt in ("--images", "--coords", "--out", "--rate", "--compressed", "--topic-prefix",
                "--gt-topic", "--frame-id", "--start-time", "--storage", "--mcap-compression",
                "--overwrite"):
        assert opt in text, opt
    assert "NavSatFix ground-truth topic" in text and "header.frame_id" in text
