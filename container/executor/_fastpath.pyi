"""Type stub of the ``_fastpath`` extension (``_fastpath.c``)."""

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

def poll(wait_set: int, timeout_ns: int, /) -> None:
    """``rcl_wait`` on rclpy's wait set at that address (its ``pointer``),
    keeping the GIL: for a wait whose guard condition is already triggered."""

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
    ) -> None: ...
    def wait(self, timeout_ns: int, poll: bool = False, /) -> Ready: ...

class Express:
    def __init__(
        self,
        *,
        notifier: Notifier,
        waitset: object,
        take_lock: object,
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
        cancelled_error: type[BaseException],
    ) -> None: ...
    def drain(self, deadline_ns: int, /) -> bool: ...
    def call_timers(self, routes: Mapping[int, tuple[Any, ...]], ready: Iterable[int], /) -> list[int]: ...
    def run_fired(self) -> None: ...
    @property
    def expressed(self) -> int: ...
