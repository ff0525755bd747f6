"""Stacks cut down to a plugin's frames: what reports of a plugin's fault show."""

from __future__ import annotations

import asyncio
import json
import sys
import traceback
import types
from pathlib import Path

import pytest
import rclpy

import container
from container.executor._frames import format_plugin_frames, is_platform_file


def _parse(text: str) -> object:
    return json.loads(text)  # the plugin's line; the error is raised in the stdlib


def test_platform_files_are_the_stdlib_rclpy_and_container() -> None:
    assert is_platform_file(asyncio.__file__)
    assert is_platform_file(json.__file__)
    assert is_platform_file(rclpy.__file__)
    assert is_platform_file(container.__file__)
    assert is_platform_file("<frozen importlib._bootstrap>")
    assert not is_platform_file(__file__)
    assert not is_platform_file("<string>")


def test_the_container_commands_script_is_the_platforms(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    # The `container` command's file (bin/container: `sys.exit(main())`) is
    # outside every platform directory; the bottom frame of every stack.
    script = tmp_path / "container"
    script.write_text("from container.__main__ import main\n", encoding="utf-8")
    main = types.ModuleType("__main__")
    main.__file__ = str(script)
    other = str(tmp_path / "other")
    assert not is_platform_file(str(script))
    monkeypatch.setitem(sys.modules, "__main__", main)
    assert not is_platform_file(other)  # no command yet: `main` is not the container's
    from container.__main__ import main as command

    main.main = command  # type: ignore[attr-defined]
    is_platform_file.cache_clear()
    try:
        assert is_platform_file(str(script))
        assert not is_platform_file(other)
    finally:
        is_platform_file.cache_clear()


def test_a_traceback_shows_the_plugin_frames_and_counts_the_platform_ones() -> None:
    try:
        _parse("{")
    except ValueError as exc:
        error = exc
    text = format_plugin_frames(error.__traceback__)
    lines = text.splitlines()
    files = [line for line in lines if line.startswith('  File "')]
    assert files[0] == f'  File "{__file__}", line {_parse.__code__.co_firstlineno + 1}, in _parse', "innermost first"
    assert "json.loads(text)" in lines[1]
    assert files[1].endswith("in test_a_traceback_shows_the_plugin_frames_and_counts_the_platform_ones")
    assert len(files) == 2
    assert lines[-1] == "  (3 platform frames omitted: asyncio, rclpy, container, stdlib)"  # in json
    in_call_order = format_plugin_frames(traceback.extract_tb(error.__traceback__), innermost_first=False)
    assert in_call_order.splitlines()[0].endswith(files[1].rsplit(",", 1)[1]), "call order: the test first"


def test_a_stack_of_platform_frames_only_shows_its_innermost_frames() -> None:
    stack = traceback.extract_stack()  # this test's frames, pytest's and the stdlib's
    platform_only = [frame for frame in stack if is_platform_file(frame.filename)]
    text = format_plugin_frames(platform_only)
    assert text.count('  File "') == min(3, len(platform_only))
    assert format_plugin_frames([]) == "  (no stack)"
