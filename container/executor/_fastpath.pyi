"""Type stub of the ``_fastpath`` extension (``fastpath/*.c``)."""

import contextvars
from collections.abc import Callable, Iterable, Mapping, Sequence, Sized
from typing import Any

SUBSCRIPTION: int
CLIENT: int
SERVICE: int
EVENT: int
#: The count ``ready()`` gives for "take until nothing is left" (a fresh watch).
DRAIN: int

class Notifier:
    def __init__(self, *, guard: int) -> None: ...
    def watch(self, pointer: int, kind: int, plain: bool = False, /) -> bool: ...
    def unwatch(self, pointer: int, /) -> bool: ...
    def arm(self) -> bool: ...
    def disarm(self) -> None: ...
    def pending(self) -> bool: ...
    def ready(self) -> list[tuple[int, int]]: ...
    def carry(self) -> list[tuple[int, int]]: ...
    def close(self) -> None: ...
    @property
    def triggers(self) -> int: ...
    @property
    def watched(self) -> int: ...

class FdWatcher:
    """A compiled thread that triggers the rcl guard condition at ``guard``
    once, each time it is armed, when ``epoll`` becomes readable."""

    def __init__(self, *, epoll: int, guard: int) -> None: ...
    def arm(self) -> None: ...
    def take(self) -> bool: ...
    def pending(self) -> bool: ...
    def close(self) -> None: ...
    @property
    def armed(self) -> bool: ...
    @property
    def wakes(self) -> int: ...

class Handoff:
    """The busy loop thread lets go of the GIL until the workers it woke have started."""

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

def poll(wait_set: int, timeout_ns: int, /) -> None:
    """``rcl_wait`` on rclpy's wait set at that address (its ``pointer``),
    keeping the GIL: for a wait whose guard condition is already triggered."""

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

def publisher_gid(publisher: int, /) -> dict[str, str | bytes]:
    """The gid of the rcl publisher at that address, as rclpy 9's message
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
    def __init__(self, *, subscription: int, message_type: type, publisher_gid: bool = False) -> None: ...
    def take(self) -> object | None: ...
    def take_with_info(self) -> tuple[object, dict[str, Any]] | None:
        """With the keys rclpy's ``take_message`` gives (``publisher_gid`` when made with it)."""

class Server:
    """One service's requests, taken into a kept C message, and its answers."""

    def __init__(self, *, service: int, srv_type: type) -> None: ...
    def take(self) -> tuple[Any, bytes] | None:
        """``(request, header)``; the header is for :meth:`send` only."""
    def send(self, response: Any, header: bytes, let_go: bool = False, /) -> bool:
        """``False`` while the client's response reader is not matched (rmw waits up to
        100 ms for it, without the GIL with ``let_go``); ``TypeError`` for a response
        of another type."""

class Caller:
    """One client's responses, taken into a kept C message."""

    def __init__(self, *, client: int, srv_type: type) -> None: ...
    def take(self) -> tuple[int, Any] | None:
        """``(sequence_number, response)``."""

#: What :meth:`WaitSet.wait` gives: the ready handle addresses of each kind
#: (subscriptions, guard conditions, timers, clients, services, events), or
#: an empty tuple when it timed out.
Ready = tuple[list[int], ...]

class WaitSet:
    def __init__(
        self,
        context: int,
        *,
        subscriptions: Sequence[int] = (),
        guard_conditions: Sequence[int] = (),
        timers: Sequence[int] = (),
        clients: Sequence[int] = (),
        services: Sequence[int] = (),
        events: Sequence[int] = (),
        notifier: Notifier | None = None,
        handoff: Handoff | None = None,
    ) -> None: ...
    def wait(self, timeout_ns: int, poll: bool = False, /) -> Ready: ...

class Token:
    """Whether work for one entity (or for a node itself) may still start.

    The dispatcher retires a token when its entity is destroyed or its node
    is removed from the executor; work already waiting in a lane is then
    dropped instead of run, as rclpy's executors drop it.
    """

    node: object
    retired: bool
    def __init__(self, node: object, retired: bool = False) -> None: ...

class Work:
    """One callback invocation waiting for, or running in, a lane."""

    #: The rclpy entity whose callback this is (identity only).
    entity: object
    #: Runs the callback with ``args``; returns a coroutine when ``is_async``.
    call: Callable[..., Any]
    is_async: bool
    #: How many waiting invocations of ``entity`` to keep.
    depth: int
    #: Told the outcome, in the thread or task that ran ``call``.
    done: Callable[[Work, BaseException | None], None]
    #: Whose work this is; once retired, the work never starts.
    token: Token | None
    #: What ``call`` is called with (a taken message).
    args: tuple[Any, ...]
    #: What its callback costs is told (``None``: not metered).
    meter: Meter | None
    #: When it arrived (monotonic ns: taken, or a timer's due time; 0 when not metered).
    arrived: int
    #: When its first step started (monotonic ns; 0: not yet, or not metered).
    started: int
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

    def take(self) -> tuple[int, int, int, int, int, int, int, int, int, int, int, int, int]:
        """``(runs, finished, busy_ns, cpu_ns, late_p50, late_p99, late_max, duration_p50,
        duration_p99, duration_max, dropped, stuck, running_ns)``: this window's, then a new one."""

def stuck_after(ns: int, /) -> None:
    """How long one step of a callback runs before its meter counts it stuck (every meter)."""

class Runner:
    """A runner task of a lane, the future it idles on, the context it runs in."""

    task: Any
    context: contextvars.Context
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
    """A lane's admission state; its methods are called with :attr:`lock` held."""

    lock: Lock
    limit: int
    running: int
    dropped: int
    closed: bool
    active: set[Work]
    idle_runners: list[Runner]
    waiting: int
    def __init__(self, limit: int) -> None: ...
    def admit(self, work: Work, /) -> bool: ...
    def next(self, finished: Work, /) -> Work | None: ...
    def close(self) -> None: ...
    def retire(self, node: object, /) -> list[Work]: ...
    def of(self, node: object, /) -> list[Work]: ...
    def busy(self) -> bool: ...

class Route:
    """What the async chain needs of one entity, resolved once per wait-set change."""

    first: Any
    entry: Any
    lane: Any
    slots: Slots
    marker: Work
    entity: Any
    token: Token
    callback: str
    def __init__(
        self, *, first: Any, entry: Any, lane: Any, slots: Slots, marker: Work, entity: Any, token: Token, callback: str
    ) -> None: ...

class Routes:
    """A wait set's current routes, and whether they are stale or closed."""

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
