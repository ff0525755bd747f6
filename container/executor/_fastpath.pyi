"""The executor's engine: what the compiled ``_fastpath`` (``fastpath/*.c``) and
the pure-Python ``_pyengine`` both provide (``_engine`` chooses one).

Every object that reads an rcl or rmw pointer is given the rclpy handle that
owns it (``entity.handle``, never its address): it holds a strong reference
to the handle and keeps it entered (``__enter__``) until ``close()`` (or
until it is collected), so the rcl object outlives every use. Readiness is
reported by handle address (``handle.pointer``): a key to look entries up
by, never dereferenced by the caller.
"""

import asyncio
import contextvars
from collections.abc import Callable, Iterable, Mapping, Sequence, Sized
from typing import Any, Protocol, TypeVarTuple

_Ts = TypeVarTuple("_Ts")

class Handle(Protocol):
    """An rclpy handle (``Subscription``, ``Timer``, ``GuardCondition``, ``Context``, ...
    of ``rclpy._rclpy_pybind11``): the owner of one rcl object."""

    @property
    def pointer(self) -> int: ...
    def __enter__(self) -> Any: ...
    def __exit__(self, exc_type: Any, exc_value: Any, traceback: Any, /) -> Any: ...

SUBSCRIPTION: int
CLIENT: int
SERVICE: int
EVENT: int
#: The count ``ready()`` gives for "take until nothing is left" (a fresh watch).
DRAIN: int

class Notifier:
    """rmw's new-data callbacks of the watched entities, turned into a ready list and
    one trigger of ``guard`` while the waiter sleeps (armed)."""

    def __init__(self, *, guard: Handle) -> None: ...
    def watch(self, handle: Handle, kind: int, plain: bool = False, /) -> bool:
        """Report new data of ``handle``'s entity (kept entered until :meth:`unwatch`);
        ``False``: watched already. ``NotImplementedError`` where rmw (or the engine)
        offers no such callback: the entity is then waited on."""
    def unwatch(self, handle: Handle, /) -> bool:
        """Stop; no callback for it runs once this returns (then the handle is let go)."""
    def arm(self) -> bool: ...
    def disarm(self) -> None: ...
    def pending(self) -> bool: ...
    def ready(self) -> list[tuple[int, int]]: ...
    def carry(self) -> list[tuple[int, int]]: ...
    def close(self) -> None:
        """Never trigger the guard again; unwatch everything and let every handle go."""
    @property
    def triggers(self) -> int: ...
    @property
    def watched(self) -> int: ...

class FdWatcher:
    """A thread that triggers the rcl guard condition ``guard`` (held until
    :meth:`close`) once, each time it is armed, when ``epoll`` becomes readable."""

    def __init__(self, *, epoll: int, guard: Handle) -> None: ...
    def arm(self) -> None: ...
    def take(self) -> bool: ...
    def pending(self) -> bool: ...
    def close(self) -> None: ...
    @property
    def armed(self) -> bool: ...
    @property
    def wakes(self) -> int: ...

class Deadline:
    """Unless :meth:`cancel` comes within ``seconds``, a thread that needs no GIL says
    ``message`` (WARN, under ``logger``, on rcutils' console sink) and ends the process
    with status ``code``."""

    def __init__(self, seconds: float, *, code: int, logger: str, message: str) -> None: ...
    def cancel(self) -> None: ...

class Handoff:
    """The busy loop thread lets go of the GIL until the workers it woke have started.

    ``spin``: whether a thread may stay awake (spinning, without the GIL) for
    another's hand-over; ``False`` where the process has one CPU, on which a
    spinning thread only delays the thread it waits for.
    """

    def __init__(self, *, spin: bool = True) -> None: ...
    @property
    def spin(self) -> bool: ...
    def handed(self) -> None: ...
    def started(self) -> None: ...
    def finished(self) -> None: ...
    def give(self, timeout_ns: int, spin_ns: int = 0, /) -> bool: ...
    def linger(self, spin_ns: int, /) -> bool: ...
    @property
    def outstanding(self) -> int: ...
    @property
    def given(self) -> int: ...
    @property
    def lingered(self) -> int: ...

def poll(wait_set: Handle, timeout_ns: int, /) -> None:
    """``rcl_wait`` on rclpy's wait set, keeping the GIL (the compiled engine): for a
    wait whose guard condition is already triggered."""

def first_step(
    loop: object,
    enter_task: Callable[..., object],
    leave_task: Callable[..., object],
    cancelled_error: type[BaseException],
    runner: Runner,
    work: Work,
    /,
) -> BaseException | tuple[Any, Any, contextvars.Context] | None:
    """Async ``work`` up to its first suspension, in ``runner``'s task and a copy of its context
    (the same step the compiled chain runs): ``None`` done (or cancelled itself), the
    error it failed with, or ``(coro, yielded, context)`` suspended."""

def mark_carrier() -> None:
    """This thread takes, after each plain callback, what it published to
    other plain callbacks (``Notifier.carry``): a notifier's waiter due to
    wake within 5 ms anyway is not woken for such a publish."""

def publisher_gid(publisher: Handle, /) -> dict[str, str | bytes]:
    """The gid of ``publisher``'s rcl publisher (its handle), as rclpy 9's message
    info gives a message's ``publisher_gid``."""

class Lock:
    """A mutex used as ``threading.Lock``, which the compiled path checks and takes directly."""

    def __init__(self) -> None: ...
    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool: ...
    def release(self) -> None: ...
    def locked(self) -> bool: ...
    def __enter__(self) -> bool: ...
    def __exit__(self, *exc_info: object) -> None: ...

class Taker:
    """One subscription's messages (its handle held), taken into a kept C message."""

    def __init__(self, *, subscription: Handle, message_type: type, publisher_gid: bool = False) -> None: ...
    def take(self) -> object | None: ...
    def take_with_info(self) -> tuple[object, dict[str, Any]] | None:
        """With the keys rclpy's ``take_message`` gives (``publisher_gid`` when made with it)."""
    def close(self) -> None:
        """Let the handle go; a take after this raises ``RuntimeError``."""

class Server:
    """One service's requests, taken into a kept C message, and its answers."""

    def __init__(self, *, service: Handle, srv_type: type) -> None: ...
    def take(self) -> tuple[Any, Any] | None:
        """``(request, header)``; the header (opaque: bytes in C, rclpy's request id in
        Python) is for :meth:`send` only."""
    def send(self, response: Any, header: Any, let_go: bool = False, /) -> bool:
        """``False`` while the client's response reader is not matched (rmw waits up to
        100 ms for it, without the GIL with ``let_go``); ``TypeError`` for a response
        of another type."""
    def close(self) -> None:
        """Let the handle go; a take or send after this raises ``RuntimeError``."""
    @property
    def closed(self) -> bool: ...

class Caller:
    """One client's responses, taken into a kept C message."""

    def __init__(self, *, client: Handle, srv_type: type) -> None: ...
    def take(self) -> tuple[int, Any] | None:
        """``(sequence_number, response)``."""
    def close(self) -> None:
        """Let the handle go; a take after this raises ``RuntimeError``."""

#: What :meth:`WaitSet.wait` gives: the ready handle addresses of each kind
#: (subscriptions, guard conditions, timers, clients, services, events), or
#: an empty tuple when it timed out.
Ready = tuple[list[int], ...]

class WaitSet:
    """An rcl wait set over entities given once (their handles held until :meth:`close`)."""

    def __init__(
        self,
        context: Handle,
        *,
        subscriptions: Sequence[Handle] = (),
        guard_conditions: Sequence[Handle] = (),
        timers: Sequence[Handle] = (),
        clients: Sequence[Handle] = (),
        services: Sequence[Handle] = (),
        events: Sequence[Handle] = (),
        notifier: Notifier | None = None,
        handoff: Handoff | None = None,
    ) -> None: ...
    def wait(self, timeout_ns: int, poll: bool = False, /) -> Ready: ...
    @property
    def timers_waited(self) -> int:
        """How many timers the last wait gave ``rcl_wait`` (the others wait for their deadline apart)."""
    def close(self) -> None:
        """Let every handle go; a wait after this raises ``RuntimeError``."""

class Token:
    """Whether work for one entity (or for a node itself) may still start.

    The dispatcher retires a token when its entity is destroyed or its node
    is removed from the executor; work already waiting in a lane is then
    dropped instead of run, as rclpy's executors drop it.
    """

    @property
    def node(self) -> object: ...
    retired: bool
    def __init__(self, node: object, retired: bool = False) -> None: ...

class Work:
    """One callback invocation waiting for, or running in, a lane."""

    @property
    def entity(self) -> object:
        """The rclpy entity whose callback this is (identity only)."""
    @property
    def call(self) -> Callable[..., Any]:
        """Runs the callback with ``args``; returns a coroutine when ``is_async``."""
    @property
    def is_async(self) -> bool: ...
    @property
    def depth(self) -> int:
        """How many waiting invocations of ``entity`` to keep."""
    @property
    def done(self) -> Callable[[Work, BaseException | None], None]:
        """Told the outcome, in the thread or task that ran ``call``."""
    @property
    def token(self) -> Token | None:
        """Whose work this is; once retired, the work never starts."""
    @property
    def args(self) -> tuple[Any, ...]:
        """What ``call`` is called with (a taken message)."""
    @property
    def meter(self) -> Meter | None:
        """What its callback costs is told (``None``: not metered)."""
    @property
    def arrived(self) -> int:
        """When it arrived (monotonic ns: taken, or a timer's due time; 0 when not metered)."""
    @property
    def started(self) -> int:
        """When its first step started (monotonic ns; 0: not yet, or not metered)."""
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
    ) -> None: ...
    def run(self, context: contextvars.Context, /) -> Any:
        """A plain callback: ``call(*args)`` in ``context``, metered."""
    def step(self, send: Callable[[Any], Any], value: Any, /) -> Any:
        """``send(value)``: one step of the async callback's coroutine, metered (the first
        begins it; one that raises, ``StopIteration`` included, ends it)."""

class Meter:
    """What one entity's callbacks cost, per window (see ``fastpath/meter.c``)."""

    @property
    def running(self) -> int:
        """How long the step running now has run (ns; 0: none runs)."""
    def call(self, arrived: int, call: Callable[..., Any], /, *args: Any) -> Any:
        """``call(*args)`` as one run of this meter, begun (its lateness from ``arrived``,
        monotonic ns; 0 unknown) and ended when it returns or raises."""

    def take(self) -> tuple[int, int, int, int, int, int, int, int, int, int, int, int, int]:
        """``(runs, finished, busy_ns, cpu_ns, late_p50, late_p99, late_max, duration_p50,
        duration_p99, duration_max, dropped, stuck, running_ns)``: this window's, then a new one."""

class HandleMeter:
    """The first base of an event loop whose ``call_soon`` and ``call_at`` meter each handle a
    node's code schedules as that node's (see ``fastpath/handles.c`` and ``_loop.py``)."""

    def __init__(
        self,
        owner: contextvars.ContextVar[Any],
        executor: object,
        task_type: type,
        call_soon: Callable[..., Any],
        call_at: Callable[..., Any],
        unattributed: Any,
    ) -> None: ...
    def call_soon(
        self, callback: Callable[[*_Ts], object], *args: *_Ts, context: contextvars.Context | None = None
    ) -> asyncio.Handle:
        """The loop's own ``call_soon``; a node's handle is scheduled metered as its."""
    def call_at(
        self, when: float, callback: Callable[[*_Ts], object], *args: *_Ts, context: contextvars.Context | None = None
    ) -> asyncio.TimerHandle:
        """The loop's own ``call_at``; a node's timer is scheduled metered as its, late from ``when``."""

def stuck_after(ns: int, /) -> None:
    """How long one step of a callback runs before its meter counts it stuck (every meter)."""

class Runner:
    """A runner task of a lane, the future it idles on, the context it runs in."""

    @property
    def task(self) -> Any: ...
    @property
    def context(self) -> contextvars.Context: ...
    idle: Any
    current: Work | None
    def __init__(
        self, task: Any, context: contextvars.Context, idle: Any = None, current: Work | None = None
    ) -> None: ...

class KeepLast:
    """Items in arrival order, at most ``depth`` per entity, the entity's oldest going first."""

    def push(self, item: object, entity: object, depth: int, /) -> bool: ...
    def pop(self) -> Any: ...
    def clear(self) -> None: ...
    def items(self) -> list[Any]: ...
    def __len__(self) -> int: ...

class Slots:
    """A lane's admission state and its idle runners.

    Admission (:meth:`admit` ... :meth:`activate`) is called with :attr:`lock`
    held; the idle runners (:meth:`park` ... :meth:`idle_runner`) are the loop
    thread's only. The compiled chain reads and takes the same state while
    the lock is free.
    """

    @property
    def lock(self) -> Lock: ...
    limit: int
    @property
    def running(self) -> int: ...
    @property
    def dropped(self) -> int: ...
    @property
    def closed(self) -> bool: ...
    @property
    def waiting(self) -> int: ...
    @property
    def idle(self) -> int:
        """How many runners are parked."""
    def __init__(self, limit: int) -> None: ...
    def admit(self, work: Work, /) -> bool: ...
    def next(self, finished: Work, /) -> Work | None: ...
    def activate(self, work: Work, /) -> None:
        """Count ``work``, whose slot is taken already (a suspended first step), as started."""
    def close(self) -> None: ...
    def retire(self, node: object, /) -> list[Work]: ...
    def of(self, node: object, /) -> list[Work]: ...
    def busy(self) -> bool: ...
    def park(self, runner: Runner, /) -> None:
        """``runner`` idles (on its ``idle`` future); the last parked is used first."""
    def unpark(self, runner: Runner, /) -> bool:
        """Take ``runner`` out of the parked ones (it was woken, or its task ended)."""
    def idle_runner(self) -> Runner | None:
        """The last parked runner whose ``idle`` future is pending (left parked);
        parked runners whose future is done (cancelled while idle) are dropped."""

class Route:
    """What the async chain needs of one entity, resolved once per wait-set change."""

    @property
    def first(self) -> Any: ...
    @property
    def entry(self) -> Any: ...
    @property
    def lane(self) -> Any: ...
    @property
    def slots(self) -> Slots: ...
    @property
    def marker(self) -> Work: ...
    @property
    def entity(self) -> Any: ...
    @property
    def token(self) -> Token: ...
    @property
    def callback(self) -> str: ...
    def __init__(
        self, *, first: Any, entry: Any, lane: Any, slots: Slots, marker: Work, entity: Any, token: Token, callback: str
    ) -> None: ...

class Routes:
    """A wait set's current routes, and whether they are stale or closed.

    The dicts are copied when set: what the chain reads is never changed under it.
    """

    dirty: bool
    closed: bool
    subscriptions: dict[int, Route]
    timers: dict[int, Route]

class Express:
    def __init__(
        self,
        *,
        notifier: Notifier,
        routes: Routes,
        take_lock: Lock,
        loop: object,
        ready_queue: object,
        eager: object,
        run_eager: Callable[[], object],
        enter_task: Callable[..., object],
        leave_task: Callable[..., object],
        on_done: Callable[[], object],
        done_waiters: Sized,
        slow: Callable[..., object],
        suspended: Callable[..., object],
        failed: Callable[..., object],
        release_pending: Callable[[Any, Work], object],
        take_rest: Callable[[list[tuple[int, int]]], object],
        cancelled_error: type[BaseException],
    ) -> None: ...
    def drain(self, deadline_ns: int, /) -> bool: ...
    def call_timers(self, routes: Mapping[int, Route], ready: Iterable[int], /) -> list[int]: ...
    def run_fired(self) -> None: ...
    @property
    def expressed(self) -> int: ...
