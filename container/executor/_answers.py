"""Sending a service's answer without waiting on the event loop for a client that may never match.

Fast DDS's rmw (``__rmw_send_response``, rmw_fastrtps_shared_cpp) waits, in
every send, for the client's response reader to match the service's
response writer, up to the writer's blocking time (100 ms), and gives up
with "client will not receive response" (``RCL_RET_TIMEOUT``). A client
matched once is never waited for again: rmw's wait returns at once for a
matched reader, and for a reader gone since (its client is "gone": the
answer is dropped, successfully). Two kinds of clients make it wait:

- one that has just discovered the service (``wait_for_service``
  returned) and calls before the service matched its response reader
  (``ros2 component load`` right after a container starts): a few
  milliseconds, or a retry later;
- one whose response reader can never match (an incompatible QoS, such as
  a transient-local response reader against the volatile writer; on
  purpose or not): every send of every answer to it waits the whole
  100 ms. Inline on the loop, that was 100 ms of the whole process per
  request (the GIL held).

So answers are sent per client, keyed by the GUID in the request header
(Fast DDS puts the client's response reader's there, the one rmw waits for;
the compiled engine's header is the bytes of ``rmw_request_id_t``, rclpy's
header has it read by ``_compat.request_client``):

- to a client known to be matched, inline, wherever the callback ran: rmw
  does not wait. Known: an answer to it went through, or (its first answer)
  the node's graph knows its response reader on the service's response
  topic, with a QoS every writer there offers (:func:`_in_graph`: tens of
  microseconds, once per client; so a well-formed client's first answer
  goes out at once, even when its service is destroyed right after);
- to a client not known yet, from the resender thread (``respond-again``):
  the compiled send (``Server.send(..., let_go=True)``) lets go of the GIL
  while rmw waits, tried again every :data:`RETRY_EVERY_S`; its first
  answer that goes through makes the client known, and its other answers
  wait for it in the thread meanwhile;
- to a client whose response reader did not match in :data:`RETRY_S`
  seconds: its waiting answers are dropped, with one log line for that
  client (never another for it), and so are its later answers, at once,
  for :data:`GIVEN_UP_S` seconds; after that its next answer is tried again.

What is remembered is bounded: :data:`MAX_CLIENTS` clients known matched
and as many waiting or given up on (the oldest forgotten first: a forgotten
client's next answer goes through the thread once more), and
:data:`MAX_WAITING` answers waiting in the thread (more are dropped, said
once per client). A client is remembered by its service weakly, and holds
the service (and the node its answers need) only while answers wait: an
unloaded node goes, whoever its clients were.

rclpy's send (``send_response``, for a service the compiled path cannot
serve; the Python engine's ``Server``) keeps the GIL while rmw waits: there
each unmatched try would stall the process up to 100 ms, so the resender
tries such a send only once the graph shows the client's response reader
compatible (:func:`_in_graph`, every :data:`RETRY_EVERY_S`); an
incompatible client is never tried, and costs nothing. Should a try still
find the client unmatched (a reader the graph shows compatible that DDS
does not match), the next is :data:`HOLDING_EVERY_S` later.

Where a header's GUID cannot be read (a binding this does not know), a
service's answers are sent inline until one finds its client unmatched
(that send stalls the process up to 100 ms); from then on, for
:data:`SUSPECT_S` seconds, they go to the resender, which tries them in
turn, one unmatched try per :data:`HOLDING_EVERY_S` seconds, each answer
until :data:`RETRY_S` (one log line per service). rclpy reports an
unmatched client by a ``RuntimeWarning`` from C++, which a caller cannot
catch, so exactly that warning is made an error for the whole process
(``_compat.raise_client_not_matched``; ``_compat.client_not_matched``
recognises it, and the Python engine's ``Server`` with it).

Answers that waited in the resender leave it at most one per
:data:`PACE_S` for each service: a client is given every answer of its
service, and rclpy's default keeps only the last 10 it has not taken.

The resender ends after :data:`IDLE_S` seconds with nothing to send, and
:func:`end_resender` ends it at once (a session ending: the container's
own thread is not a plugin's leak).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
import weakref
from typing import Any

from rclpy.exceptions import InvalidHandle
from rclpy.node import Node
from rclpy.qos import QoSCompatibility, qos_check_compatible

from .._compat import client_not_matched, raise_client_not_matched, request_client
from . import _engine
from ._engine import Server
from ._owners import executor_work

__all__ = ["end_resender", "respond", "waiting_for"]

_log = logging.getLogger(__name__)

#: How long a client's response reader may take to match before its answers are dropped.
RETRY_S = 3.0
#: Between two tries of an unmatched client (each try waits up to 100 ms in rmw, GIL let go).
RETRY_EVERY_S = 0.05
#: Between two unmatched tries of a service answered through rclpy (each holds the GIL up to 100 ms).
HOLDING_EVERY_S = 1.0
#: How long a client given up on has its answers dropped at once.
GIVEN_UP_S = 30.0
#: How long a service answered through rclpy sends its answers from the resender after an unmatched one.
SUSPECT_S = 30.0
#: Answers waiting in the resender at most; more are dropped. Clients not
#: discovered yet are legitimate callers too: a burst of 500 requests from five
#: new clients once waited here, and a bound of 256 dropped answers they awaited.
MAX_WAITING = 4096
#: Between two answers the resender sends for one service. DDS delivers every
#: answer of a service to every client of it, and a client with rclpy's default
#: QoS keeps only the last 10 it has not taken (rclcpp#2397): answers queued
#: while their clients were being discovered, sent back to back, pushed most of
#: them out (50 of 500 arrived). Paced, a client has 10 of these to take each.
PACE_S = 0.01
#: Clients remembered at most, matched ones and given-up ones each.
MAX_CLIENTS = 1024
#: The resender ends after this long with nothing to send.
IDLE_S = 3.0
#: The size of a GUID, the first bytes of the compiled engine's header (``rmw_request_id_t``).
_GUID_SIZE = 16

#: A client of one service: the service weakly (an unloaded node's services, and
#: the node their callbacks hold, are not kept alive by what is remembered here),
#: and the GUID its headers name.
_Key = tuple["weakref.ref[Any]", bytes | None]

#: Clients known to be matched, oldest first.
_matched: dict[_Key, None] = {}


def respond(srv: Any, response: Any, header: Any, *, server: Server | None = None, node: Node | None = None) -> None:
    """Send ``response`` to the client ``header`` names: inline if it is known to be
    matched, else through the resender (module docstring).

    ``server``: the service's compiled answers, which ``header`` came from
    (``None``: rclpy's ``send_response``, with rclpy's header). ``node``: the
    service's, whose graph may know the client's response reader.
    """
    guid = header[:_GUID_SIZE] if isinstance(header, bytes) else request_client(header)
    key = (weakref.ref(srv), guid)
    if guid is not None:
        if key in _matched or (not _resender.knows(key) and node is not None and _in_graph(node, srv, guid)):
            if _sent(srv, server, response, header):
                _resender.matched(key)
                return
            _resender.unmatched(key)  # rmw waited: not matched after all
        _resender.add(key, srv, server, response, header, node=node)
    elif _resender.suspect(key):
        _resender.add(key, srv, server, response, header, node=node)
    elif not _sent(srv, server, response, header):
        _resender.add(key, srv, server, response, header, tried=True, node=node)


def _in_graph(node: Node, srv: Any, guid: bytes) -> bool:
    """Whether the graph knows the response reader ``guid`` on the service's reply
    topic, with a QoS every writer there offers (so it matched, or is about to).

    A first answer to a client not known yet: ``ros2 service call`` and every
    new client (tens of microseconds). Where the graph does not say so (not
    discovered yet, an incompatible QoS, the service or its node destroyed
    meanwhile), the resender sends it.
    """
    try:
        return _graph_knows(node, srv, guid)
    except InvalidHandle:
        return False


def _graph_knows(node: Node, srv: Any, guid: bytes) -> bool:
    """:func:`_in_graph`, raising rclpy's ``InvalidHandle`` for a service or node destroyed."""
    with srv.handle:
        topic = f"rr{srv.handle.name}Reply"  # rmw's name for the service's response topic
    readers = node.get_subscriptions_info_by_topic(topic, no_mangle=True)
    reader = next((info for info in readers if bytes(info.endpoint_gid[:_GUID_SIZE]) == guid), None)
    if reader is None:
        return False
    writers = node.get_publishers_info_by_topic(topic, no_mangle=True)
    return bool(writers) and all(
        info.topic_type == reader.topic_type
        and qos_check_compatible(info.qos_profile, reader.qos_profile)[0] == QoSCompatibility.OK
        for info in writers
    )


def end_resender(*, timeout: float) -> None:
    """End the resender thread now, dropping the answers it holds; wait up to ``timeout`` for it.

    A process about to exit, or to count the threads it left behind, calls it.
    """
    _resender.end(timeout=timeout)


def waiting_for(node: Node) -> int:
    """How many answers of ``node``'s services wait in the resender for their clients.

    An unload waits for them before it destroys the node (see
    ``AsyncioExecutor.retire``): a destroyed service's waiting answers are
    dropped, and a caller whose response reader was still being discovered
    when its answer was ready (a ``change_state`` that the unload cancelled)
    was left waiting for good.
    """
    return _resender.waiting_for(node)


def _sent(srv: Any, server: Server | None, response: Any, header: Any, *, let_go: bool = False) -> bool:
    """Send once; ``False`` when the client's response reader is not matched (yet).

    ``let_go``: the compiled send lets go of the GIL while rmw waits for
    the client (the resender thread: every other thread runs meanwhile).
    """
    if server is not None:
        # Entered: a service destroyed meanwhile raises InvalidHandle here (the
        # server's own hold only defers its destruction).
        with srv.handle:
            return server.send(response, header, let_go)
    try:
        srv.send_response(response, header)
    except Exception as error:
        if client_not_matched(error):
            return False
        raise
    return True


def _remember_matched(key: _Key) -> None:
    """Changed only under the resender's lock; read without it (respond's one lookup)."""
    _matched[key] = None
    while len(_matched) > MAX_CLIENTS:
        del _matched[next(iter(_matched))]


class _Client:
    """The answers waiting for one client (``guid``), or for one service's clients
    whose headers name none (``guid`` ``None``)."""

    __slots__ = (
        "answers", "dropped", "given_up_at", "guid", "key", "logged", "name", "next_try", "node", "server", "srv",
        "stalled", "until",
    )  # fmt: skip

    def __init__(self, key: _Key, srv: Any, server: Server | None, node: Node | None) -> None:
        self.key = key
        #: Held while answers wait (then let go: :meth:`let_go`).
        self.srv: Any = srv
        self.server = server
        self.node = node
        self.name = str(getattr(srv, "srv_name", srv))
        self.guid = key[1]
        #: ``(deadline, response, header)``, oldest first.
        self.answers: collections.deque[tuple[float, Any, Any]] = collections.deque()
        self.next_try = 0.0
        self.given_up_at: float | None = None
        #: The last try held the GIL while rmw waited (the next one waits :data:`HOLDING_EVERY_S`).
        self.stalled = False
        #: A service without GUIDs: its answers go to the resender until then.
        self.until = 0.0
        self.dropped = 0
        self.logged = False

    def describe(self) -> str:
        if self.guid is None:
            return f"service {self.name}"
        return f"service {self.name}: client {self.guid.hex()}"

    def hold(self, srv: Any, server: Server | None, node: Node | None) -> None:
        """Hold what the next answer is sent with (given again with each answer)."""
        self.srv, self.server, self.node = srv, server, node

    def let_go(self) -> None:
        """Nothing waits: keep only what decides about later answers, not the service."""
        self.srv = self.server = self.node = None


class _Resender:
    """One thread that sends the answers of clients not known to be matched."""

    def __init__(self) -> None:
        self._wake = threading.Condition()
        #: Clients with answers waiting, given up on, or suspect: oldest first.
        self._clients: dict[_Key, _Client] = {}
        self._waiting = 0
        self._thread: threading.Thread | None = None
        self._ending = False
        #: Answers dropped, in all (tests and the curious read it).
        self.dropped = 0
        #: When the resender may next send for a service (:data:`PACE_S`), by service.
        self._paced: dict[weakref.ref[Any], float] = {}

    def knows(self, key: _Key) -> bool:
        """Whether answers to that client wait here, or it was given up on."""
        return key in self._clients

    def waiting_for(self, node: Node) -> int:
        """:func:`waiting_for`."""
        with self._wake:
            # A client holds its node while answers wait for it, and only then (``let_go``).
            return sum(len(client.answers) for client in self._clients.values() if client.node is node)

    def matched(self, key: _Key) -> None:
        """Remember that an answer to that client went through: its next ones go inline."""
        if key not in _matched:
            with self._wake:
                _remember_matched(key)

    def unmatched(self, key: _Key) -> None:
        """Forget that a client was matched (its send waited after all)."""
        with self._wake:
            _matched.pop(key, None)

    def suspect(self, key: _Key) -> bool:
        """Whether a service whose headers name no client sends its answers from the resender now."""
        client = self._clients.get(key)
        return client is not None and client.until > time.monotonic()

    def add(
        self, key: _Key, srv: Any, server: Server | None, response: Any, header: Any,
        *, tried: bool = False, node: Node | None = None,
    ) -> None:
        """Hand an answer over; ``tried``: it was just found unmatched (a service without GUIDs).
        ``node``: the service's, whose graph tells a try that holds the GIL whether it can succeed."""
        now = time.monotonic()
        with self._wake:
            client = self._clients.get(key)
            if client is None:
                client = self._clients[key] = _Client(key, srv, server, node)
                self._forget_oldest()
            else:
                client.hold(srv, server, node)
            if client.guid is None and tried:
                client.until = now + SUSPECT_S
                client.next_try = now + HOLDING_EVERY_S
            if client.given_up_at is not None:
                if now < client.given_up_at + GIVEN_UP_S:
                    self._count_dropped(client, 1)
                    return
                client.given_up_at = None
            if self._waiting >= MAX_WAITING:
                self._count_dropped(client, 1)
                if not client.logged:
                    client.logged = True
                    _log.warning(
                        "%s: %d answers already wait for their clients to match; its answers are dropped",
                        client.describe(), self._waiting,
                    )
                return
            client.answers.append((now + RETRY_S, response, header))
            self._waiting += 1
            if self._thread is None:
                self._ending = False
                self._thread = threading.Thread(target=self._run, name="respond-again", daemon=True)
                with executor_work():
                    self._thread.start()
            self._wake.notify()

    def end(self, *, timeout: float) -> None:
        with self._wake:
            thread = self._thread
            self._ending = True
            for client in self._clients.values():
                self._drop_waiting(client)
            self._wake.notify()
        if thread is not None:
            thread.join(timeout)

    def _forget_oldest(self) -> None:
        """Keep at most :data:`MAX_CLIENTS`: the oldest is forgotten, its answers dropped."""
        while len(self._clients) > MAX_CLIENTS:
            self._drop_waiting(self._clients.pop(next(iter(self._clients))))

    def _count_dropped(self, client: _Client, count: int) -> None:
        client.dropped += count
        self.dropped += count

    def _drop_waiting(self, client: _Client) -> int:
        """Drop every answer waiting for ``client``; how many there were."""
        count = len(client.answers)
        client.answers.clear()
        client.let_go()
        self._waiting -= count
        self._count_dropped(client, count)
        return count

    def _next(self, now: float) -> tuple[_Client | None, float]:
        """The client whose head answer is due now (untried ones first), or how long until one is."""
        due: _Client | None = None
        soonest = IDLE_S
        for client in self._clients.values():
            if not client.answers:
                continue
            wait = max(client.next_try, self._paced.get(client.key[0], 0.0)) - now
            if wait <= 0:
                if due is None or client.next_try < due.next_try:
                    due = client
            else:
                soonest = min(soonest, wait)
        return due, soonest

    def _run(self) -> None:
        idle_since = time.monotonic()
        while True:
            with self._wake:
                now = time.monotonic()
                self._expire(now)
                client, wait = None, IDLE_S
                if not self._ending:
                    client, wait = self._next(now)
                if client is None:
                    if self._ending or (self._waiting == 0 and now - idle_since >= IDLE_S):
                        self._thread = None
                        return
                    self._wake.wait(wait)
                    continue
                entry = client.answers[0]
                holding = (client.srv, client.server, client.node)
            outcome = self._try(client, entry, *holding)
            # Not held past the try: the last exit of a service destroyed
            # meanwhile destroys it, under the GIL (Fast DDS deletes its
            # endpoints: 200-300 ms of the whole process on a busy machine).
            # Held by this frame, that was whenever the next answer came,
            # seconds later, in the middle of other nodes' work.
            del holding
            with self._wake:
                now = idle_since = time.monotonic()
                if not client.answers or client.answers[0] is not entry:
                    continue  # dropped meanwhile (the end, or forgotten)
                if outcome is None:  # unmatched
                    client.next_try = now + (HOLDING_EVERY_S if client.stalled else RETRY_EVERY_S)
                    if client.guid is None:
                        client.answers.rotate(-1)  # the others may be other clients'
                    continue
                client.answers.popleft()
                self._waiting -= 1
                if outcome:
                    self._pace(client.key[0], now)
                if not client.answers:
                    client.let_go()
                if outcome and client.guid is not None:
                    _remember_matched(client.key)
                    if not client.answers:
                        self._clients.pop(client.key, None)

    def _pace(self, service: weakref.ref[Any], now: float) -> None:
        """The next answer for ``service`` no sooner than :data:`PACE_S` from ``now``."""
        self._paced[service] = now + PACE_S
        if len(self._paced) > MAX_CLIENTS:
            for key in [key for key, at in self._paced.items() if at <= now]:
                del self._paced[key]

    def _expire(self, now: float) -> None:
        """Drop the answers past their deadline: a client with a GUID is given up on
        (one log line, the first time), a service without is said once."""
        for client in list(self._clients.values()):
            if not client.answers:
                if client.given_up_at is None and client.until <= now:
                    self._clients.pop(client.key, None)  # nothing to remember
                continue
            if client.answers[0][0] > now:
                continue
            if client.guid is not None:
                count = self._drop_waiting(client)
                client.given_up_at = now
            else:
                count = 0
                while client.answers and client.answers[0][0] <= now:
                    client.answers.popleft()
                    count += 1
                if not client.answers:
                    client.let_go()
                self._waiting -= count
                self._count_dropped(client, count)
            if client.logged:
                continue
            client.logged = True
            if client.guid is not None:
                _log.warning(
                    "%s: its response reader did not match in %.1f s (an incompatible QoS?): "
                    "dropped %d answer(s), and will drop its answers for %.0f s",
                    client.describe(), RETRY_S, count, GIVEN_UP_S,
                )
            else:
                _log.warning(
                    "%s: a client's response reader did not match in %.1f s (an incompatible QoS?): "
                    "dropped %d answer(s), and will drop more without another line",
                    client.describe(), RETRY_S, count,
                )

    @staticmethod
    def _try(
        client: _Client, entry: tuple[float, Any, Any], srv: Any, server: Server | None, node: Node | None
    ) -> bool | None:
        """Try once: ``True`` sent, ``None`` unmatched, ``False`` done with it otherwise.

        A send that would hold the GIL while rmw waits is tried only once the
        graph knows the client's response reader with a compatible QoS: an
        incompatible client then costs no stall at all.
        """
        _, response, header = entry
        holds_gil = server is None or _engine.ENGINE != "compiled"
        try:
            if holds_gil and node is not None and client.guid is not None and not _graph_knows(node, srv, client.guid):
                client.stalled = False
                return None
            client.stalled = holds_gil
            if _sent(srv, server, response, header, let_go=True):
                return True
        except InvalidHandle:
            return False  # the service is gone, and its client's wait with it
        except Exception as error:
            _log.warning("%s: an answer was not sent (%s)", client.describe(), error)
            return False
        return None


# rclpy reports an unmatched client as a warning, which only an error lets _sent see.
raise_client_not_matched()
_resender = _Resender()
