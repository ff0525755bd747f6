"""Whose work the loop thread runs: which node's which callback, plugin or platform.

The loop watchdog reports a stall only when the loop is stuck in a plugin's
work; the container's own start-up, imports and services are not a plugin's
fault, and a client command's output is no place for them. What is a
plugin's work:

* a callback the dispatcher runs for a node's entity (timer, subscription,
  service, client, waitable, action) or for a node itself (a lifecycle
  transition run in the node's callback group): the lane's runner task
  carries that work (``Lane.work_of``);
* a task created while such work ran, and so on down: the executor's task
  factory notes, for each task it creates, the work its creator ran
  (:class:`TaskOrigins`);
* loop work the platform runs for a node where no callback of the node
  created it, declared with :func:`working_for` (a lifecycle transition a
  ``change_state`` request started, posted to the loop from the service's
  worker thread), and the tasks created under it;
* a task or a loop handle (a reader, a ``call_later``) started where a
  node's code ran, as the accounting knows it (``_owners``): a task created
  from a node's thread or one of its handles, a serial transport's reads
  (:func:`handle_culprit`).

Everything else on the loop thread is the platform's: the session's main
task (``_guarded``), the container's own coroutines, asyncio's callbacks.
So is the work of the container's own nodes (:func:`is_platform_node`).
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import weakref
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from rclpy.node import Node

from ._engine import Token, Work
from ._entries import describe
from ._owners import OWNER, Owner

__all__ = ["Culprit", "TaskOrigins", "handle_culprit", "is_platform_node", "working_for"]


@dataclass(frozen=True, slots=True)
class Culprit:
    """What holds the loop thread, named for a log line."""

    #: ``/talker: timer callback Talker._tick``, or ``task 'Task-2' (_guarded)``.
    what: str
    #: A plugin node's work: stalls in it are reported.
    plugin: bool
    #: The same for every run of one callback (one node's entity, or the
    #: coroutine of tasks it creates): repeated stalls of it are one episode.
    key: tuple[str, ...]


#: A task's origin: the entity whose work created it, and that work's token;
#: or the owner whose code created it (see ``_owners``).
_Origin = tuple[object, Token | None] | Owner

#: Loop work declared as a node's (:func:`working_for`), in this context.
_working_for: contextvars.ContextVar[_Origin | None] = contextvars.ContextVar("working_for", default=None)


@contextlib.contextmanager
def working_for(node: Node, what: object) -> Iterator[None]:
    """Count the loop work in this block, and the tasks it creates, as ``node``'s ``what``.

    For platform code that runs a node's work on the loop where none of the
    node's callbacks created it: the watchdog then reports a stall in it as
    that node's (``what``, a callable or an entity, names it as
    ``describe`` does). Use it inside a task, as ContextVars are per task.
    """
    reset = _working_for.set((what, Token(node)))
    try:
        yield
    finally:
        _working_for.reset(reset)


def is_platform_node(node: object) -> bool:
    """Whether ``node`` is the container's own (``ComponentManager``,
    ``LifecycleManager``, ...), not a plugin's.

    The rule: its exact class is defined in a private module of the
    ``container`` package (``container._container``). A plugin's node is an
    instance of the plugin's own class, usually a subclass of a public base
    (``container.LifecycleNode``); the shipped demo plugins live in a public
    module (``container.demo``) and count as plugins.
    """
    module = type(node).__module__
    parts = module.split(".")
    return parts[0] == "container" and any(part.startswith("_") for part in parts[1:])


class TaskOrigins:
    """Remember, for each task created on the loop, the callback work it came from.

    :param runner_work: the work a lane's runner task carries now, if the
        given task is a runner.
    """

    def __init__(self, runner_work: Callable[[asyncio.Task[object]], Work | None]) -> None:
        self._runner_work = runner_work
        self._origins: weakref.WeakKeyDictionary[asyncio.Task[object], _Origin] = weakref.WeakKeyDictionary()

    def note(self, task: asyncio.Task[object], parent: asyncio.Task[object] | None) -> None:
        """``parent`` (the running task, if any) just created ``task``."""
        origin = self._origins.get(parent) if parent is not None else None
        if origin is None and parent is not None:
            work = self._runner_work(parent)
            if work is not None:
                origin = (work.entity, work.token)
        if origin is None or isinstance(origin, Owner):
            # Declared (the factory runs in the creator's context): it says more than whose code ran.
            origin = _working_for.get() or origin
        if origin is None:
            owner = OWNER.get()
            if isinstance(owner, Owner) and owner.name:
                origin = owner
        if origin is not None:
            self._origins[task] = origin

    def culprit(self, task: asyncio.Task[object] | None) -> Culprit:
        """Name what ``task`` (the loop thread's current task) runs, and whose it is."""
        if task is None:
            return Culprit("a callback outside any task", plugin=False, key=("platform",))
        work = self._runner_work(task)
        if work is not None:
            node, plugin = _owner(work.token)
            callback = describe(work.entity)
            return Culprit(f"{node}: {callback}" if node else callback, plugin=plugin, key=(node, callback))
        coro = task.get_coro()
        code = str(getattr(coro, "__qualname__", coro))
        origin = self._origins.get(task) or _declared(task)
        if origin is None:
            return Culprit(f"task {task.get_name()!r} ({code})", plugin=False, key=("platform", code))
        if isinstance(origin, Owner):
            what = f"task {task.get_name()!r} ({code})"
            return Culprit(f"{origin.name}: {what}", plugin=origin.plugin, key=(origin.name, "task", code))
        entity, token = origin
        node, plugin = _owner(token)
        callback = describe(entity)
        what = f"task {task.get_name()!r} ({code}) started by {callback}"
        return Culprit(f"{node}: {what}" if node else what, plugin=plugin, key=(node, callback, code))


def handle_culprit(node: str, plugin: bool, kind: str) -> Culprit:
    """Name a loop handle a node scheduled (``kind``: how the accounting names its kind of work;
    the report's stack shows which of its callbacks)."""
    if not node:
        return Culprit(f"{kind} of no node", plugin=False, key=("platform", kind))
    return Culprit(f"{node}: {kind}", plugin=plugin, key=(node, kind))


def _declared(task: asyncio.Task[object]) -> _Origin | None:
    """What ``task`` declared itself to work for (:func:`working_for`), or whose code made it
    (``OWNER``), on Python 3.12+."""
    get_context = getattr(task, "get_context", None)
    if get_context is None:
        return None
    context = get_context()
    declared = context.get(_working_for)
    if declared is not None:
        return declared  # type: ignore[no-any-return]
    owner = context.get(OWNER)
    return owner if isinstance(owner, Owner) and owner.name else None


def _owner(token: Token | None) -> tuple[str, bool]:
    """The node's name (empty if unknown) and whether it is a plugin's."""
    node = token.node if token is not None else None
    if not isinstance(node, Node):
        return "", False
    try:
        name = node.get_fully_qualified_name()
    except Exception:  # a node destroyed meanwhile
        name = ""
    return name, not is_platform_node(node)
