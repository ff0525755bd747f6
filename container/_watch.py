"""``container run --reload``: reload a plugin's nodes when its code changes on disk.

For development. The files watched are those of every plugin distribution
that can be reloaded (:meth:`PluginRegistry.reloadable_sources`): each root
package's directory, found from the modules Python imported, so an editable
install is watched in its project and a plain one in ``site-packages``.
watchfiles (Rust's ``notify``: inotify on Linux) watches them on a thread of
its own and groups a burst of writes (an editor's save, a ``git checkout``)
into one batch, once no write has come for :data:`QUIET_MS`; its default
filter leaves out byte code, editors' swap files and VCS directories. Each
batch reloads the distributions it touches, one after the other on the
event loop, through the same :class:`~container._reload.Reloader` as the
``reload_node`` service; a failed reload (a syntax error saved mid-edit) is
logged once per batch, and the old code's nodes run on until the next save.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import os
import threading
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING

from ._errors import ContainerError
from ._text import MESSAGE_LIMIT, clip
from .executor import call_soon

if TYPE_CHECKING:
    from rclpy.impl.rcutils_logger import RcutilsLogger

    from ._registry import PluginRegistry
    from ._reload import Reloader

__all__ = ["QUIET_MS", "SourceWatcher"]

#: The watching thread's voice (Python logging reaches ROS logging in a container).
_logger = logging.getLogger("container.reload")

#: A batch of writes is over once none has come for this long.
QUIET_MS = 150
#: ... or once it has lasted this long.
BATCH_MS = 1000
#: How often the watching thread tells the loop it saw nothing, to see whether
#: the set of distributions changed (a plugin installed since).
_TICK_MS = 2000
#: How long watchfiles waits for a change before coming back with none.
_CHECK_MS = 250

#: One batch of changes: (kind, path) as watchfiles reports them.
Batch = set[tuple[object, str]]


class SourceWatcher:
    """Watch the plugins' code; reload a distribution's nodes when its files change."""

    def __init__(self, reloader: Reloader, registry: PluginRegistry, log: RcutilsLogger) -> None:
        self._reloader = reloader
        self._registry = registry
        self._log = log

    async def run(self) -> None:
        """Watch until cancelled."""
        loop = asyncio.get_running_loop()
        while True:
            distributions = self._registry.distributions
            sources = self._registry.reloadable_sources()
            batches: asyncio.Queue[Batch] = asyncio.Queue()

            stop = threading.Event()
            deliver = functools.partial(_deliver, loop, batches)
            paths = [path for found in sources.values() for path in found]
            if paths:
                threading.Thread(
                    target=_watch, args=(paths, _snapshot(paths), stop, deliver), name="reload-watch", daemon=True
                ).start()
                self._log.info(
                    "Reloading on change: watching "
                    + "; ".join(f"{name} ({', '.join(map(str, found))})" for name, found in sources.items())
                )
            else:
                self._log.info("Reloading on change: no reloadable plugin distribution is installed")
            try:
                while True:
                    if not paths:
                        await asyncio.sleep(_TICK_MS / 1000)
                        batch: Batch = set()
                    else:
                        batch = await batches.get()
                    if not batch:
                        if self._registry.distributions != distributions:
                            break  # watch the new set
                        continue
                    for distribution in _touched(batch, sources):
                        await self._reload(distribution)
            finally:
                stop.set()

    async def _reload(self, distribution: str) -> None:
        try:
            await self._reloader.reload_distribution(distribution)
        except ContainerError as exc:
            # The reloader logged the steps; this is the one line an author reads.
            self._log.error(clip(str(exc), limit=MESSAGE_LIMIT))
        except Exception as exc:  # a fault of ours must not end the watching
            self._log.error(f"Reloading {distribution!r} failed: {type(exc).__name__}: {clip(str(exc))}")


def _deliver(loop: asyncio.AbstractEventLoop, batches: asyncio.Queue[Batch], batch: Batch) -> None:
    """Hand a batch from the watching thread to the loop's queue (nothing once the loop is closed)."""
    call_soon(loop, batches.put_nowait, batch)


def _touched(batch: Batch, sources: Mapping[str, Iterable[Path]]) -> list[str]:
    """The distributions whose files a batch changed, in the registry's order."""
    changed = [Path(path) for _, path in batch]
    return [
        distribution
        for distribution, found in sources.items()
        if any(path == source or path.is_relative_to(source) for path in changed for source in found)
    ]


#: A file's (modification time, size), to tell what changed before the OS watch was in place.
Snapshot = dict[str, tuple[int, int]]


def _snapshot(paths: Iterable[Path]) -> Snapshot:
    """Every watched file's modification time and size, as the default filter sees them."""
    import watchfiles

    keep = watchfiles.DefaultFilter()
    found: Snapshot = {}
    for root in paths:
        walked = [(str(root.parent), [], [root.name])] if root.is_file() else os.walk(root)
        for directory, _, files in walked:
            for name in files:
                path = os.path.join(directory, name)
                if keep(watchfiles.Change.modified, path):
                    with contextlib.suppress(OSError):
                        stat = os.stat(path)
                        found[path] = (stat.st_mtime_ns, stat.st_size)
    return found


def _watch(paths: list[Path], before: Snapshot, stop: threading.Event, deliver: Callable[[Batch], None]) -> None:
    """The watching thread: each batch of changes to ``deliver``, and an empty one every tick.

    The OS watch is in place once watchfiles first comes back (after
    :data:`_CHECK_MS` at most); what changed between ``before`` (taken when
    the watch was decided on) and then is found by comparing files, and
    joins that first batch.
    """
    # It logs every batch at INFO ("1 change detected"); the reload's own lines say more.
    logging.getLogger("watchfiles").setLevel(logging.WARNING)
    try:
        _watch_changes(paths, before, stop, deliver)
    except Exception as exc:  # watchfiles' own errors (a watched directory gone): said, not silent
        _logger.error("Reloading on change stopped: watching %s failed: %s: %s", paths, type(exc).__name__, exc)


def _stat(path: str) -> tuple[int, int] | None:
    try:
        stat = os.stat(path)
    except OSError:
        return None
    return (stat.st_mtime_ns, stat.st_size)


def _unseen(paths: Iterable[str], known: Snapshot) -> set[str]:
    """The paths whose (modification time, size) is not the one ``known`` holds, ``known`` updated:
    a file is delivered once per state it is saved in, however many ways its change is told."""
    unseen = set()
    for path in paths:
        now = _stat(path)
        if known.get(path) != now:
            unseen.add(path)
            if now is None:
                known.pop(path, None)
            else:
                known[path] = now
    return unseen


def _watch_changes(
    paths: list[Path], before: Snapshot, stop: threading.Event, deliver: Callable[[Batch], None]
) -> None:
    import watchfiles

    first = True
    quiet_ms = 0
    for changes in watchfiles.watch(
        *paths,
        watch_filter=watchfiles.DefaultFilter(),
        debounce=BATCH_MS,
        step=QUIET_MS,
        stop_event=stop,
        rust_timeout=_CHECK_MS,
        yield_on_timeout=True,
        raise_interrupt=False,
    ):
        if stop.is_set():
            return
        named = {path for _, path in changes}
        if first:
            # What changed before the OS watch was in place shows only here.
            first = False
            named |= before.keys() | _snapshot(paths).keys()
        # Each state of a file once: a change the first comparison found may
        # come from the OS watch in the next batch too.
        batch: Batch = {(watchfiles.Change.modified, path) for path in _unseen(named, before)}
        if batch:
            deliver(batch)
            quiet_ms = 0
            continue
        quiet_ms += _CHECK_MS
        if quiet_ms >= _TICK_MS:
            deliver(set())
            quiet_ms = 0
