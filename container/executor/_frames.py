"""Stacks cut down to a plugin's own frames, for reports a plugin author reads.

A stack through the executor is mostly ours: asyncio's event loop, rclpy,
the ``container`` package, the standard library. Twenty-five such frames
around the one line of plugin code that blocked (or raised) hide that line;
they are counted, not shown. *Platform* frames are those in the standard
library (asyncio included, and frozen import machinery), ``rclpy`` and
``container``; every other frame (the plugin, the libraries it calls,
tests) is the plugin's.
"""

from __future__ import annotations

import functools
import os
import site
import sys
import sysconfig
import traceback
from collections.abc import Iterable
from traceback import FrameSummary
from types import TracebackType

__all__ = ["format_plugin_frames", "is_platform_file"]

#: Packages whose frames are the platform's besides the standard library.
_PLATFORM_PACKAGES = ("rclpy", "container")

#: Platform frames shown when a stack has no plugin frame at all.
_FALLBACK_FRAMES = 3


@functools.cache
def _platform_roots() -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(platform directories, installed-package directories inside them)."""
    paths = sysconfig.get_paths()
    roots = {paths["stdlib"], paths["platstdlib"]}
    for name in _PLATFORM_PACKAGES:
        module = sys.modules.get(name)
        roots.update(getattr(module, "__path__", ()))
    # A system Python's site-packages may sit inside its standard library.
    installed = {paths["purelib"], paths["platlib"], *_site_dirs()}
    return _dirs(roots), _dirs(installed)


def _site_dirs() -> list[str]:
    dirs = list(getattr(site, "getsitepackages", list)())
    user = getattr(site, "getusersitepackages", None)
    if user is not None:
        dirs.append(user())
    return dirs


def _dirs(paths: Iterable[str]) -> tuple[str, ...]:
    return tuple(os.path.join(os.path.realpath(path), "") for path in paths if path)


def _command_file() -> str | None:
    """The script this process runs when it is the ``container`` command, resolved.

    The command is a file in the environment's ``bin/`` (or ``lib/<package>``
    for ros2 run), outside every platform directory: without this, the
    bottom frame of every thread's stack would pass for a plugin's.
    """
    main = sys.modules.get("__main__")
    command = sys.modules.get("container.__main__")
    file = getattr(main, "__file__", None)
    if file is None or command is None or getattr(main, "main", None) is not getattr(command, "main", None):
        return None
    return os.path.realpath(str(file))


@functools.lru_cache(maxsize=1024)
def is_platform_file(filename: str) -> bool:
    """Whether code in ``filename`` is the platform's (see the module's docstring)."""
    if filename.startswith("<frozen "):
        return True  # importlib's bootstrap, frozen into the interpreter
    if filename.startswith("<"):
        return False  # code a plugin compiled or exec'd itself
    path = os.path.realpath(filename)
    if path == _command_file():
        return True  # the `container` command's script (its `sys.exit(main())` line)
    roots, installed = _platform_roots()
    inside = [root for root in roots if path.startswith(root)]
    if not inside:
        return False
    deepest = max(inside, key=len)
    # Under site-packages inside the stdlib: only rclpy and container count.
    return not any(path.startswith(site) and len(site) > len(deepest) for site in installed)


def format_plugin_frames(
    stack: TracebackType | Iterable[FrameSummary] | None, *, innermost_first: bool = True
) -> str:
    """Format ``stack`` showing the plugin's frames and counting the platform's.

    :param stack: a traceback (``exc.__traceback__``) or frames in call order,
        outermost first, as :func:`traceback.extract_stack` and
        :func:`traceback.extract_tb` return them.
    :param innermost_first: list the innermost frame (where the code is
        now, or raised) first, as the watchdog does so that the line that
        blocks opens its report; ``False``: call order, as Python prints
        tracebacks.
    :return: the plugin's frames as :func:`traceback.format_list` formats
        them, then one line counting the platform frames left out. A stack
        without any plugin frame shows its innermost few frames instead.
        No trailing newline.
    """
    if stack is None:
        frames: list[FrameSummary] = []
    elif isinstance(stack, TracebackType):
        frames = list(traceback.extract_tb(stack))
    else:
        frames = list(stack)
    shown = [frame for frame in frames if not is_platform_file(frame.filename)]
    if not shown:
        shown = frames[-_FALLBACK_FRAMES:]
    omitted = len(frames) - len(shown)
    if innermost_first:
        shown.reverse()
    lines = traceback.format_list(shown)
    if omitted:
        plural = "s" if omitted != 1 else ""
        lines.append(f"  ({omitted} platform frame{plural} omitted: asyncio, rclpy, container, stdlib)\n")
    return "".join(lines).rstrip("\n") or "  (no stack)"
