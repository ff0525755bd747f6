"""A command's output closed early (``container list | head -1``): quiet, status 0.

Python ignores SIGPIPE, so a write to a pipe nobody reads any more raises
``BrokenPipeError`` wherever the command happens to print, and the
interpreter's last flush of ``sys.stdout`` raises again at exit (status 120).
The usual cure for a Python program, SIGPIPE back to ``SIG_DFL``, is wrong
here: the kernel would kill the process at that write, in the middle of a ROS
session, so the client node's DDS participant would never be destroyed (the
container and every peer keep it in discovery until its lease runs out; its
shared-memory segments stay behind), and the shell would report 141, not 0.
The disposition is the whole process's, too: any socket a plugin or a
transport writes to would kill the container when its peer hangs up, and
every child process would inherit it. So SIGPIPE stays ignored, and the
standard streams are guarded instead (:func:`guard_output`, by the
``container`` process's entry point, :mod:`container.__main__`, before the
command line is imported; this module imports only the standard library):

* the first write or flush that finds its reader gone points the stream's
  file descriptor at ``/dev/null``, so that nothing written afterwards fails:
  neither the session's clean-up, nor rich's last refresh, nor the
  interpreter's final flush;
* standard output: a command that only reads (``list``, ``top``,
  ``lifecycle get``, ...) stops there: the write raises ``BrokenPipeError``,
  the session shuts ROS down as for any error, and the entry point ends the
  process with status 0 (:func:`closed_early`). A command that acts
  (``load``, ``unload``, ``lifecycle set``, ``index``, ``run``,
  ``manager``: its parser sets ``finish_without_output``, and the command
  line calls :func:`finish_without_output`) carries on and does all it was
  asked, its status its own: ``container unload C 1 2 | head -1``
  must not leave component 2 loaded and still exit 0;
* standard error (diagnostics, and a server's log through ``logging``;
  rcutils writes to the descriptor itself and ignores the error) never stops
  a command.

A ``BrokenPipeError`` from anything else (a plugin's socket) is not one of
these, and is not silenced.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
from typing import TextIO

__all__ = ["closed_early", "finish_without_output", "guard_output"]


class _GuardedStream(io.TextIOWrapper):
    """A standard stream, rewrapped around the same buffer: its closed reader is noticed once.

    :ivar closed_early: the reader went away and the descriptor now points at ``/dev/null``.
    """

    def __init__(self, stream: TextIO, *, stop: bool) -> None:
        super().__init__(
            stream.buffer,
            encoding=stream.encoding,
            errors=stream.errors,
            line_buffering=bool(stream.line_buffering),
            write_through=getattr(stream, "write_through", False),
        )
        self.stop = stop
        self.closed_early = False

    def write(self, text: str) -> int:
        try:
            return super().write(text)
        except BrokenPipeError:
            self._reader_gone()
            return len(text)

    def flush(self) -> None:
        try:
            super().flush()
        except BrokenPipeError:
            self._reader_gone()

    def _reader_gone(self) -> None:
        first = not self.closed_early
        if first:
            self.closed_early = True
            devnull = os.open(os.devnull, os.O_WRONLY)
            try:
                os.dup2(devnull, self.fileno())
            finally:
                os.close(devnull)
        # What the buffer still holds goes to /dev/null now, not at exit.
        with contextlib.suppress(OSError, ValueError):
            super().flush()
        if first and self.stop:
            raise BrokenPipeError("standard output closed by its reader")


def guard_output() -> None:
    """Guard the process's own ``sys.stdout`` and ``sys.stderr``; closed standard output stops the command.

    Streams replaced already (pytest's capture, a caller's redirection) are
    not the process's descriptors, and are left alone.
    """
    if sys.stdout is sys.__stdout__ and isinstance(sys.stdout, io.TextIOWrapper):
        sys.stdout.flush()
        sys.stdout = _GuardedStream(sys.stdout, stop=True)
    if sys.stderr is sys.__stderr__ and isinstance(sys.stderr, io.TextIOWrapper):
        sys.stderr.flush()
        sys.stderr = _GuardedStream(sys.stderr, stop=False)


def finish_without_output() -> None:
    """Let the command do all it was asked when standard output closes early (it acts, not only reads)."""
    if isinstance(sys.stdout, _GuardedStream):
        sys.stdout.stop = False


def closed_early() -> bool:
    """Whether the reader of standard output went away (the command may end quietly, status 0)."""
    return isinstance(sys.stdout, _GuardedStream) and sys.stdout.closed_early
