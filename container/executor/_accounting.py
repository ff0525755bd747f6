"""What each node's callbacks cost inside the one process: the executor's accounting.

In a container, ``top`` shows one process. The executor knows, for every
callback it runs, the node and group it belongs to, when its work arrived
and when each step ran, so it can say which node eats the CPU and whose
callbacks are late, live, as no other executor does.

Each entity gets a compiled :class:`Meter` (``fastpath/meter.c``), timed where
its callbacks' steps run, on whichever path and thread: the loop's compiled
chain, the Python lanes, the workers' plain calls. A step costs two clock
reads; a thread's CPU clock is read only at the end of a step of 1 ms or
more and at the start of a step when its last read is 10 ms old, and
shorter steps are credited their wall time (see ``meter.c`` for how). :meth:`Accounting.sample`
closes a window: it takes every meter's figures and adds them up per callback
group, per node and for the container. Work the executor runs for no entity
(a lifecycle transition is metered as its node's; its own bookkeeping, the
middleware's threads) is the *executor's* share: the process's CPU time less
the callbacks'.
"""

from __future__ import annotations

import threading
import time
import weakref
from collections import defaultdict
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from rclpy.node import Node

from ._engine import Meter, stuck_after
from ._entries import describe

__all__ = ["Accounting", "CallbackLoad", "ContainerLoad", "GroupLoad", "NodeLoad"]

_NS = 1e-9


@dataclass(frozen=True, slots=True)
class CallbackLoad:
    """One callback's figures over a window. Times in seconds; ``cpu`` in cores (0.25: a quarter of one)."""

    node: str
    group: str
    #: ``subscription``, ``timer``, ``service``, ``client``, ``guard_condition``, ``waitable`` or ``transition``.
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
class ContainerLoad:
    """The process over a window, and every node in it (highest CPU first)."""

    #: Seconds the window covered.
    period: float
    #: The process's CPU time over the window, in cores (all its threads).
    cpu: float
    #: What the callbacks took of it.
    callbacks_cpu: float
    #: The rest: the executor's own work, the middleware's threads, anything outside a callback.
    executor_cpu: float
    #: The event loop's thread: its CPU, in cores, and the share of the window it was not on a CPU.
    loop_cpu: float
    loop_idle: float
    nodes: tuple[NodeLoad, ...]


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


def _reference(entity: object) -> Callable[[], object | None]:
    try:
        return weakref.ref(entity)
    except TypeError:
        return lambda: entity


class Accounting:
    """Every entity's meter, and the windows they are read in.

    Always on: a step costs two clock reads and a few additions (the
    executor benchmarks with it on stay within 3% of the same code with it
    off, see ``tests/benchmarks/bench_accounting.py``). Thread-safe: meters
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
        self._lock = threading.Lock()
        #: One window closes at a time (its totals are added up outside ``_lock``).
        self._sampling = threading.Lock()
        self._metered: dict[int, _Metered] = {}
        #: (node id, group id) -> (the group, its name), numbered per node as first seen.
        self._groups: dict[tuple[int, int], tuple[object, str]] = {}
        self._window_start = time.monotonic_ns()
        self._process_at = time.process_time_ns()
        self._loop_at: tuple[int, int] | None = None

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
            period_ns = max(1, now - self._window_start)
            process_ns = process - self._process_at
            self._window_start, self._process_at = now, process
            loop_cpu_ns = self._loop_cpu(now)
        callbacks = [self._figures(item, period_ns) for item in metered]
        nodes = _nodes(callbacks)
        callbacks_cpu = sum(node.cpu for node in nodes)
        cpu = process_ns / period_ns
        loop_cpu = loop_cpu_ns / period_ns if loop_cpu_ns is not None else 0.0
        return ContainerLoad(
            period=period_ns * _NS,
            cpu=cpu,
            callbacks_cpu=callbacks_cpu,
            executor_cpu=max(0.0, cpu - callbacks_cpu),
            loop_cpu=loop_cpu,
            loop_idle=max(0.0, 1.0 - loop_cpu) if loop_cpu_ns is not None else 0.0,
            nodes=nodes,
        )

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
        (runs, _, _, cpu_ns, late50, late99, late_max, dur50, dur99, dur_max, dropped, stuck, running) = (
            item.meter.take()
        )
        item.runs_total += runs
        item.cpu_ns_total += cpu_ns
        return CallbackLoad(
            node=item.node,
            group=item.group,
            kind=item.kind,
            name=item.name,
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
            runs_total=item.runs_total,
            cpu_seconds_total=item.cpu_ns_total * _NS,
        )


def _summed(members: list[CallbackLoad]) -> dict[str, Any]:
    """What a group and a node add up alike from their callbacks: sums, and the worst lateness and stuck time."""
    return {
        "cpu": sum(c.cpu for c in members),
        "rate": sum(c.rate for c in members),
        "lateness_p99": max(c.lateness_p99 for c in members),
        "dropped": sum(c.dropped for c in members),
        "stuck": sum(c.stuck for c in members),
        "stuck_for": max(c.stuck_for for c in members),
    }


def _nodes(callbacks: list[CallbackLoad]) -> tuple[NodeLoad, ...]:
    by_node: dict[str, list[CallbackLoad]] = defaultdict(list)
    for callback in callbacks:
        by_node[callback.node].append(callback)
    nodes = []
    for name, own in by_node.items():
        own.sort(key=lambda c: (-c.cpu, c.name))
        by_group: dict[str, list[CallbackLoad]] = defaultdict(list)
        for callback in own:
            by_group[callback.group].append(callback)
        groups = tuple(
            GroupLoad(node=name, name=group, **_summed(members)) for group, members in sorted(by_group.items())
        )
        nodes.append(
            NodeLoad(
                name=name,
                **_summed(own),
                duration_p99=max(c.duration_p99 for c in own),
                cpu_seconds_total=sum(c.cpu_seconds_total for c in own),
                groups=groups,
                callbacks=tuple(own),
            )
        )
    nodes.sort(key=lambda n: (-n.cpu, n.name))
    return tuple(nodes)

