"""``container top``: which node of a container eats the CPU, whose callbacks are late.

Every container publishes its nodes' load on ``<container>/load``
(``lifecycle_container_interfaces/msg/ContainerLoad``, see ``container._load``)
while something subscribes; this command subscribes to every such topic on
the domain (or one container's) and shows the latest window, like ``top``:

* live (the default, on a terminal): nodes sorted by CPU; keys sort by
  another column, move the selection, open a node's callbacks;
* ``--once``: one plain table per container, for scripts and tests; also
  what ``top`` does when its output is not a terminal (``container top |
  head``): a live view off a terminal would print nothing until it is
  stopped, and a pipe's reader would wait for it forever;
* ``--json``: the same windows as one JSON document (one, never one per
  refresh: ``json.loads`` reads all of it).

Without the ros2 daemon, containers are found by polling the graph, as the
other commands do.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import json
import os
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from ._types import positive_seconds

if TYPE_CHECKING:
    from lifecycle_container_interfaces.msg import CallbackLoad, ContainerLoad, NodeLoad
    from rclpy.node import Node
    from rich.console import RenderableType

    from .._compat import SubParsers

__all__ = ["History", "add_parser", "as_dict", "plain_table", "short_name"]

#: The load message's type, as the graph names it.
LOAD_TYPE = "lifecycle_container_interfaces/msg/ContainerLoad"
#: Interval between two looks at the graph for containers.
_DISCOVER_S = 0.1
#: Once every container found has reported, ``--once`` waits this long for more to appear.
_SETTLE_S = 0.5

#: Sort keys: key -> (the column sorted by, None for the first; how to sort nodes and callbacks).
_SORTS: dict[str, tuple[str | None, Callable[[Any], Any]]] = {
    "c": ("CPU%", lambda item: -item.cpu),
    "r": ("CB/S", lambda item: -item.rate),
    "l": ("LATE_P99_MS", lambda item: -item.lateness_p99),
    "d": ("DUR_P99_MS", lambda item: -item.duration_p99),
    "n": (None, lambda item: item.name),
}
_SORT_NAMES = {"cpu": "c", "rate": "r", "lateness": "l", "duration": "d", "name": "n"}


def add_parser(subparsers: SubParsers) -> None:
    """Register ``top``."""
    top = subparsers.add_parser(
        "top",
        help="show what each node of a container costs, live",
        description=(
            "Show each node's CPU, callbacks per second, lateness and stuck callbacks, for every "
            "container on the ROS domain (or one), from the load each container publishes."
        ),
    )
    top.add_argument("container", nargs="?", default=None, help="one container node's full name (default: all)")
    top.add_argument(
        "--once", action="store_true",
        help="print one plain table per container and exit (the default when output is not a terminal)",
    )
    top.add_argument("--json", action="store_true", help="print one JSON document of every container and exit")
    top.add_argument(
        "--node", default=None, help="with --once: that node's callbacks too (its full name)"
    )
    top.add_argument(
        "--sort", choices=sorted(_SORT_NAMES), default="cpu", help="what to sort nodes by (default: cpu)"
    )
    top.add_argument(
        "--timeout", type=positive_seconds, default=5.0,
        help="with --once or --json: seconds to wait for the first report (default: 5)",
    )
    top.set_defaults(handler=_run)


#: Seconds of each node's CPU the live view draws, and in how many characters.
HISTORY_S = 60.0
SPARK_WIDTH = 30
_SPARKS = " ▁▂▃▄▅▆▇█"


class History:
    """Each node's CPU over the last :data:`HISTORY_S` seconds, per container, drawn as a sparkline."""

    def __init__(self) -> None:
        self._cpu: dict[tuple[str, str], collections.deque[tuple[float, float]]] = {}

    def add(self, load: ContainerLoad, now: float) -> None:
        for node in load.nodes:
            seen = self._cpu.setdefault((load.container, node.name), collections.deque())
            seen.append((now, node.cpu))
            while seen and seen[0][0] < now - HISTORY_S:
                seen.popleft()

    def peak(self, container: str) -> float:
        """The highest CPU of any node of ``container`` in the last minute (the lines' common scale)."""
        return max(
            (cpu for (name, _), seen in self._cpu.items() if name == container for _, cpu in seen), default=0.0
        )

    def spark(self, container: str, node: str, now: float, *, scale: float, width: int = SPARK_WIDTH) -> str:
        """``width`` characters, the oldest first, each the highest CPU of its share of the minute,
        ``scale`` cores a full block (at least 1% of a core: an idle node stays at the bottom)."""
        slots: list[float | None] = [None] * width
        slot_s = HISTORY_S / width
        for at, cpu in self._cpu.get((container, node), ()):
            index = width - 1 - int((now - at) / slot_s)
            if 0 <= index < width:
                slots[index] = max(cpu, slots[index] or 0.0)
        top = max(scale, 0.01)
        return "".join(
            " " if cpu is None else _SPARKS[1 + min(7, int(cpu / top * 7.999))] for cpu in slots
        )


@dataclass
class _Reports:
    """The latest window of each container heard from, and the subscriptions bringing them."""

    node: Node
    only: str | None
    latest: dict[str, ContainerLoad] = field(default_factory=dict)
    history: History = field(default_factory=History)
    heard: float = 0.0
    _subscribed: dict[str, Any] = field(default_factory=dict)
    changed: asyncio.Event = field(default_factory=asyncio.Event)

    def discover(self) -> None:
        from lifecycle_container_interfaces.msg import ContainerLoad
        from rclpy.qos import QoSProfile

        for topic, types in self.node.get_topic_names_and_types():
            if LOAD_TYPE not in types or topic in self._subscribed:
                continue
            if self.only is not None and topic != f"{self.only.rstrip('/')}/load":
                continue
            self._subscribed[topic] = self.node.create_subscription(
                ContainerLoad, topic, self._heard, QoSProfile(depth=5)
            )

    def _heard(self, message: ContainerLoad) -> None:
        self.latest[message.container] = message
        self.heard = time.monotonic()
        self.history.add(message, self.heard)
        self.changed.set()

    @property
    def topics(self) -> int:
        return len(self._subscribed)

    def loads(self) -> list[ContainerLoad]:
        """The latest window of each container heard from, by container name."""
        return [self.latest[name] for name in sorted(self.latest)]


def _run(args: argparse.Namespace) -> int:
    from .._session import Session, run_session

    container = args.container
    if container is not None and not container.startswith("/"):
        container = f"/{container}"

    async def run(session: Session) -> int:
        with session.client_node(f"_container_top_{os.getpid()}") as node:
            reports = _Reports(node, container)
            if args.once or args.json or not sys.stdout.isatty():
                return await _once(reports, args)
            return await _live(reports, args, session.stopping)

    return run_session(run, ros_args=getattr(args, "ros_args", ()))


async def _once(reports: _Reports, args: argparse.Namespace) -> int:
    deadline = time.monotonic() + args.timeout
    while time.monotonic() < deadline:
        reports.discover()
        heard_all = reports.latest and len(reports.latest) >= reports.topics
        if heard_all and time.monotonic() - reports.heard >= _SETTLE_S:
            break
        await asyncio.sleep(_DISCOVER_S)
    if not reports.latest:
        which = f"container {reports.only}" if reports.only else "any container"
        print(f"no load report from {which} within {args.timeout:g} s", file=sys.stderr)
        return 1
    loads = reports.loads()
    if args.json:
        print(json.dumps([as_dict(load) for load in loads], indent=2))
    else:
        print("\n\n".join(plain_table(load, sort=_SORT_NAMES[args.sort], node=args.node) for load in loads))
    return 0


def as_dict(message: Any) -> Any:
    """A ROS message as plain JSON-ready values (field names as the message's)."""
    if isinstance(message, list | tuple):
        return [as_dict(item) for item in message]
    fields = getattr(message, "get_fields_and_field_types", None)
    if fields is None:
        return message
    return {name: as_dict(getattr(message, name)) for name in fields()}


def _ms(seconds: float) -> str:
    """Milliseconds in at most 6 characters, 4 significant digits or so: 0.458, 20.89, 458.1, 12345."""
    ms = seconds * 1e3
    if ms < 10:
        return f"{ms:.3f}"
    if ms < 100:
        return f"{ms:.2f}"
    if ms < 1000:
        return f"{ms:.1f}"
    return f"{ms:.0f}"


#: What a shortened callback name may be at most, in characters (the full name is in ``--json``).
NAME_WIDTH = 40

#: Kinds of entity whose rclpy names say little (``eventhandler callback ...``), as a person says them.
_ENTITY_WORDS = {"eventhandler": "QoS event", "guardcondition": "guard condition", "waitable": "waitable"}


def short_name(name: str, *, width: int = NAME_WIDTH) -> str:
    """A callback's name as a person reads it, in at most ``width`` characters.

    rclpy's own callbacks have long generated names (``eventhandler callback
    PublisherEventCallbacks.create_event_handlers.<locals>._default_incompatible_qos_callback``):
    the word ``callback`` goes, the kinds of entity are said in words, a
    function's ``<locals>`` steps go (``Node.__init__.<locals>.tick`` reads
    ``Node.__init__.tick``) and a lambda is ``λ``. Still too long, step by
    step: the function keeps its first and last parts
    (``PublisherEventCallbacks…_on_matched``); a topic's or service's callback
    is its topic or service alone; the function is its own name alone, without
    a leading underscore or a ``_callback`` ending (``QoS event
    default_incompatible_qos``); what is left too long is cut in the middle.
    """
    head, sep, code = name.partition(" callback ")
    if not sep:
        return _cut(name, width)
    first, _, rest = head.partition(" ")
    head = " ".join(filter(None, (_ENTITY_WORDS.get(first, first), rest)))
    code = code.replace(".<locals>", "").replace("<lambda>", "λ")
    parts = code.split(".")

    def fits(candidate: str) -> bool:
        return len(head) + 1 + len(candidate) <= width

    if not fits(code) and len(parts) > 2:
        code = f"{parts[0]}…{parts[-1]}"
    if not fits(code) and "'" in head:
        return _cut(head, width)
    if not fits(code):
        code = parts[-1].lstrip("_").removesuffix("_callback") or parts[-1]
    return _cut(f"{head} {code}", width)


def _cut(text: str, width: int) -> str:
    if len(text) <= width:
        return text
    keep = width - 1
    return f"{text[: (keep + 1) // 2]}…{text[len(text) - keep // 2 :]}"


def _stuck(item: NodeLoad | CallbackLoad) -> str:
    if item.stuck_for > 0:
        return f"NOW {item.stuck_for:.1f}s"
    return str(item.stuck) if item.stuck else "-"


def _heading(load: ContainerLoad) -> str:
    return (
        f"container {load.container}  window {load.period:.2f} s  cpu {load.cpu * 100:.1f}%"
        f"  nodes {load.nodes_cpu * 100:.1f}%  executor {load.executor_cpu * 100:.1f}%"
        f"  unattributed {load.unattributed_cpu * 100:.1f}%  loop idle {load.loop_idle * 100:.1f}%"
    )


#: An unattributed kind below this share of a core is left out of its line.
_SHOWN_FROM = 0.0005


def _unattributed(load: ContainerLoad) -> str | None:
    """``unattributed: middleware threads 0.4%  python threads 0.1%``, or ``None`` when all are below 0.05%."""
    parts = [
        f"{item.kind} {item.cpu * 100:.1f}%"
        for item in sorted(load.unattributed, key=lambda item: -item.cpu)
        if item.cpu >= _SHOWN_FROM
    ]
    return f"unattributed: {'  '.join(parts)}" if parts else None


_NODE_COLUMNS = ("NODE", "CPU%", "CB/S", "LATE_P99_MS", "DUR_P99_MS", "DROPPED", "STUCK", "CPU_TOTAL_S")
#: Times in ms; p50s and the full names are in ``--json``. Fits 120 columns.
_CALLBACK_COLUMNS = (
    "CALLBACK", "GROUP", "CPU%", "CB/S", "LATE_P99", "LATE_MAX", "DUR_P99", "DUR_MAX", "DROP", "STUCK",
)


def _node_row(node: NodeLoad) -> list[str]:
    return [
        node.name, f"{node.cpu * 100:.1f}", f"{node.rate:.1f}", _ms(node.lateness_p99), _ms(node.duration_p99),
        str(node.dropped), _stuck(node), f"{node.cpu_seconds_total:.2f}",
    ]


def _callback_row(callback: CallbackLoad) -> list[str]:
    if callback.kind == "thread":  # CPU alone: no runs, no times
        times = ["-"] * 4
    else:
        times = [_ms(callback.lateness_p99), _ms(callback.lateness_max), _ms(callback.duration_p99),
                 _ms(callback.duration_max)]  # fmt: skip
    return [
        short_name(callback.name), callback.group, f"{callback.cpu * 100:.1f}", f"{callback.rate:.1f}", *times,
        str(callback.dropped), _stuck(callback),
    ]


def _columns(header: Sequence[str], rows: list[list[str]]) -> Iterator[str]:
    widths = [max(len(row[i]) for row in [list(header), *rows]) for i in range(len(header))]
    for row in [list(header), *rows]:
        # The name left-aligned, figures right-aligned.
        cells = [row[0].ljust(widths[0])] + [cell.rjust(width) for cell, width in zip(row[1:], widths[1:], strict=True)]
        yield "  ".join(cells).rstrip()


#: Below a node's callbacks: those left out.
_NEVER_RAN = "and {} callback(s) that never ran (--json lists every one)"


def _ran(callbacks: Sequence[CallbackLoad]) -> tuple[list[CallbackLoad], int]:
    """The callbacks that ever ran, took CPU or are stuck (a lifecycle node has some twenty of
    rclpy's own that an operator would scroll past), and how many others there are."""
    shown = [c for c in callbacks if c.runs_total or c.cpu_seconds_total or c.cpu or c.stuck_for]
    return shown, len(callbacks) - len(shown)


def _sorted(items: Sequence[Any], sort: str) -> list[Any]:
    return sorted(items, key=lambda item: (_SORTS[sort][1](item), item.name))


def plain_table(load: ContainerLoad, *, sort: str = "c", node: str | None = None) -> str:
    """One container's window as plain text: a heading, then a row per node (and ``node``'s callbacks)."""
    lines = [_heading(load)]
    unattributed = _unattributed(load)
    if unattributed is not None:
        lines.append(unattributed)
    lines += _columns(_NODE_COLUMNS, [_node_row(item) for item in _sorted(load.nodes, sort)])
    if node is not None:
        chosen = [item for item in load.nodes if item.name == node]
        lines.append("")
        if not chosen:
            lines.append(f"no node {node} in container {load.container}")
        else:
            lines.append(f"callbacks of {node} (times in ms)")
            shown, idle = _ran(chosen[0].callbacks)
            lines += _columns(_CALLBACK_COLUMNS, [_callback_row(c) for c in _sorted(shown, sort)])
            if idle:
                lines.append(_NEVER_RAN.format(idle))
    return "\n".join(lines)


# -- live ------------------------------------------------------------------------------
@dataclass
class _View:
    """What the live view shows: which container, sorted how, which row, opened or not."""

    sort: str = "c"
    container: int = 0
    selected: int = 0
    opened: str | None = None
    quit: bool = False

    def key(self, key: str, load: ContainerLoad | None, containers: int) -> None:
        rows = len(self._rows(load)) if load is not None else 0
        if key in ("q", "\x03"):
            self.quit = True
        elif key in _SORTS:
            self.sort = key
        elif key in ("j", "\x1b[B"):
            self.selected = min(self.selected + 1, max(0, rows - 1))
        elif key in ("k", "\x1b[A"):
            self.selected = max(0, self.selected - 1)
        elif key in ("\r", "\n", "\x1b[C") and self.opened is None and load is not None and rows:
            self.opened = self._rows(load)[self.selected].name
            self.selected = 0
        elif key in ("\x1b", "\x7f", "h", "\x1b[D"):
            self.opened, self.selected = None, 0
        elif key == "\t" and containers:
            self.container = (self.container + 1) % containers
            self.opened, self.selected = None, 0

    def _rows(self, load: ContainerLoad) -> list[Any]:
        if self.opened is None:
            return _sorted(load.nodes, self.sort)
        for node in load.nodes:
            if node.name == self.opened:
                return _sorted(_ran(node.callbacks)[0], self.sort)
        return []

    def render(
        self, loads: list[ContainerLoad], history: History | None = None, *, now: float | None = None
    ) -> RenderableType:
        """The screen: a container's heading and its nodes (or a node's callbacks), with each
        node's last minute from ``history`` (as of ``now``, monotonic seconds)."""
        from rich.console import Group
        from rich.table import Table
        from rich.text import Text

        keys = Text(
            "keys: c cpu  r rate  l lateness  d duration  n name  j/k or arrows move  enter open  "
            "esc back  tab next container  q quit",
            style="dim",
        )
        if not loads:
            return Group(Text("waiting for a container's load report..."), keys)
        self.container %= len(loads)
        load = loads[self.container]
        rows = self._rows(load)
        self.selected = min(self.selected, max(0, len(rows) - 1))
        title = f"{self.opened} (callbacks, times in ms)" if self.opened is not None else "nodes"
        columns = _CALLBACK_COLUMNS if self.opened is not None else _NODE_COLUMNS
        sparks = history is not None and self.opened is None
        if sparks:
            columns = (*columns, "CPU_LAST_MIN")
        now = time.monotonic() if now is None else now
        scale = history.peak(load.container) if history is not None else 0.0
        table = Table(title=title, expand=True)
        sorted_by = _SORTS[self.sort][0] or columns[0]
        names = 2 if self.opened is not None else 1  # left-aligned: the name (and the group)
        for index, column in enumerate(columns):
            mark = " *" if column == sorted_by else ""
            if index < names:  # names shrink (cut with an ellipsis); figures keep their width
                table.add_column(column + mark, no_wrap=True, overflow="ellipsis", ratio=3 if index == 0 else 1)
            elif column == "CPU_LAST_MIN":
                table.add_column(column, no_wrap=True, min_width=SPARK_WIDTH)
            else:
                table.add_column(column + mark, justify="right", no_wrap=True)
        for index, item in enumerate(rows):
            cells = _callback_row(item) if self.opened is not None else _node_row(item)
            if sparks and history is not None:
                cells.append(history.spark(load.container, item.name, now, scale=scale))
            style = "reverse" if index == self.selected else ("bold red" if item.stuck_for > 0 else None)
            table.add_row(*cells, style=style)
        if self.opened is not None:
            idle = sum(_ran(node.callbacks)[1] for node in load.nodes if node.name == self.opened)
            if idle:
                table.caption = _NEVER_RAN.format(idle)
        heading = _heading(load) + (f"   [{self.container + 1}/{len(loads)}]" if len(loads) > 1 else "")
        unattributed = _unattributed(load)
        if unattributed is not None:
            heading += f"\n{unattributed}"
        return Group(Text(heading), table, keys)


@contextlib.contextmanager
def _keys(on_key: Callable[[str], None]) -> Iterator[None]:
    """Read keys from a terminal without echo or line buffering, on the running loop."""
    if not sys.stdin.isatty():
        yield
        return
    import termios
    import tty

    fd = sys.stdin.fileno()
    saved = termios.tcgetattr(fd)
    loop = asyncio.get_running_loop()

    def read() -> None:
        data = os.read(fd, 16).decode(errors="replace")
        if data.startswith("\x1b[") and len(data) >= 3:
            on_key(data[:3])
        else:
            for char in data:
                on_key(char)

    tty.setcbreak(fd)
    loop.add_reader(fd, read)
    try:
        yield
    finally:
        loop.remove_reader(fd)
        termios.tcsetattr(fd, termios.TCSADRAIN, saved)


async def _live(reports: _Reports, args: argparse.Namespace, stopping: asyncio.Event) -> int:
    from rich.console import Console
    from rich.live import Live

    view = _View(sort=_SORT_NAMES[args.sort])
    console = Console()

    def on_key(key: str) -> None:
        current = reports.loads()
        view.key(key, current[view.container % len(current)] if current else None, len(current))
        reports.changed.set()

    with _keys(on_key), Live(view.render([]), console=console, auto_refresh=False, screen=console.is_terminal) as live:
        next_discovery = 0.0
        while not view.quit and not stopping.is_set():
            if time.monotonic() >= next_discovery:
                reports.discover()
                next_discovery = time.monotonic() + 1.0
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(reports.changed.wait(), timeout=1.0)
            reports.changed.clear()
            live.update(view.render(reports.loads(), reports.history), refresh=True)
    return 0
