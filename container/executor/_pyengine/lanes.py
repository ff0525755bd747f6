"""What a callback group's lane is, as the lanes and the async chain read it (``fastpath/lanes.c``).

:class:`Work` (one callback invocation), :class:`Token` (whether an
entity's work may still start), :class:`Runner` (a lane's runner task, the
future it idles on and the context it runs in), :class:`KeepLast` (work
waiting, bounded per entity like a DDS keep-last history), :class:`Slots`
(a lane's admission state: how many run, the limit, what waits, the idle
runners), :class:`Route` (what the async chain needs of one entity,
resolved once per wait-set change) and :class:`Routes` (the wait set's
current routes and its dirty and closed flags).

One admission protocol serves both paths: the Python lanes call the
methods of :class:`Slots` under its lock; the async chain (``express``)
reads and changes the same state through this module's functions
(:func:`admit_first_step`, :func:`release_first_step`,
:func:`undo_first_step`) while the lock is free. The fields the compiled
engine keeps to itself are this module's own too: other modules of the
engine go through the functions below, as ``fastpath.h`` declares them for C.

Difference: the compiled chain changes a lane's state without taking its
lock, because it holds the GIL and runs no Python code in between: no
thread can come in. Python code can be interrupted between any two
bytecodes, so here the chain takes the lock, without waiting (a lock held
by another thread is what the compiled one reads as "the lane is locked").
"""

from __future__ import annotations

import contextvars
import operator
import time
from collections.abc import Callable
from typing import Any

from .held import Held
from .lock import Lock
from .meter import Meter, begin, count_dropped, end, pause, resume
from .taker import Taker

__all__ = [
    "KeepLast",
    "Route",
    "Routes",
    "Runner",
    "Slots",
    "Token",
    "Work",
    "admit_first_step",
    "release_first_step",
    "undo_first_step",
]


def _integer(value: object) -> int:
    """``value`` as the compiled engine takes a count (``PyLong_AsSsize_t``): an ``int``, nothing else."""
    if not isinstance(value, int):
        raise TypeError("an integer is required")
    return value


# -- Token ---------------------------------------------------------------------------------


class Token:
    """Whether work of one entity (or of a node itself) may still start.

    The dispatcher retires a token when its entity is destroyed or its node
    is removed from the executor; work already waiting in a lane is then
    dropped instead of run, as rclpy's executors drop it.
    """

    __slots__ = ("_node", "_retired")

    def __init__(self, node: object, retired: bool = False) -> None:
        self._node = node
        self._retired = bool(retired)

    @property
    def node(self) -> object:
        """The node whose work this token covers."""
        return self._node

    @property
    def retired(self) -> bool:
        """Once true, the work never starts."""
        return self._retired

    @retired.setter
    def retired(self, value: bool) -> None:
        if not isinstance(value, bool):
            raise TypeError("attribute value type must be bool")
        self._retired = value


# -- Work ----------------------------------------------------------------------------------


class Work:
    """One callback invocation waiting for, or running in, a lane."""

    __slots__ = (
        "_args", "_arrived", "_call", "_depth", "_done", "_entity", "_is_async", "_meter", "_started", "_token",
    )  # fmt: skip

    def __init__(
        self,
        entity: object,
        call: Callable[..., Any],
        is_async: bool,
        depth: int,
        done: Callable[[Work, BaseException | None], None],
        token: Token | None = None,
        args: tuple[Any, ...] = (),
        *,
        meter: Meter | None = None,
        arrived: int = 0,
        started: int = 0,
    ) -> None:
        depth = operator.index(depth)
        if not isinstance(args, tuple):
            raise TypeError(f"Work() argument 7 must be tuple, not {type(args).__name__}")
        if token is not None and not isinstance(token, Token):
            raise TypeError("Work: token must be a Token or None")
        if meter is not None and not isinstance(meter, Meter):
            raise TypeError("Work: meter must be a Meter or None")
        self._entity = entity
        self._call = call
        self._is_async = bool(is_async)
        self._depth = depth
        self._done = done
        self._token = token
        self._args = args
        self._meter = meter
        # Stamped only when metered: nothing else reads it.
        self._arrived = arrived if arrived > 0 or meter is None else time.monotonic_ns()
        self._started = started

    def __repr__(self) -> str:
        return f"Work(entity={self._entity!r}, is_async={self._is_async}, depth={self._depth})"

    @property
    def entity(self) -> object:
        """The rclpy entity whose callback this is (identity only)."""
        return self._entity

    @property
    def call(self) -> Callable[..., Any]:
        """Runs the callback with ``args``; returns a coroutine when ``is_async``."""
        return self._call

    @property
    def is_async(self) -> bool:
        return self._is_async

    @property
    def depth(self) -> int:
        """How many waiting invocations of ``entity`` to keep."""
        return self._depth

    @property
    def done(self) -> Callable[[Work, BaseException | None], None]:
        """``done(work, error)``: told the outcome where ``call`` ran."""
        return self._done

    @property
    def token(self) -> Token | None:
        """Whose work this is (``None``: nobody's to retire)."""
        return self._token

    @property
    def args(self) -> tuple[Any, ...]:
        """What ``call`` is called with (a taken message)."""
        return self._args

    @property
    def meter(self) -> Meter | None:
        """What its callback costs is told (``None``: not metered)."""
        return self._meter

    @property
    def arrived(self) -> int:
        """When it arrived (monotonic ns: taken, or a timer's due time; 0 when not metered)."""
        return self._arrived

    @property
    def started(self) -> int:
        """When its first step started (monotonic ns; 0: not yet, or not metered)."""
        return self._started

    def run(self, context: contextvars.Context, /) -> Any:
        """A plain callback: ``call(*args)`` in ``context``, timed by its meter."""
        if type(context) is not contextvars.Context:
            raise TypeError("run(context): a contextvars.Context")
        return context.run(self._run)

    def _run(self) -> Any:
        meter = self._meter
        if meter is None:
            return self._call(*self._args)
        start = self._started = begin(meter, self._arrived)
        try:
            return self._call(*self._args)
        finally:
            end(meter, start, start)

    def step(self, send: Callable[[Any], Any], value: Any, /) -> Any:
        """``send(value)``: one step of the async callback's coroutine (``send`` is its
        ``send`` or ``throw``), timed by its meter: the first step begins it, a step
        that raises (``StopIteration`` included) ends it."""
        meter = self._meter
        if meter is None:
            return send(value)
        if self._started == 0:
            start = self._started = begin(meter, self._arrived)
        else:
            start = resume(meter)
        try:
            result = send(value)
        except BaseException:
            end(meter, start, self._started)
            raise
        pause(meter, start)
        return result


def set_started(work: Work, started: int) -> None:
    """When ``work``'s first step started (0: reset), as the async chain's first step tells it."""
    work._started = started


# -- Runner --------------------------------------------------------------------------------


class Runner:
    """A runner task of a lane, the future it idles on, the context it runs in.

    ``idle`` and ``current`` are written by the lane and by the first step,
    on the loop thread.
    """

    __slots__ = ("_context", "_task", "current", "idle")

    def __init__(self, task: Any, context: contextvars.Context, idle: Any = None, current: Work | None = None) -> None:
        if type(context) is not contextvars.Context:
            raise TypeError("Runner: context must be a contextvars.Context")
        self._task = task
        self._context = context
        #: The future it idles on, or ``None`` while busy.
        self.idle = idle
        #: The work it carries now, or ``None``.
        self.current = current

    @property
    def task(self) -> Any:
        """The runner's asyncio task."""
        return self._task

    @property
    def context(self) -> contextvars.Context:
        """The context it runs in (each callback in a copy)."""
        return self._context


# -- KeepLast ------------------------------------------------------------------------------


class KeepLast:
    """Items in arrival order, at most ``depth`` per entity, the entity's oldest going first.

    ``_items`` and ``_entities`` are lists read from ``_head`` on (popped
    places are ``None`` until the next compaction); ``_counts`` holds each
    entity's count by its ``id``.
    """

    __slots__ = ("_counts", "_entities", "_head", "_items")

    def __init__(self) -> None:
        self._items: list[Any] = []
        self._entities: list[Any] = []
        self._counts: dict[int, int] = {}
        self._head = 0

    def _count_add(self, entity: object, delta: int) -> int:
        """The entity's count changes by ``delta`` (its entry goes at zero): the count before."""
        key = id(entity)
        count = self._counts.get(key, 0)
        if delta:
            if count + delta <= 0:
                self._counts.pop(key, None)
            else:
                self._counts[key] = count + delta
        return count

    def push(self, item: object, entity: object, depth: int, /) -> bool:
        """Append ``item`` of ``entity``, keeping at most ``depth`` of the entity's:
        ``True`` if an older one of it was dropped for this one."""
        depth = _integer(depth)
        dropped = False
        if self._count_add(entity, 0) >= depth:
            entities = self._entities
            for index in range(self._head, len(entities)):
                if entities[index] is entity:
                    older = self._items[index]
                    if (
                        isinstance(older, Work)
                        and isinstance(item, Work)
                        and 0 < older._arrived < item._arrived
                    ):
                        # The entity's callback has been owed since the older one
                        # arrived: its lateness counts from then (a timer's first missed firing).
                        item._arrived = older._arrived
                    del self._items[index]
                    del entities[index]
                    dropped = True
                    break
        if not dropped:
            self._count_add(entity, 1)
        self._items.append(item)
        self._entities.append(entity)
        return dropped

    def pop(self) -> Any:
        """The oldest item (``IndexError`` when empty)."""
        items, entities = self._items, self._entities
        head, size = self._head, len(items)
        if head >= size:
            raise IndexError("pop from an empty KeepLast")
        item = items[head]
        self._count_add(entities[head], -1)
        items[head] = entities[head] = None
        head += 1
        if head == size:
            items.clear()
            entities.clear()
            head = 0
        elif head >= 64 and head * 2 >= size:
            del items[:head]
            del entities[:head]
            head = 0
        self._head = head
        return item

    def clear(self) -> None:
        self._head = 0
        self._items.clear()
        self._entities.clear()
        self._counts.clear()

    def items(self) -> list[Any]:
        """What waits, oldest first."""
        return self._items[self._head :]

    def __len__(self) -> int:
        return len(self._items) - self._head

    def take_out(self, keep: Callable[[Any], bool]) -> list[Any]:
        """Take out every item for which ``keep(item)`` is false: they are returned in order."""
        out: list[Any] = []
        index = self._head
        while index < len(self._items):
            item = self._items[index]
            if keep(item):
                index += 1
                continue
            self._count_add(self._entities[index], -1)
            out.append(item)
            del self._items[index]
            del self._entities[index]
        return out


# -- Slots ---------------------------------------------------------------------------------


def _check_work(work: object) -> None:
    if not isinstance(work, Work):
        raise TypeError("a lane admits Work only")


def _check_runner(runner: object) -> None:
    if not isinstance(runner, Runner):
        raise TypeError("a lane parks Runners only")


def _of_node(work: Work, node: object) -> bool:
    token = work._token
    return token is not None and token._node is node


def _idle_done(runner: Runner) -> bool:
    """Whether ``runner`` is not idling on a pending future (``None``, or done: cancelled while idle)."""
    idle = runner.idle
    return idle is None or bool(idle.done())


class Slots:
    """A lane's admission state and its idle runners.

    Admission (:meth:`admit` ... :meth:`activate`) is called with :attr:`lock`
    held; the idle runners (:meth:`park` ... :meth:`idle_runner`) are the loop
    thread's only. The async chain reads and takes the same state while the
    lock is free (:func:`admit_first_step`).

    A limit under 1 is refused, by the constructor and by the :attr:`limit` setter.
    """

    __slots__ = ("_active", "_closed", "_dropped", "_idle_runners", "_limit", "_lock", "_pending", "_running")

    def __init__(self, limit: int) -> None:
        self._limit = operator.index(limit)
        if self._limit < 1:
            raise ValueError("a lane's limit is at least 1")
        self._lock = Lock()
        self._running = 0
        self._dropped = 0
        self._closed = False
        self._pending = KeepLast()
        #: Work started and not done.
        self._active: set[Work] = set()
        #: Parked runners, the last used first.
        self._idle_runners: list[Runner] = []

    @property
    def lock(self) -> Lock:
        """Held while the lane changes the state; the chain touches it only while it is free."""
        return self._lock

    @property
    def limit(self) -> int:
        """How many may run at once."""
        return self._limit

    @limit.setter
    def limit(self, limit: int) -> None:
        limit = _integer(limit)
        if limit < 1:
            raise ValueError("a lane's limit is at least 1")
        self._limit = limit

    @property
    def running(self) -> int:
        """Slots taken."""
        return self._running

    @property
    def dropped(self) -> int:
        """Waiting work dropped for newer of its entity."""
        return self._dropped

    @property
    def closed(self) -> bool:
        """Closed: nothing is admitted any more."""
        return self._closed

    @property
    def waiting(self) -> int:
        """How much work waits for a slot."""
        return len(self._pending)

    @property
    def idle(self) -> int:
        """How many runners are parked."""
        return len(self._idle_runners)

    def admit(self, work: Work, /) -> bool:
        """The slot is taken (``True``), or the work waits, keep-last per entity
        (``False``), or the lane is closed (``False``: dropped)."""
        _check_work(work)
        if self._closed:
            return False
        if self._running < self._limit:
            self._active.add(work)
            self._running += 1
            return True
        dropped = self._pending.push(work, work._entity, work._depth)
        self._dropped += dropped
        if dropped and work._meter is not None:
            count_dropped(work._meter)  # the dropped one was of the same entity
        return False

    def next(self, finished: Work, /) -> Work | None:
        """``finished`` is done: its slot goes to the oldest waiting work (returned,
        to be started) or is given back."""
        self._active.discard(finished)
        if len(self._pending) > 0 and not self._closed:
            work: Work = self._pending.pop()
            self._active.add(work)
            return work
        self._running -= 1
        return None

    def close(self) -> None:
        """Admit nothing more; what waits is dropped."""
        self._closed = True
        self._pending.clear()

    def retire(self, node: object, /) -> list[Work]:
        """The node's waiting work, taken out (to be told it was dropped)."""
        return self._pending.take_out(lambda work: not _of_node(work, node))

    def of(self, node: object, /) -> list[Work]:
        """The node's work started and not yet done."""
        return [work for work in self._active if _of_node(work, node)]

    def busy(self) -> bool:
        """Something runs or waits."""
        return self._running > 0 or len(self._pending) > 0

    def activate(self, work: Work, /) -> None:
        """Count ``work``, whose slot is taken already (a suspended first step), as started."""
        _check_work(work)
        self._active.add(work)

    def park(self, runner: Runner, /) -> None:
        """``runner`` idles (on its ``idle`` future); the last parked is used first."""
        _check_runner(runner)
        self._idle_runners.append(runner)

    def unpark(self, runner: Runner, /) -> bool:
        """Take ``runner`` out of the parked ones (``False``: it was not parked)."""
        runners = self._idle_runners
        for index in range(len(runners) - 1, -1, -1):
            if runners[index] is runner:
                del runners[index]
                return True
        return False

    def idle_runner(self) -> Runner | None:
        """The last parked runner idling on a pending future, left parked;
        those whose future is done on the way are dropped."""
        runners = self._idle_runners
        while runners:
            runner = runners[-1]
            if not _idle_done(runner):
                return runner
            # Still the last one (the call may have run code that parked more)?
            if runners and runners[-1] is runner:
                runners.pop()
            else:
                self.unpark(runner)
        return None


def admit_first_step(slots: Slots) -> Runner | None:
    """An idle runner whose first step may run now, its slot taken; ``None`` when none
    may (the lane is locked, closed, full or without an idle runner: the Python
    path finds or makes one)."""
    lock = slots._lock
    if not lock.acquire(blocking=False):
        return None
    try:
        if slots._closed or slots._running >= slots._limit or not slots._idle_runners:
            return None
        runner = slots._idle_runners[-1]
        if _idle_done(runner):
            return None  # not idle after all: the Python path finds or makes one
        slots._running += 1
        return runner
    finally:
        lock.release()


def release_first_step(slots: Slots) -> bool:
    """The slot :func:`admit_first_step` took is given back: ``False`` done,
    ``True`` when the lane must do it (its lock is held, or work waits for the slot)."""
    lock = slots._lock
    if not lock.acquire(blocking=False):
        return True
    try:
        if len(slots._pending) > 0:
            return True
        slots._running -= 1
        return False
    finally:
        lock.release()


def undo_first_step(slots: Slots) -> None:
    """The first step could not even start: its slot is given back as it was taken."""
    with slots._lock:
        slots._running -= 1


# -- Route ---------------------------------------------------------------------------------


class Route:
    """What the async chain needs of one entity, resolved once per wait-set change.

    A subscription's ``first`` is its :class:`~.taker.Taker` (which holds the
    subscription); a timer's is its handle, held here (entered) until the
    route is collected: :meth:`~.express.Express.call_timers` calls it.
    """

    __slots__ = ("_callback", "_entity", "_entry", "_first", "_lane", "_marker", "_slots", "_token", "arrived", "timer")

    def __init__(
        self, *, first: Any, entry: Any, lane: Any, slots: Slots, marker: Work, entity: Any, token: Token, callback: str
    ) -> None:
        if hasattr(self, "_first"):
            raise RuntimeError("Route is initialised once")
        for name, value, kind in (("slots", slots, Slots), ("marker", marker, Work), ("token", token, Token)):
            if not isinstance(value, kind):
                raise TypeError(f"Route() argument '{name}' must be {kind.__name__}, not {type(value).__name__}")
        if not isinstance(callback, str):
            raise TypeError(f"Route() argument 'callback' must be str, not {type(callback).__name__}")
        #: A timer's handle, held (``None`` for a subscription's route): the chain's.
        self.timer: Held | None = None if isinstance(first, Taker) else Held(first)
        self._first = first
        self._entry = entry
        self._lane = lane
        self._slots = slots
        self._marker = marker
        self._entity = entity
        self._token = token
        self._callback = callback
        #: When what it runs next arrived (monotonic ns): taken, or the timer's due
        #: time; the chain's to write and read.
        self.arrived = 0

    @property
    def first(self) -> Any:
        """The subscription's Taker, or the timer's handle (held)."""
        return self._first

    @property
    def entry(self) -> Any:
        """The dispatcher's entry, handed back to its hooks."""
        return self._entry

    @property
    def lane(self) -> Any:
        """The lane, handed back to its hooks."""
        return self._lane

    @property
    def slots(self) -> Slots:
        """The lane's Slots."""
        return self._slots

    @property
    def marker(self) -> Work:
        """The Work a runner carries meanwhile (for reports)."""
        return self._marker

    @property
    def entity(self) -> Any:
        """The rclpy entity."""
        return self._entity

    @property
    def token(self) -> Token:
        """The entity's Token."""
        return self._token

    @property
    def callback(self) -> str:
        """The name of the entity's callback attribute."""
        return self._callback


# -- Routes --------------------------------------------------------------------------------


def _copied(value: object) -> dict[int, Route]:
    """A copy of ``value``: what the chain reads is never changed under it."""
    if not isinstance(value, dict):
        raise TypeError("routes are a dict of handle address -> Route")
    return dict(value)


class Routes:
    """A wait set's current routes, and whether they are stale (``dirty``) or ``closed``.

    The dicts are copied when set: what the chain reads is never changed under it.
    """

    __slots__ = ("_subscriptions", "_timers", "closed", "dirty")

    def __init__(self) -> None:
        #: The entities changed: the routes are stale until rebuilt.
        self.dirty = True
        #: The wait set is closed: nothing is taken.
        self.closed = False
        self._subscriptions: dict[int, Route] = {}
        self._timers: dict[int, Route] = {}

    @property
    def subscriptions(self) -> dict[int, Route]:
        """Async subscriptions the chain takes and runs, by handle address."""
        return self._subscriptions

    @subscriptions.setter
    def subscriptions(self, value: dict[int, Route]) -> None:
        self._subscriptions = _copied(value)

    @property
    def timers(self) -> dict[int, Route]:
        """Async timers the chain calls and runs, by handle address."""
        return self._timers

    @timers.setter
    def timers(self, value: dict[int, Route]) -> None:
        self._timers = _copied(value)
