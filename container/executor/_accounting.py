"""What each node costs inside the one process: the executor's accounting.

In a container, ``top`` shows one process. The executor knows, for every
callback it runs, the node and group it belongs to, when its work arrived
and when each step ran; and for the rest of what a node runs (its asyncio
tasks, the loop callbacks and timers it schedules, the file descriptors it
reads, the threads it starts) whose it is, from the node's mark in the
context that work was started in (``_owners``). So it can say which node
eats the CPU and whose work is late or stuck, live, as no other executor
does.

Each entity gets a compiled :class:`Meter` (``fastpath/meter.c``), timed where
its callbacks' steps run, on whichever path and thread: the loop's compiled
chain, the Python lanes, the workers' plain calls. A step costs two clock
reads; a thread's CPU clock is read only at the end of a step of 1 ms or
more and at the start of a step when its last read is 10 ms old, and
shorter steps are credited their wall time (see ``meter.c`` for how). Each
node's other work is metered alike, one meter per kind (its
:class:`~._owners.Owner`'s accounts: the task factory times each step of its
tasks, the loop each of its handles, ``_loop``), and its threads are read
through their own CPU clocks (``_threads``).

:meth:`Accounting.sample` closes a window: it takes every meter's figures and
adds them up per callback group, per node and for the container. What the
executor spent is its own threads' and its loop thread's CPU, less what the
nodes' work took on them; what nobody's work took (loop work scheduled where
no node's code ran, threads started outside any node, the middleware's and
other native threads) is shown as unattributed, by kind.
"""

from __future__ import annotations

import contextlib
import threading
import time
import weakref
from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any, Final

from rclpy.node import Node

from ._culprit import is_platform_node
from ._engine import Meter, stuck_after
from ._entries import describe
from ._owners import KINDS, OWNER, Account, Owner
from ._threads import ThreadLedger, ThreadShares, install

__all__ = ["Accounting", "CallbackLoad", "ContainerLoad", "GroupLoad", "NodeLoad", "UnattributedLoad"]

_NS = 1e-9


@dataclass(frozen=True, slots=True)
class CallbackLoad:
    """One callback's figures over a window. Times in seconds; ``cpu`` in cores (0.25: a quarter of one)."""

    node: str
    #: The callback group (``default``, ``Reentrant 1``), or ``asyncio`` and ``threads`` for the
    #: node's other work.
    group: str
    #: ``subscription``, ``timer``, ``service``, ``client``, ``guard_condition``, ``waitable`` or
    #: ``transition``; for a node's other work ``task``, ``loop_callback``, ``loop_timer``, ``fd``,
    #: ``thread_call`` or ``thread`` (see ``_owners.KINDS``).
    kind: str
    #: How a ROS user recognises it: ``subscription '/scan' callback on_scan``.
    name: str
    cpu: float
    #: Callbacks started per second.
    rate: float
    #: From its work's arrival (a message taken, a timer's due time) to its start.
    lateness_p50: float
    lateness_p99: float
    lateness_max: float
    #: From its start to its end (an ``async def`` callback's awaits included).
    duration_p50: float
    duration_p99: float
    duration_max: float
    #: Waiting invocations dropped for newer ones (keep-last, while its group was busy).
    dropped: int
    #: Steps that ran for ``stuck_after`` or more, counted once each, in the window.
    stuck: int
    #: How long its step running now has run, if that is ``stuck_after`` or more; else 0.
    stuck_for: float
    #: Since the executor first saw it.
    runs_total: int
    cpu_seconds_total: float


@dataclass(frozen=True, slots=True)
class GroupLoad:
    """One callback group's figures: its callbacks' sums, and their worst lateness."""

    node: str
    #: ``default`` (the node's default group), else its kind and a number, per node in the order seen.
    name: str
    cpu: float
    rate: float
    lateness_p99: float
    dropped: int
    stuck: int
    stuck_for: float


@dataclass(frozen=True, slots=True)
class NodeLoad:
    """One node's figures: its callbacks' sums, their worst lateness and duration, and each part."""

    name: str
    cpu: float
    rate: float
    #: The highest of its callbacks' p99 (the node's worst callback, not a pooled p99).
    lateness_p99: float
    duration_p99: float
    dropped: int
    stuck: int
    stuck_for: float
    cpu_seconds_total: float
    groups: tuple[GroupLoad, ...]
    callbacks: tuple[CallbackLoad, ...]


@dataclass(frozen=True, slots=True)
class UnattributedLoad:
    """CPU no node's work and not the executor took, of one kind (in cores)."""

    #: ``tasks``, ``loop callbacks``, ``loop timers``, ``file descriptors``, ``calls on threads``
    #: (loop work scheduled where no node's code ran), ``python threads`` (started outside any
    #: node), ``middleware threads`` (Fast DDS's) or ``native threads`` (other C and C++ threads).
    kind: str
    cpu: float


@dataclass(frozen=True, slots=True)
class ContainerLoad:
    """The process over a window, and every node in it (highest CPU first)."""

    #: Seconds the window covered.
    period: float
    #: The process's CPU time over the window, in cores (all its threads).
    cpu: float
    #: What the nodes' callbacks (and transitions) took of it.
    callbacks_cpu: float
    #: What the executor spent: its loop's thread and its own threads, less the nodes' work on them.
    executor_cpu: float
    #: The event loop's thread: its CPU, in cores, and the share of the window it was not on a CPU.
    loop_cpu: float
    loop_idle: float
    nodes: tuple[NodeLoad, ...]
    #: Everything the nodes ran: callbacks, tasks, loop callbacks and timers, readers, threads.
    nodes_cpu: float = 0.0
    #: What no node's work took, nor the executor: the sum of ``unattributed``.
    unattributed_cpu: float = 0.0
    unattributed: tuple[UnattributedLoad, ...] = ()


@dataclass(slots=True)
class _Metered:
    entity: Callable[[], object | None]
    node: str
    group: str
    kind: str
    name: str
    meter: Meter
    runs_total: int = 0
    cpu_ns_total: int = 0
    #: Its row of the last window, kept while nothing of it ran (see :data:`_IDLE`).
    idle: CallbackLoad | None = None


def _reference(entity: object) -> Callable[[], object | None]:
    try:
        return weakref.ref(entity)
    except TypeError:
        return lambda: entity


#: How the unattributed kinds of loop work are shown (by the owner's kinds).
_UNATTRIBUTED_LOOP = {
    "task": "tasks",
    "loop_callback": "loop callbacks",
    "loop_timer": "loop timers",
    "fd": "file descriptors",
    "thread_call": "calls on threads",
}
#: A meter's figures over a window in which nothing of its ran, nothing was dropped and
#: nothing runs (``Meter.take``): its row is all zeros but for its totals, which did not move.
_IDLE: Final = (0,) * 13
#: Kinds of a node's work that are handles on the loop.
_LOOP_HANDLES = frozenset({"loop_callback", "loop_timer", "fd"})


class Accounting:
    """Every entity's meter, every node's other work, and the windows they are read in.

    Always on: a step costs two clock reads and a few additions (its budget
    is 3% of the work; what it costs on each measure, side by side with the
    same code with it off: ``tests/benchmarks/bench_accounting.py``, and
    ``docs/benchmarks.md``). Thread-safe: meters
    are handed out under a lock and read with the GIL held, as they are
    written.

    :param loop_thread: the ident of the event loop's thread, or ``None``
        while nobody spins (its CPU is then not reported).
    :param stuck_after_s: seconds one step of a callback runs before it counts
        as stuck (the loop watchdog's threshold by default).
    """

    def __init__(self, *, loop_thread: Callable[[], int | None], stuck_after_s: float = 1.0) -> None:
        if stuck_after_s <= 0:
            raise ValueError(f"stuck_after_s must be positive, not {stuck_after_s}")
        self._loop_thread = loop_thread
        self._stuck_after_ns = int(stuck_after_s * 1e9)
        stuck_after(self._stuck_after_ns)  # process-wide: the meters are the compiled module's
        install()  # threads a node starts are noted from now on (once per process)
        self._lock = threading.Lock()
        #: One window closes at a time (its totals are added up outside ``_lock``).
        self._sampling = threading.Lock()
        self._metered: dict[int, _Metered] = {}
        #: (node id, group id) -> (the group, its name), numbered per node as first seen.
        self._groups: dict[tuple[int, int], tuple[object, str]] = {}
        #: Each node's other work, by the node's full name.
        self._owners: dict[str, Owner] = {}
        self._threads = ThreadLedger()
        #: Work nobody's context names, metered by kind alike.
        self.unattributed = self._new_owner("", plugin=False)
        #: Native ids of the threads that ran the loop (the latest kept after its spin ends).
        self._loop_tids: frozenset[int] = frozenset()
        self._window_start = time.monotonic_ns()
        self._process_at = time.process_time_ns()
        self._loop_at: tuple[int, int] | None = None
        #: Each node's rows and load of the last window (``_nodes``).
        self._last_nodes: dict[str, tuple[tuple[int, ...], NodeLoad]] = {}

    def _new_owner(self, name: str, *, plugin: bool) -> Owner:
        return Owner(name, plugin=plugin, new_meter=Meter, thread_ended=self._threads.ended)

    def owner(self, node: Node) -> Owner:
        """The owner of ``node``'s work beside its callbacks: the same one for as long as its name stays."""
        return self.owner_named(node.get_fully_qualified_name(), plugin=not is_platform_node(node))

    def owner_named(self, name: str, *, plugin: bool = True) -> Owner:
        """The owner of the node named ``name`` (fully qualified), which may not exist yet:
        what its constructor starts is its own."""
        with self._lock:
            found = self._owners.get(name)
            if found is None:
                found = self._owners[name] = self._new_owner(name, plugin=plugin)
            elif not plugin:
                found.plugin = False
            return found

    @contextlib.contextmanager
    def working_as(self, name: str) -> Iterator[None]:
        """Count what this block starts (a task, and through it a node's constructor on its
        thread, and the threads that starts) as the node named ``name``'s, which may not
        exist yet (see :meth:`owner_named`)."""
        reset = OWNER.set(self.owner_named(name))
        try:
            yield
        finally:
            OWNER.reset(reset)

    def running_on_loop(self) -> Account | None:
        """The account whose loop handle (a reader, a loop callback or timer) runs now, if one does:
        for the watchdog, which asks while that handle holds the loop."""
        with self._lock:
            owners = [*self._owners.values(), self.unattributed]
        for owner in owners:
            for account in owner.accounts():
                if account.kind in _LOOP_HANDLES and account.meter.running > 0:
                    return account
        return None

    def loop_started(self) -> None:
        """The calling thread runs the loop from now on (its CPU is the executor's)."""
        self._loop_tids = frozenset({threading.get_native_id()})

    def meter(self, entity: object, node: Node, kind: str) -> Meter:
        """The meter of ``entity`` of ``node``: the same one for as long as the entity stays."""
        key = id(entity)
        with self._lock:
            found = self._metered.get(key)
            if found is not None and found.entity() is entity:
                return found.meter
            group = getattr(entity, "callback_group", None)
            metered = _Metered(
                entity=_reference(entity),
                node=node.get_fully_qualified_name(),
                group=self._group_name(node, group),
                kind=kind,
                name="lifecycle transitions" if kind == "transition" else describe(entity),
                meter=Meter(),
            )
            self._metered[key] = metered
            return metered.meter

    def _group_name(self, node: Node, group: object) -> str:
        """``default``, or the group's kind and how many groups of ``node`` were seen before it."""
        if group is None or group is node.default_callback_group:
            return "default"
        key = (id(node), id(group))
        found = self._groups.get(key)
        if found is not None and found[0] is group:
            return found[1]
        index = 1 + sum(1 for (node_id, _) in self._groups if node_id == id(node))
        name = f"{type(group).__name__.removesuffix('CallbackGroup')} {index}"
        self._groups[key] = (group, name)
        return name

    def forget(self, live: Iterable[int]) -> None:
        """Drop the meters of entities (by id) not in ``live``: they left the executor."""
        keep = set(live)
        with self._lock:
            for key in [key for key, metered in self._metered.items() if key not in keep or metered.entity() is None]:
                del self._metered[key]
            for pair in [pair for pair in self._groups if pair[0] not in keep]:
                del self._groups[pair]

    def sample(self) -> ContainerLoad:
        """Close the window: every callback's figures since the last sample, summed up.

        Each call closes a window for every reader: in a container the
        ``~/load`` reporter is the one that does (``container._load``).
        """
        with self._sampling:
            return self._sample()

    def _sample(self) -> ContainerLoad:
        now = time.monotonic_ns()
        process = time.process_time_ns()
        with self._lock:
            metered = list(self._metered.values())
            owners = list(self._owners.values())
            period_ns = max(1, now - self._window_start)
            process_ns = process - self._process_at
            self._window_start, self._process_at = now, process
            loop_cpu_ns = self._loop_cpu(now)
        threads = self._threads.sample(loop_threads=self._loop_tids)
        callbacks = [self._figures(item, period_ns) for item in metered]
        entities = sum(c.cpu for c in callbacks)
        for owner in owners:
            callbacks += self._owner_rows(owner, threads, period_ns)
        loop_unattributed = {
            _UNATTRIBUTED_LOOP[account.kind]: self._account_figures(account, period_ns).cpu
            for account in self.unattributed.accounts()
        }
        self._forget_idle(owners, threads, callbacks)
        nodes = _nodes(callbacks, self._last_nodes)
        nodes_cpu = sum(node.cpu for node in nodes)
        # What the nodes' work took on the executor's threads and the loop's: theirs, not the executor's.
        on_executor = sum(c.cpu for c in callbacks if c.kind != "thread") + sum(loop_unattributed.values())
        unattributed = [UnattributedLoad(kind, cpu) for kind, cpu in sorted(loop_unattributed.items())] + [
            UnattributedLoad(kind, spent / period_ns) for kind, spent in threads.unattributed.items()
        ]
        cpu = process_ns / period_ns
        loop_cpu = loop_cpu_ns / period_ns if loop_cpu_ns is not None else 0.0
        return ContainerLoad(
            period=period_ns * _NS,
            cpu=cpu,
            callbacks_cpu=entities,
            executor_cpu=max(0.0, threads.executor / period_ns - on_executor),
            loop_cpu=loop_cpu,
            loop_idle=max(0.0, 1.0 - loop_cpu) if loop_cpu_ns is not None else 0.0,
            nodes=nodes,
            nodes_cpu=nodes_cpu,
            unattributed_cpu=sum(item.cpu for item in unattributed),
            unattributed=tuple(unattributed),
        )

    def _owner_rows(self, owner: Owner, threads: ThreadShares, period_ns: int) -> list[CallbackLoad]:
        """A node's other work, one row per kind it used; its threads' row while it has any."""
        rows = [self._account_figures(account, period_ns) for account in owner.accounts()]
        spent = threads.owners.get(owner, 0)
        running = threads.running.get(owner, 0)
        if spent or running:
            thread_account = owner.account("thread")
            thread_account.cpu_ns_total += spent
            rows = [row for row in rows if row.kind != "thread"]
            rows.append(
                _row(
                    thread_account,
                    name=f"threads it started ({running} running)",
                    cpu=spent / period_ns,
                    cpu_seconds_total=thread_account.cpu_ns_total * _NS,
                )
            )
        return rows

    def _forget_idle(self, owners: list[Owner], threads: ThreadShares, rows: list[CallbackLoad]) -> None:
        """Drop the owners of nodes gone: nothing of theirs ran, runs or lives, and no callback of
        their node is metered any more (a node unloaded, its threads ended)."""
        busy = {row.node for row in rows if row.rate > 0 or row.cpu > 0 or row.stuck_for > 0}
        with self._lock:
            named = {item.node for item in self._metered.values()}
            for owner in owners:
                idle = owner.name not in busy and owner.name not in named and not threads.running.get(owner)
                if idle and self._owners.get(owner.name) is owner:
                    del self._owners[owner.name]

    def _loop_cpu(self, now: int) -> int | None:
        """The loop thread's CPU time since the last sample (``None``: unknown)."""
        ident = self._loop_thread()
        if ident is None:
            self._loop_at = None
            return None
        try:
            cpu = time.clock_gettime_ns(time.pthread_getcpuclockid(ident))
        except (OSError, AttributeError):
            return None
        last, self._loop_at = self._loop_at, (ident, cpu)
        if last is None or last[0] != ident:
            return None
        return cpu - last[1]

    def _figures(self, item: _Metered, period_ns: int) -> CallbackLoad:
        return self._window_row(item, period_ns, node=item.node, group=item.group, kind=item.kind, name=item.name)

    def _account_figures(self, account: Account, period_ns: int) -> CallbackLoad:
        return self._window_row(
            account, period_ns, node=account.owner.name, group=KINDS[account.kind][0], kind=account.kind,
            name=account.name,
        )  # fmt: skip

    def _window_row(
        self, item: _Metered | Account, period_ns: int, *, node: str, group: str, kind: str, name: str
    ) -> CallbackLoad:
        """The window's row of ``item`` (an entity's or a node's other work), its totals carried on.

        Most rows of a container are idle (a node's parameter services): a
        window in which nothing of one ran gives the row the last such window
        gave, not a new one."""
        figures = item.meter.take()
        if figures == _IDLE and item.idle is not None:
            idle: CallbackLoad = item.idle
            return idle
        item.runs_total += figures[0]
        item.cpu_ns_total += figures[3]
        row = self._load(
            figures, period_ns, node=node, group=group, kind=kind, name=name,
            runs_total=item.runs_total, cpu_ns_total=item.cpu_ns_total,
        )  # fmt: skip
        item.idle = row if figures == _IDLE else None
        return row

    def _load(
        self,
        figures: tuple[int, ...],
        period_ns: int,
        *,
        node: str,
        group: str,
        kind: str,
        name: str,
        runs_total: int,
        cpu_ns_total: int,
    ) -> CallbackLoad:
        (runs, _, _, cpu_ns, late50, late99, late_max, dur50, dur99, dur_max, dropped, stuck, running) = figures
        return CallbackLoad(
            node=node,
            group=group,
            kind=kind,
            name=name,
            cpu=cpu_ns / period_ns,
            rate=runs / (period_ns * _NS),
            lateness_p50=late50 * _NS,
            lateness_p99=late99 * _NS,
            lateness_max=late_max * _NS,
            duration_p50=dur50 * _NS,
            duration_p99=dur99 * _NS,
            duration_max=dur_max * _NS,
            dropped=dropped,
            stuck=stuck,
            stuck_for=running * _NS if running >= self._stuck_after_ns else 0.0,
            runs_total=runs_total,
            cpu_seconds_total=cpu_ns_total * _NS,
        )


def _row(account: Account, *, name: str, cpu: float, cpu_seconds_total: float) -> CallbackLoad:
    """A row of CPU alone (a node's threads): no runs, no lateness, nothing stuck."""
    return CallbackLoad(
        node=account.owner.name,
        group=KINDS[account.kind][0],
        kind=account.kind,
        name=name,
        cpu=cpu,
        rate=0.0,
        lateness_p50=0.0,
        lateness_p99=0.0,
        lateness_max=0.0,
        duration_p50=0.0,
        duration_p99=0.0,
        duration_max=0.0,
        dropped=0,
        stuck=0,
        stuck_for=0.0,
        runs_total=0,
        cpu_seconds_total=cpu_seconds_total,
    )


def _summed(members: list[CallbackLoad]) -> dict[str, Any]:
    """What a group and a node add up alike from their callbacks: sums, and the worst lateness and stuck time."""
    # One pass, not one generator per figure: a sample adds up every group and node each second.
    cpu = rate = lateness_p99 = stuck_for = 0.0
    dropped = stuck = 0
    for c in members:
        cpu += c.cpu
        rate += c.rate
        dropped += c.dropped
        stuck += c.stuck
        if c.lateness_p99 > lateness_p99:
            lateness_p99 = c.lateness_p99
        if c.stuck_for > stuck_for:
            stuck_for = c.stuck_for
    return {
        "cpu": cpu,
        "rate": rate,
        "lateness_p99": lateness_p99,
        "dropped": dropped,
        "stuck": stuck,
        "stuck_for": stuck_for,
    }


def _nodes(callbacks: list[CallbackLoad], last: dict[str, tuple[tuple[int, ...], NodeLoad]]) -> tuple[NodeLoad, ...]:
    """Every node's load, its callbacks' rows summed by group and by node.

    :param last: each node's rows (by identity) and load of the previous
        window, updated: a node whose rows are all the same objects (all
        idle, each reusing its last idle row) gets the same load again, so a
        window costs what ran, not every node of a large container. The rows
        a load holds stay alive, so their ids are not reused meanwhile.
    """
    by_node: dict[str, list[CallbackLoad]] = defaultdict(list)
    for callback in callbacks:
        by_node[callback.node].append(callback)
    nodes = []
    for gone in [name for name in last if name not in by_node]:
        del last[gone]
    for name, own in by_node.items():
        rows = tuple(map(id, own))
        cached = last.get(name)
        if cached is not None and cached[0] == rows:
            nodes.append(cached[1])
            continue
        own.sort(key=lambda c: (-c.cpu, c.name))
        by_group: dict[str, list[CallbackLoad]] = defaultdict(list)
        for callback in own:
            by_group[callback.group].append(callback)
        groups = tuple(
            GroupLoad(node=name, name=group, **_summed(members)) for group, members in sorted(by_group.items())
        )
        load = NodeLoad(
            name=name,
            **_summed(own),
            duration_p99=max(c.duration_p99 for c in own),
            cpu_seconds_total=sum(c.cpu_seconds_total for c in own),
            groups=groups,
            callbacks=tuple(own),
        )
        last[name] = (rows, load)
        nodes.append(load)
    nodes.sort(key=lambda n: (-n.cpu, n.name))
    return tuple(nodes)

