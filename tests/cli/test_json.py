"""Every command with ``--json`` is tested for printing exactly one JSON document (tests/cli/test_pipes.py)."""

from __future__ import annotations

import argparse
from collections.abc import Iterator

from container.cli import build_parser
from tests.cli.test_pipes import JSON_OUTPUT

Command = tuple[str, ...]


def _commands(parser: argparse.ArgumentParser, path: Command = ()) -> Iterator[tuple[Command, set[str]]]:
    """Each command of ``parser`` (its words) with its option strings; sub-commands before their parent."""
    options: set[str] = set()
    for action in parser._actions:
        options.update(action.option_strings)
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _commands(sub, (*path, name))
    yield path, options


def test_every_command_with_json_output_is_tested_as_one_document() -> None:
    with_json = sorted(path for path, options in _commands(build_parser()) if "--json" in options)
    assert with_json == [("top",)]  # `container list` and the rest print text only
    tested = {args[: args.index("--json")] for args in JSON_OUTPUT}
    assert set(with_json) <= tested
