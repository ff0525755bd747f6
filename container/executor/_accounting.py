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
from collections.abc import Callable, Collection, Iterable, Iterator
from dataclasses import dataclass
from typing import Final, NamedTuple

from rclpy.node import Node

from ._culprit import is_platform_node
from ._engine import Meter, stuck_after
from ._entries import describe
from ._owners import KINDS, OWNER, Account, Owner
from ._threads import ThreadLedger, ThreadShares, install

__all__ = ["Accounting", "CallbackLoad", "ContainerLoad", "GroupLoad", "NodeLoad", "UnattributedLoad"]

_NS = 1e-9


# A window's rows and loads are named tuples, as immutable as a frozen dataclass and built
# cheaper: 0.5 us for a callback's row of 17 fields against 3.5 us (a frozen dataclass sets each
# field with object.__setattr__), and a window of 500 busy nodes builds some 2,000 of them.


class CallbackLoad(NamedTuple):
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


class GroupLoad(NamedTuple):
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


class NodeLoad(NamedTuple):
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
        #: The same meters by node name, in the order each was first seen: a window walks them
        #: node by node. Each node's are a tuple, replaced when they change: a window copies the
        #: dict under ``_lock`` and reads the tuples outside it.
        self._by_node: dict[str, tuple[_Metered, ...]] = {}
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
        #: What each node's idle rows add to its load, as of the last window (``_Rows``).
        self._last_nodes: dict[str, _IdlePart] = {}

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
            if found is not None:  # a dead entity's id, reused
                self._by_node = _index(self._metered.values())
            else:
                self._by_node[metered.node] = (*self._by_node.get(metered.node, ()), metered)
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
            self._by_node = _index(self._metered.values())
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
            metered = dict(self._by_node)
            owners = dict(self._owners)
            period_ns = max(1, now - self._window_start)
            process_ns = process - self._process_at
            self._window_start, self._process_at = now, process
            loop_cpu_ns = self._loop_cpu(now)
        threads = self._threads.sample(loop_threads=self._loop_tids)
        last, self._last_nodes = self._last_nodes, {}
        nodes: list[NodeLoad] = []
        entities = on_threads = 0.0
        for name in metered.keys() | owners.keys():
            rows = _Rows(last.get(name))
            keep = rows.kept.append
            for item in metered.get(name, ()):
                figures = item.meter.take()
                row = item.idle
                if row is not None and figures == _IDLE:  # most rows, written out: no call
                    keep(row)
                else:
                    self._built(rows, item, figures, period_ns, item.group, item.kind, item.name)
            entities += sum(row.cpu for row in rows.built)
            owner = owners.get(name)
            if owner is not None:
                on_threads += self._owner_rows(owner, threads, period_ns, rows)
            load = rows.load(name)
            if load is not None and rows.idle is not None:
                nodes.append(load)
                self._last_nodes[name] = rows.idle
        nodes.sort(key=lambda n: (-n.cpu, n.name))
        loop_unattributed = {}
        for account in self.unattributed.accounts():
            rows = _Rows(None)
            self._take_account(rows, account, period_ns)
            loop_unattributed[_UNATTRIBUTED_LOOP[account.kind]] = sum(row.cpu for row in rows.built)
        self._forget_idle(owners.values(), threads, nodes, named=metered.keys())
        nodes_cpu = sum(node.cpu for node in nodes)
        # What the nodes' work took on the executor's threads and the loop's: theirs, not the executor's.
        on_executor = nodes_cpu - on_threads + sum(loop_unattributed.values())
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
            nodes=tuple(nodes),
            nodes_cpu=nodes_cpu,
            unattributed_cpu=sum(item.cpu for item in unattributed),
            unattributed=tuple(unattributed),
        )

    def _take(self, rows: _Rows, item: _Metered | Account, period_ns: int, group: str, kind: str, name: str) -> None:
        """Close ``item``'s window into ``rows``: a row built if anything of it ran, else its
        idle row (all zeros but its totals), kept from the first window it was idle in."""
        figures = item.meter.take()
        was: CallbackLoad | None = item.idle
        if was is not None and figures == _IDLE:
            rows.kept.append(was)
        else:
            self._built(rows, item, figures, period_ns, group, kind, name)

    def _take_account(self, rows: _Rows, account: Account, period_ns: int) -> None:
        """:meth:`_take` for one kind of a node's other work (or of nobody's)."""
        self._take(rows, account, period_ns, KINDS[account.kind][0], account.kind, account.name)

    def _built(
        self, rows: _Rows, item: _Metered | Account, figures: tuple[int, ...], period_ns: int,
        group: str, kind: str, name: str,
    ) -> None:  # fmt: skip
        """Build ``item``'s row from its meter's ``figures``, its totals carried on: a window in
        which something of it ran, or the first it was idle in (that row is then kept, and given
        again for each idle window after it)."""
        (runs, _, _, cpu_ns, late50, late99, late_max, dur50, dur99, dur_max, dropped, stuck, running) = figures
        runs_total = item.runs_total = item.runs_total + runs
        cpu_ns_total = item.cpu_ns_total = item.cpu_ns_total + cpu_ns
        row = CallbackLoad(  # CallbackLoad's fields, in order
            item.node if isinstance(item, _Metered) else item.owner.name, group, kind, name,
            cpu_ns / period_ns, runs / (period_ns * _NS),
            late50 * _NS, late99 * _NS, late_max * _NS, dur50 * _NS, dur99 * _NS, dur_max * _NS,
            dropped, stuck, running * _NS if running >= self._stuck_after_ns else 0.0, runs_total, cpu_ns_total * _NS,
        )  # fmt: skip
        if figures != _IDLE:
            item.idle = None
            rows.built.append(row)
        else:
            item.idle = row
            rows.kept.append(row)

    def _owner_rows(self, owner: Owner, threads: ThreadShares, period_ns: int, rows: _Rows) -> float:
        """Add a node's other work to its ``rows``, one row per kind it used, and its threads' row
        while it has any; returns what its threads took (in cores)."""
        spent = threads.owners.get(owner, 0)
        running = threads.running.get(owner, 0)
        threads_row = bool(spent or running)
        for account in owner.accounts():
            # Its threads' own row replaces the thread account's.
            self._take_account(_Rows(None) if threads_row and account.kind == "thread" else rows, account, period_ns)
        if not threads_row:
            return 0.0
        thread_account = owner.account("thread")
        thread_account.cpu_ns_total += spent
        rows.built.append(
            _row(
                thread_account,
                name=f"threads it started ({running} running)",
                cpu=spent / period_ns,
                cpu_seconds_total=thread_account.cpu_ns_total * _NS,
            )
        )
        return spent / period_ns

    def _forget_idle(
        self, owners: Iterable[Owner], threads: ThreadShares, nodes: list[NodeLoad], *, named: Collection[str]
    ) -> None:
        """Drop the owners of nodes gone: nothing of theirs ran, runs or lives, and no callback of
        their node is metered any more (``named``: a node unloaded, its threads ended)."""
        busy = {node.name for node in nodes if node.rate > 0 or node.cpu > 0 or node.stuck_for > 0}
        gone = [
            owner for owner in owners
            if owner.name not in busy and owner.name not in named and not threads.running.get(owner)
        ]  # fmt: skip
        if not gone:
            return
        with self._lock:
            for owner in gone:
                if self._owners.get(owner.name) is owner:
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


def _summed(members: list[CallbackLoad]) -> tuple[float, float, float, int, int, float]:
    """What a group and a node add up alike from their callbacks: sums, and the worst lateness and stuck
    time (GroupLoad's order of fields)."""
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
    return cpu, rate, lateness_p99, dropped, stuck, stuck_for


def _index(metered: Iterable[_Metered]) -> dict[str, tuple[_Metered, ...]]:
    """``metered`` by node name, each node's in the order given."""
    by_node: dict[str, list[_Metered]] = defaultdict(list)
    for item in metered:
        by_node[item.node].append(item)
    return {node: tuple(items) for node, items in by_node.items()}


class _IdlePart:
    """What a node's idle rows add to its load (nothing to its sums and maxima: they are all
    zeros but their totals), worked out again only when they change."""

    __slots__ = ("groups", "kept", "load", "names", "rows", "total")

    def __init__(self, node: str, kept: list[CallbackLoad]) -> None:
        #: The rows, in the order taken (not changed after).
        self.kept = kept
        #: The same, in a node's order of callbacks (all without CPU: by name).
        self.rows = tuple(sorted(kept, key=_order))
        #: A load of zeros for each of their groups, and the groups' names in order.
        zero = (0.0, 0.0, 0.0, 0, 0, 0.0)
        self.groups = {row.group: GroupLoad(node, row.group, *zero) for row in kept}
        self.names = sorted(self.groups)
        self.total = sum(row.cpu_seconds_total for row in kept)
        #: The node's load of the last window in which nothing of it ran.
        self.load: NodeLoad | None = None


class _Rows:
    """One node's rows of a window, as its meters are taken: those of work that ran, and the
    idle ones kept; and its load from them.

    A window costs what ran, not every row of a large container: only the
    rows built this window are summed, and what the idle ones add is
    worked out again only when they change (a row joined or left them). A
    node none of whose work ran gets its last such load again.

    :param idle: the node's idle part of the last window (``None``: none).
    """

    __slots__ = ("built", "idle", "kept")

    def __init__(self, idle: _IdlePart | None) -> None:
        self.built: list[CallbackLoad] = []
        self.kept: list[CallbackLoad] = []
        self.idle = idle

    def load(self, node: str) -> NodeLoad | None:
        """The node's load (``None``: it has no rows); its idle part is then :attr:`idle`."""
        built, kept = self.built, self.kept
        if not built and not kept:
            return None
        idle = self.idle
        # The same row objects, mostly: a list's comparison tells them by identity first.
        if idle is None or kept != idle.kept:
            idle = self.idle = _IdlePart(node, kept)
        elif not built and idle.load is not None:
            return idle.load
        load = _node_load(node, built, idle)
        if not built:
            idle.load = load
        return load


def _order(row: CallbackLoad) -> tuple[float, str]:
    return -row.cpu, row.name


def _node_load(name: str, built: list[CallbackLoad], idle: _IdlePart) -> NodeLoad:
    """A node's load: its rows built this window summed, by group and in all, beside its idle part."""
    if len(built) > 1:
        built.sort(key=_order)
    if built and built[-1].cpu <= 0.0 and idle.rows:
        callbacks = tuple(sorted([*built, *idle.rows], key=_order))  # rows of no CPU interleave by name
    else:
        callbacks = (*built, *idle.rows)
    sums = _summed(built)
    by_group: dict[str, list[CallbackLoad]] = {}
    for c in built:
        by_group.setdefault(c.group, []).append(c)
    groups = idle.groups
    names = idle.names
    if by_group:
        groups = dict(groups)
        for group, members in by_group.items():
            # One group ran (most nodes): its sums are the node's.
            groups[group] = GroupLoad(name, group, *(sums if len(by_group) == 1 else _summed(members)))
        if len(groups) != len(names):
            names = sorted(groups)
    cpu, rate, lateness_p99, dropped, stuck, stuck_for = sums
    return NodeLoad(  # NodeLoad's fields, in order
        name, cpu, rate, lateness_p99, max((c.duration_p99 for c in built), default=0.0), dropped, stuck, stuck_for,
        idle.total + sum(c.cpu_seconds_total for c in built),
        tuple(groups[group] for group in names), callbacks,
    )  # fmt: skip
